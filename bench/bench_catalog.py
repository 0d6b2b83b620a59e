"""Catalog benchmarks: Dong et al. counts, Enright & McVittie table 1 (BSC5 and Hipparcos), build and upload times.

Prints figures only (no asserts):

1. Dong et al.: guide stars with V <= 5.0 and pairs with 0.05 deg <= theta <= 24.5 deg, against the
   paper's 1631 stars and 65 890 pairs (SKY2000).
2. Enright & McVittie table 1, every row, built from the Yale BSC5 (as in the paper) and from Hipparcos,
   next to the paper's numbers; N views on the generalized spiral (1e5 as in the paper).
3. Table 1 against its own definition (BSC5, the paper's catalog; issue 32): the template floor
   (perfect colours, every QE model; the stars spread evenly over 91-131 spectra), the colour
   spread the paper's ambiguity would take (per-star jitter on row 1; random colours on every row,
   2-D and on a 1-D locus), the monochrome unresolvable views a two-star view alone forces, and the
   pairs a wider field shares with a narrower one.
4. Colour fallbacks (B-V / V-I lookups, blackbody) against the Pickles-by-MK-type ratios.
5. Build time of the default catalog (Hipparcos, M 5.0, theta_FOV 7.5 deg) and of table 1's
   largest row, against a baseline measured in the same run: reading the source catalog alone.
6. Upload time of the default catalog image to an in-process device paced at 115 200 baud over a
   pty, against the line-rate minimum (10 bits per payload byte).

Usage: .venv/bin/python bench/bench_catalog.py [--views 100000] [--skip-upload] [--out DIR]
           [--checks-only] [--seeds 5]   (--checks-only: item 3 alone, ~1 min)
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from firmware_model.catalog.image_io import catalog_to_image
from firmware_model.catalog.onboard import angle_between
from firmware_model.device.catalog_slot import catalog_slot_handler
from firmware_model.device.device import Device
from firmware_model.device.link import PtyLink, serve
from ground.catalog.analyze import (
    TABLE_HEADER,
    ambiguous_pairs,
    analyze,
    even_template_floor,
    field_nesting,
    jittered_colour_ambiguity,
    plot_views,
    solve_decreasing,
    spiral_points,
    synthetic_colour_ambiguity,
    table_row,
    template_floor,
    two_star_views,
)
from ground.catalog.build import DEFAULT_BSC5, borrow_mk_types, build_catalog, load_source
from ground.catalog.colour import QE_MODELS, ColourModel, ColourSource, ballesteros_temperature, blackbody_ratios
from ground.catalog.design import CatalogDesign
from ground.catalog.sources import read_hipparcos, select_stars
from ground.link.client import Client

#: Enright & McVittie table 1: (M_thresh, theta_FOV, sigma_pix, sigma_colour, pairs e3, bad %, amb %, unres, mono amb %, mono unres)
PAPER_TABLE1 = [
    (4.5, 7.5, 0.200, 0.020, 7.8, 15.92, 0.26, 0, 99.77, 44),
    (4.5, 7.5, 0.408, 0.020, 7.8, 15.92, 0.84, 0, 99.99, 187),
    (4.5, 7.5, 0.408, 0.050, 7.8, 15.92, 3.86, 0, 99.99, 187),
    (4.5, 10.0, 0.200, 0.020, 13.6, 2.75, 0.19, 0, 99.88, 9),
    (4.5, 10.0, 0.408, 0.100, 13.6, 2.75, 8.11, 0, 99.99, 9),
    (5.0, 7.5, 0.200, 0.020, 24.7, 2.19, 0.71, 0, 100.0, 8),
    (5.0, 7.5, 0.408, 0.020, 24.7, 2.19, 2.41, 0, 100.0, 154),
    (5.0, 10.0, 0.200, 0.020, 42.9, 0.05, 0.60, 0, 100.0, 0),
    (5.0, 10.0, 0.200, 0.100, 42.9, 0.05, 5.79, 0, 100.0, 0),
    (5.0, 10.0, 0.408, 0.100, 42.9, 0.05, 20.63, 0, 100.0, 0),
]


def seed001(epoch: float = 2000.0) -> None:
    print(
        "\n== Dong et al.: V <= 5.0 guide stars, pairs 0.05 deg <= theta <= 24.5 deg (paper: 1631 stars, 65 890 pairs) =="
    )
    for source in ("hipparcos", "bsc5"):
        if source == "bsc5" and not DEFAULT_BSC5.is_file():
            print("bsc5: ../shared/data/bsc5 absent, skipped")
            continue
        design = CatalogDesign(
            source=source, m_thresh=5.0, theta_fov_deg=12.25, phi_min_deg=0.05, resolve_deg=0.05, epoch=epoch
        )
        cat = build_catalog(design)
        # brute-force count with the paper's closed interval, independent of the pair table
        v = np.asarray(cat.vec)
        iu = np.triu_indices(len(v), 1)
        theta = np.degrees(angle_between(v[iu[0]], v[iu[1]]))
        n_closed = int(((theta >= 0.05) & (theta <= 24.5)).sum())
        sel = cat.meta["selection"]
        before = cat.n_stars + sel["merged_doubles"]
        print(
            f"{source:>9}: {before} stars with V <= 5.0 ({before - 1631:+d} vs 1631), {cat.n_stars} after merging "
            f"{sel['merged_doubles']} doubles < 0.05 deg, {cat.n_pairs} pairs in the table, {n_closed} by brute force "
            f"({n_closed - 65890:+d}, {100 * (n_closed / 65890 - 1):+.1f} % vs 65 890)"
        )


def table1(n_views: int, out: Path) -> None:
    print(f"\n== Enright & McVittie table 1 ({n_views} spiral views; epoch 2000; paper values in brackets) ==")
    sources = ["bsc5", "hipparcos"] if DEFAULT_BSC5.is_file() else ["hipparcos"]
    for source in sources:
        table = load_source(CatalogDesign(source=source, epoch=2000.0))
        print(f"\n-- source: {source} --")
        print(TABLE_HEADER + "   || paper: pairs e3, bad %, amb %, unres, mono amb %, mono unres")
        for row in tqdm(PAPER_TABLE1, desc=f"table 1 ({source})", leave=False):
            m, th, sp, sc = row[:4]
            design = CatalogDesign(
                source=source, m_thresh=m, theta_fov_deg=th, sigma_pix=sp, sigma_rg=sc, sigma_bg=sc, epoch=2000.0
            )
            cat = build_catalog(design, source=table)
            res, views, vc, vm = analyze(cat, design, n_views=n_views, return_views=True)
            p = row[4:]
            tqdm.write(f"{table_row(res)}   || {p[0]:5.1f} {p[1]:6.2f} {p[2]:6.2f} {p[3]:5d} {p[4]:7.2f} {p[5]:5d}")
            if (m, th, sp, sc) == (5.0, 7.5, 0.2, 0.02):
                png = out / f"bad_views_{source}_m5.0_fov7.5.png"
                plot_views(png, views, vc, vm, title=f"{source} V<=5.0 thetaFOV=7.5 deg sigma_pix 0.2 sigma_col 0.02")
                tqdm.write(f"      sky map: {png}")


def _row_design(row, **kw) -> CatalogDesign:
    m, th, sp, sc = row[:4]
    return CatalogDesign(
        source="bsc5", m_thresh=m, theta_fov_deg=th, sigma_pix=sp, sigma_rg=sc, sigma_bg=sc, epoch=2000.0, **kw
    )


def table1_checks(n_views: int, seeds: int) -> None:
    """Issue 32: what table 1's definition (eq. 4, sec. 5.1) gives, checked without any assumption."""
    print(f"\n== Table 1 against its own definition (BSC5, epoch 2000; {seeds} seeds where random) ==")
    if not DEFAULT_BSC5.is_file():
        print("../shared/data/bsc5 absent, skipped")
        return
    table = load_source(CatalogDesign(source="bsc5", epoch=2000.0))
    row1 = _row_design(PAPER_TABLE1[0])
    cat = build_catalog(row1, source=table)
    sp, ds = row1.sigma_phi, row1.delta_star

    print("\n-- template floor: row 1 with perfectly measured colours (paper: 0.26 %) --")
    for qe in QE_MODELS:
        c = build_catalog(_row_design(PAPER_TABLE1[0], qe_path=qe), source=table)
        print(f"  QE {qe:>16}: {100 * template_floor(c, sp, ds).mean():.2f} % of {c.n_pairs} pairs ambiguous")
    tmpl = np.asarray(cat.meta["template"], dtype=object)
    n_t = len(set(tmpl[tmpl != ""]))
    print(f"  {cat.n_stars} stars, {int((tmpl != '').sum())} with a Pickles template, {n_t} distinct")
    for k in (n_t, 111, 131):  # 131: every spectrum of the Pickles (1998) library
        f = [100 * even_template_floor(cat, sp, ds, k, seed).mean() for seed in range(4 * seeds)]
        print(
            f"  stars spread evenly over {k:3d} spectra: mean {np.mean(f):.2f} % over {len(f)} random assignments "
            f"(middle half {np.percentile(f, 25):.2f}-{np.percentile(f, 75):.2f} %, all {min(f):.2f}-{max(f):.2f} %)"
        )

    print("\n-- the colour spread it would take --")
    rg, bg = np.asarray(cat.rg, float), np.asarray(cat.bg, float)
    ok = np.isfinite(rg)
    print(
        f"  row 1 colour range (default QE): rg {rg[ok].min():.2f}-{rg[ok].max():.2f} "
        f"({np.ptp(rg[ok]):.2f} wide), bg {bg[ok].min():.2f}-{bg[ok].max():.2f} ({np.ptp(bg[ok]):.2f} wide)"
    )
    need = [
        solve_decreasing(lambda j, s=seed: jittered_colour_ambiguity(cat, sp, ds, 0.02, j, s), 0.26, 1e-4, 10.0)
        for seed in range(seeds)
    ]
    print(
        f"  per-star N(0, s) jitter added to rg and bg for row 1 to reach 0.26 % (sigma 0.02): "
        f"s = {np.median(need):.2f} (seeds {min(need):.2f}-{max(need):.2f})"
    )
    print("  random per-star colours (uniform over a range of width W, noise sigma as the row): W / sigma for the")
    print("  paper's ambiguity, median over seeds; 2-D: rg, bg independent; 1-D locus: rg = bg")
    print(f"  {'M_thr thFOV s_pix s_col':23s} {'paper amb %':>11} {'W/sigma 2-D':>12} {'W/sigma 1-D':>12}")
    spans: dict[int, list[float]] = {2: [], 1: []}
    for row in PAPER_TABLE1:
        d = _row_design(row)
        c = build_catalog(d, source=table)
        cells = []
        for dims in (2, 1):
            w = [
                solve_decreasing(
                    lambda x, s=seed, dims=dims, c=c, d=d: synthetic_colour_ambiguity(
                        c, d.sigma_phi, d.delta_star, x, dims, s
                    ),
                    row[6],
                    0.1,
                    1e5,
                )
                for seed in range(seeds)
            ]
            spans[dims].append(float(np.median(w)))
            cells.append(f"{np.median(w):12.0f}")
        print(f"  {row[0]:5.2f} {row[1]:5.1f} {row[2]:5.3f} {row[3]:5.3f} {row[6]:11.2f} {' '.join(cells)}")
    for dims in (2, 1):
        print(f"  {dims}-D: W / sigma runs from {min(spans[dims]):.0f} to {max(spans[dims]):.0f} over the ten rows")

    print(f"\n-- monochrome unresolvable views ({n_views} views): two stars, one ambiguous pair, is unresolvable --")
    views = spiral_points(n_views)
    print(
        f"  {'M_thr thFOV s_pix':17s} {'pairs':>6} {'unamb.':>6} {'2-star views':>12} {'of them unres.':>14} "
        f"{'all unres.':>10} {'paper':>6}"
    )
    for row in PAPER_TABLE1:
        if row[3] != 0.02 and row[:3] != (4.5, 10.0, 0.408) and row[:3] != (5.0, 10.0, 0.408):
            continue  # the monochrome columns do not depend on sigma_colour
        d = _row_design(row)
        c = build_catalog(d, source=table)
        amb = ambiguous_pairs(c, d.sigma_phi, d.delta_star)
        two = two_star_views(c, views, d.theta_fov, amb)
        res = analyze(c, d, n_views=n_views)
        print(
            f"  {row[0]:5.2f} {row[1]:5.1f} {row[2]:5.3f} {c.n_pairs:6d} {int((~amb).sum()):6d} {two.exactly_two:12d} "
            f"{two.ambiguous:14d} {res.mono_unresolvable_views:10d} {row[9]:6d}"
        )

    print("\n-- field of view: the wider field holds every narrower-field pair, with a wider window --")
    for a, b in ((0, 3), (5, 7)):
        ra, rb = PAPER_TABLE1[a], PAPER_TABLE1[b]
        # the wider field merges doubles up to its own phi_min (theta_FOV / 500), so it may lose a star:
        # also built with the narrower field's merge angle, the same stars
        da, db = _row_design(ra), _row_design(rb)
        db_same = _row_design(rb, resolve_deg=math.degrees(da.resolve_angle))
        ca, cb = build_catalog(da, source=table), build_catalog(db, source=table)
        cs = build_catalog(db_same, source=table)
        amb_s = ambiguous_pairs(cs, db.sigma_phi, db.delta_star, db.sigma_rg, db.sigma_bg)
        ns = field_nesting(
            ca, ambiguous_pairs(ca, da.sigma_phi, da.delta_star, da.sigma_rg, da.sigma_bg), cs, amb_s, 1, 1
        )
        amb_a = ambiguous_pairs(ca, da.sigma_phi, da.delta_star, da.sigma_rg, da.sigma_bg)
        amb_b = ambiguous_pairs(cb, db.sigma_phi, db.delta_star, db.sigma_rg, db.sigma_bg)
        n = field_nesting(ca, amb_a, cb, amb_b, da.delta_star * da.sigma_phi, db.delta_star * db.sigma_phi)
        pa, pb = round(ra[6] / 100 * ra[4] * 1e3), round(rb[6] / 100 * rb[4] * 1e3)
        print(
            f"  row {a + 1} (thFOV {ra[1]}) -> row {b + 1} (thFOV {rb[1]}), M {ra[0]}: {n.contained} of {n.small_pairs} "
            f"pairs contained, window x {n.window_ratio:.3f}; ambiguous {n.small_ambiguous} -> {n.big_ambiguous} "
            f"({n.still_ambiguous} of the {n.small_ambiguous} still ambiguous), added pairs {n.added_pairs} "
            f"({100 * n.added_ambiguous / max(n.added_pairs, 1):.2f} % ambiguous vs {100 * amb_a.mean():.2f} % of the "
            f"narrower)"
        )
        print(
            f"      wider field with the narrower's merge angle ({cs.n_stars} stars, {ca.n_stars} narrower): "
            f"{ns.contained} of {ns.small_pairs} pairs contained, {ns.still_ambiguous} of the {ns.small_ambiguous} "
            f"ambiguous still ambiguous, {ns.big_ambiguous} of {ns.big_pairs} ambiguous "
            f"({100 * ns.big_ambiguous / ns.big_pairs:.2f} %)"
        )
        print(
            f"      paper: {ra[6]:.2f} % of {ra[4]}e3 ~ {pa} pairs -> {rb[6]:.2f} % of {rb[4]}e3 ~ {pb} pairs: its "
            f"{round(rb[4] * 1e3 - ra[4] * 1e3)} added pairs would be {100 * (pb - pa) / (rb[4] * 1e3 - ra[4] * 1e3):.2f} % "
            f"ambiguous against {ra[6]:.2f} % of the narrower field's"
        )


def colour_fallbacks() -> None:
    """Colour-index lookups and blackbody against the MK-template ratios (types borrowed from BSC5)."""
    print("\n== Colour fallbacks vs Pickles-by-MK-type ratios (Hipparcos V <= 6.0 with a BSC5 type) ==")
    if not DEFAULT_BSC5.is_file():
        print("../shared/data/bsc5 absent, skipped")
        return
    table = read_hipparcos(epoch=2000.0)
    sel, _ = select_stars(table, 6.0, np.radians(0.015))
    sel, _ = borrow_mk_types(sel, DEFAULT_BSC5, 2000.0)
    model = ColourModel()
    rg, bg, src, _ = model.star_ratios(sel.sptype, np.full(len(sel), np.nan))
    typed = src == ColourSource.PICKLES_MK
    frg, fbg, fsrc, _ = model.star_ratios(np.full(len(sel), "", dtype=object), sel.bv, sel.vi)
    trg, tbg = blackbody_ratios(model.qe, ballesteros_temperature(np.clip(sel.bv, -0.4, 3.0)))
    print(f"{typed.sum()} stars; rms relative difference to the template ratios, rg / bg:")
    for label, mask in (("B-V < 1.0", typed & (sel.bv < 1.0)), ("B-V >= 1.0", typed & (sel.bv >= 1.0)), ("all", typed)):

        def e(a, b, mask=mask):
            return 100 * np.sqrt(np.mean((a[mask] / b[mask] - 1) ** 2))

        print(
            f"  {label:>10} (n={mask.sum():4d}): chosen lookup {e(frg, rg):5.2f} / {e(fbg, bg):5.2f} %   "
            f"Ballesteros blackbody {e(trg, rg):5.2f} / {e(tbg, bg):5.2f} %"
        )
    print("  sources chosen: " + ", ".join(f"{s.name} {int((fsrc[typed] == s).sum())}" for s in ColourSource))


def build_times() -> None:
    print("\n== Build times (cold: source read included) ==")
    t = time.perf_counter()
    read_hipparcos()
    t_read = time.perf_counter() - t
    print(f"baseline, reading hip2.dat alone: {t_read:.2f} s")
    for label, design in (
        ("default (Hipparcos, M 5.0, theta_FOV 7.5 deg)", CatalogDesign()),
        ("table 1 largest row (Hipparcos, M 5.0, theta_FOV 10 deg)", CatalogDesign(theta_fov_deg=10.0)),
        ("table 1 largest row (BSC5, M 5.0, theta_FOV 10 deg)", CatalogDesign(source="bsc5", theta_fov_deg=10.0)),
    ):
        if design.source == "bsc5" and not DEFAULT_BSC5.is_file():
            continue
        t = time.perf_counter()
        cat = build_catalog(design)
        dt = time.perf_counter() - t
        print(
            f"{label}: {dt:.2f} s for {cat.n_stars} stars / {cat.n_pairs} pairs "
            f"({dt / t_read:.2f} x the read baseline; target < 10 s)"
        )


def upload_time() -> None:
    print("\n== Upload of the default catalog at a paced 115 200 baud ==")
    image = catalog_to_image(build_catalog(CatalogDesign()))
    device = Device(slots={0: catalog_slot_handler()})
    link, stop = PtyLink(), threading.Event()
    thread = threading.Thread(target=serve, args=(device, link, stop), kwargs={"baud": 115200}, daemon=True)
    thread.start()
    try:
        with Client(link.path, timeout=5.0) as c:
            t = time.perf_counter()
            report = c.upload(0, image, progress=True)
            dt = time.perf_counter() - t
            info = c.slot_info(0)
    finally:
        stop.set()
        thread.join(2)
        link.close()
    minimum = len(image) * 10 / 115200
    print(
        f"image {len(image)} bytes, CRC-32 verified {info.crc32 == report.crc32}: {dt:.1f} s, line-rate minimum "
        f"{minimum:.1f} s -> {dt / minimum:.3f} x the minimum ({100 * minimum / dt:.1f} % of the line rate)"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=100_000)
    parser.add_argument("--skip-upload", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_catalog"))
    parser.add_argument("--checks-only", action="store_true", help="only the table-1 definition checks (~1 min)")
    parser.add_argument("--seeds", type=int, default=5, help="random draws per check that uses random colours")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.checks_only:
        table1_checks(args.views, args.seeds)
        return 0
    build_times()
    colour_fallbacks()
    seed001()
    table1(args.views, args.out)
    table1_checks(args.views, args.seeds)
    if not args.skip_upload:
        upload_time()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
