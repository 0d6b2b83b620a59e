"""Build the shipped ``data/pickles_templates.csv``: colour indices of each Pickles template.

Each solar-metallicity Pickles template gets the median catalog colour of the stars whose MK type
maps to it (:func:`ground.catalog.colour.match_template`, at least ``MIN_STARS`` stars):

* ``bv``: Yale BSC5 B-V of the BSC5 stars of that type;
* ``vi``: Hipparcos V-I of the Hipparcos stars (V <= 7) that borrow that type from the BSC5 star
  within 10 arcsec and 0.5 mag (:func:`ground.catalog.build.borrow_mk_types`).

So the lookups of :class:`ColourModel` are calibrated on the same colour scales they are applied
to. The colour ratios of every template for each shipped QE model (``QE_MODELS``) let the lookups
work on machines without the spectra. Run:

    python tools/fit_pickles_bv.py /work/shared/data/bsc5/catalog.dat /work/shared/data/pickles
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ground.atomic_write import write_text
from ground.catalog.build import borrow_mk_types
from ground.catalog.colour import (
    QE_MODELS,
    ColourModel,
    match_template,
    parse_mk,
    photon_signals,
    pickles_templates,
    ratios_from_signals,
    read_sed,
    shipped_qe,
)
from ground.catalog.sources import read_bsc5, read_hipparcos

OUT = Path(__file__).resolve().parents[1] / "ground" / "catalog" / "data" / "pickles_templates.csv"
MIN_STARS = 3
HIP_V_LIMIT = 7.0


def median_by_template(sptypes, values, templates) -> dict[str, tuple[float, int]]:
    """Template -> (median value, number of stars) over stars with a finite value and a usable type."""
    groups: dict[str, list[float]] = {}
    for sp, x in zip(sptypes, values):
        mk = parse_mk(sp) if sp and np.isfinite(x) else None
        name = match_template(mk, templates) if mk else None
        if name:
            groups.setdefault(name, []).append(x)
    return {n: (float(np.median(v)), len(v)) for n, v in groups.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bsc5", type=Path)
    parser.add_argument("pickles_dir", type=Path)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    templates = pickles_templates(args.pickles_dir)
    bsc = read_bsc5(args.bsc5)
    bvs = median_by_template(bsc.sptype, bsc.bv, templates)
    hip = read_hipparcos(epoch=2000.0)
    hip, _ = borrow_mk_types(hip.subset(hip.vmag <= HIP_V_LIMIT), args.bsc5, 2000.0)
    vis = median_by_template(hip.sptype, hip.vi, templates)
    qes = [shipped_qe(name) for name in QE_MODELS]
    lines = [
        "# Pickles (1998) solar-metallicity templates: median Yale BSC5 B-V and median Hipparcos V-I of the stars",
        f"# whose MK type maps to each (blank if fewer than {MIN_STARS}); Lambda_rg/Lambda_bg per shipped QE model.",
        "# Made by tools/fit_pickles_bv.py.",
        "template,bv,n_bv,vi,n_vi," + ",".join(f"rg_{q.name},bg_{q.name}" for q in qes),
    ]
    for name in sorted(templates):
        bv, nb = bvs.get(name, (np.nan, 0))
        vi, nv = vis.get(name, (np.nan, 0))
        sed = read_sed(args.pickles_dir / f"{name}.sed")
        ratios = [ratios_from_signals(photon_signals(qe, *sed)) for qe in qes]
        bv_text = f"{bv:.3f}" if nb >= MIN_STARS else ""
        vi_text = f"{vi:.3f}" if nv >= MIN_STARS else ""
        lines.append(f"{name},{bv_text},{nb},{vi_text},{nv}," + ",".join(f"{rg:.6f},{bg:.6f}" for rg, bg in ratios))
    write_text(args.out, "\n".join(lines) + "\n")
    for qe in qes:
        model = ColourModel(qe=qe, pickles_dir=args.pickles_dir)
        for lk in (model.bv_lookup, model.vi_lookup):
            print(
                f"{qe.name} {lk.index} lookup: range {lk.lo:.3f} .. {lk.hi:.3f}, "
                f"rms ln(rg) {lk.rms_ln[0]:.4f}, ln(bg) {lk.rms_ln[1]:.4f}"
            )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
