"""Build an on-board catalog from a :class:`CatalogDesign`: source -> selection -> colour -> pairs.

Stars are ordered by right ascension (Dong et al. sec. 1.2): the pattern stars (``V <= m_thresh``,
and the fainter ones :func:`promote_sparse` adds where the sky is sparse) first, then the
verification-only stars (``V <= m_verify``), which have no pairs. Per-star provenance (colour source,
Pickles template), the selection counts and the BSC5 MK cross-match report go into ``OnboardCatalog.meta``.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from firmware_model.catalog.onboard import OnboardCatalog, chord_of_angle
from ground.catalog.colour import SHARED_DATA, ColourModel, ColourSource, load_qe, parse_mk
from ground.catalog.design import CatalogDesign, DesignError
from ground.catalog.mk_crossmatch import MkCrossMatch, cross_match_mk
from ground.catalog.sources import StarTable, read_bsc5, read_hipparcos, select_stars

DEFAULT_BSC5 = SHARED_DATA / "bsc5" / "catalog.dat"


def load_source(design: CatalogDesign) -> StarTable:
    """The design's source catalog with positions at the design epoch."""
    if design.source == "hipparcos":
        return read_hipparcos(design.source_path, epoch=design.epoch)
    path = Path(design.source_path) if design.source_path else DEFAULT_BSC5
    if not path.is_file():
        raise DesignError(f"source_path = {str(path)!r}: BSC5 catalog.dat not found")
    return read_bsc5(path, epoch=design.epoch)


def borrow_mk_types(sel: StarTable, bsc5_path: str | Path, epoch: float) -> tuple[StarTable, MkCrossMatch]:
    """Give the stars without an MK type the parseable type of their one-to-one BSC5 match
    (:func:`~ground.catalog.mk_crossmatch.cross_match_mk`: within 10 arcsec and 0.5 mag);
    returns the updated table and the cross-match report."""
    path = Path(bsc5_path)
    if not path.is_file():
        raise DesignError(f"mk_types_path = {str(path)!r}: BSC5 catalog.dat not found")
    bsc = read_bsc5(path, epoch=epoch)
    untyped = np.flatnonzero(sel.sptype == "")
    row, report = cross_match_mk(sel.subset(untyped), bsc)
    types = np.where(row >= 0, bsc.sptype[row], "")
    usable = np.array([parse_mk(t) is not None for t in types], dtype=bool)
    sptype = sel.sptype.copy()
    sptype[untyped[usable]] = types[usable]
    return replace(sel, sptype=sptype), report


def promote_sparse(vec: np.ndarray, vmag: np.ndarray, pattern: np.ndarray, radius: float, per_cap: int) -> np.ndarray:
    """Stars below the pattern limit that become pattern stars where the sky is sparse: brightest
    first, each star with fewer than ``per_cap`` pattern stars (those promoted before it included)
    within ``radius`` (rad) of it, as plate solvers keep the N brightest stars of every region
    (tetra3's database). Returns the mask of promoted stars; none when ``per_cap`` is 0."""
    promoted = np.zeros(len(vec), bool)
    if per_cap <= 0:
        return promoted
    is_pattern = pattern.copy()
    candidates = np.flatnonzero(~pattern)
    candidates = candidates[np.argsort(vmag[candidates], kind="stable")]
    near = cKDTree(vec).query_ball_point(vec[candidates], chord_of_angle(radius))
    for c, n in zip(candidates, near):
        if np.count_nonzero(is_pattern[n]) < per_cap:
            is_pattern[c] = promoted[c] = True
    return promoted


def colour_model(design: CatalogDesign) -> ColourModel:
    """The design's detector colour model (a shipped model or CSV named by ``qe_path``; default
    the MT9P031-like model)."""
    qe = load_qe(design.qe_path)
    return ColourModel(qe=qe, pickles_dir=Path(design.pickles_dir)) if design.pickles_dir else ColourModel(qe=qe)


def colour_source_counts(src: np.ndarray) -> dict[str, int]:
    """Stars per :class:`ColourSource` name."""
    return {s.name: int((src == s).sum()) for s in ColourSource}


def build_catalog(
    design: CatalogDesign, source: StarTable | None = None, colours: ColourModel | None = None
) -> OnboardCatalog:
    """Select stars, compute colour ratios and build the pair table with both indices.

    ``source``/``colours`` may be passed to reuse already loaded data (e.g. in sweeps).
    """
    t0 = time.perf_counter()
    table = source if source is not None else load_source(design)
    if table.epoch != design.epoch:
        table = table.at_epoch(design.epoch)
    sel, stats = select_stars(table, design.m_verify_limit, design.resolve_angle, design.drop_variable)
    pattern = sel.vmag <= design.m_thresh
    if int(pattern.sum()) < 2:
        raise DesignError(f"m_thresh = {design.m_thresh}: only {int(pattern.sum())} star(s) selected")
    promoted = promote_sparse(sel.vec, sel.vmag, pattern, design.theta_fov, design.min_pattern_stars)
    pattern |= promoted
    n_pattern = int(pattern.sum())
    sel = sel.subset(np.concatenate([np.flatnonzero(pattern), np.flatnonzero(~pattern)]))
    stats["selected"], stats["promoted_sparse"] = n_pattern, int(promoted.sum())
    stats["verification_only"] = len(sel) - n_pattern
    crossmatch = None
    if design.mk_types_path:
        sel, report = borrow_mk_types(sel, design.mk_types_path, design.epoch)
        stats["mk_types_borrowed"], crossmatch = report.borrowed, report.summary()
    colours = colours or colour_model(design)
    rg, bg, src, tmpl = colours.star_ratios(sel.sptype, sel.bv, sel.vi)
    meta = {
        "design": design.to_dict(),
        "source": sel.source,
        "epoch": design.epoch,
        "selection": stats,
        "qe": colours.qe.name,
        "colour_source": src,
        "colour_source_counts": colour_source_counts(src),
        "colour_source_split": {
            "pattern": colour_source_counts(src[:n_pattern]),
            "verification_only": colour_source_counts(src[n_pattern:]),
        },
        "mk_crossmatch": crossmatch,
        "template": tmpl,
        "bv": sel.bv,
        "variable": sel.variable,
        "delta_star": design.delta_star,
        "sigma_phi": design.sigma_phi,
    }
    cat = OnboardCatalog.build(
        sel.star_id,
        sel.vec,
        sel.vmag,
        rg,
        bg,
        phi_min=design.phi_min,
        phi_max=design.phi_max,
        n_h=design.n_h,
        dphi_star=design.dphi_star,
        meta=meta,
        n_pattern_stars=n_pattern,
    )
    cat.meta["build_seconds"] = time.perf_counter() - t0
    return cat


def summary(cat: OnboardCatalog) -> dict:
    """Plain-JSON summary of a built catalog (counts, parameters, colour provenance)."""
    return {
        "source": cat.meta.get("source"),
        "epoch": cat.meta.get("epoch"),
        "n_stars": cat.n_stars,
        "n_pattern_stars": cat.n_pattern_stars,
        "n_pairs": cat.n_pairs,
        "phi_min_deg": round(float(np.degrees(cat.phi_min)), 9),
        "phi_max_deg": round(float(np.degrees(cat.phi_max)), 9),
        "n_h": cat.n_h,
        "dphi_star_deg": round(float(np.degrees(cat.dphi_star)), 9),
        "selection": cat.meta.get("selection"),
        "colour_source_counts": cat.meta.get("colour_source_counts"),
        "colour_source_split": cat.meta.get("colour_source_split"),
        "mk_crossmatch": cat.meta.get("mk_crossmatch"),
        "qe": cat.meta.get("qe"),
        "build_seconds": round(cat.meta.get("build_seconds", float("nan")), 3),
    }
