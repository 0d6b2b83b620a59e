"""Catalog benchmarks: Dong et al. counts, Enright & McVittie table 1 (BSC5 and Hipparcos), build and upload times.

Prints figures only (no asserts):

1. Dong et al.: guide stars with V <= 5.0 and pairs with 0.05 deg <= theta <= 24.5 deg, against the
   paper's 1631 stars and 65 890 pairs (SKY2000).
2. Enright & McVittie table 1, every row, built from the Yale BSC5 (as in the paper) and from Hipparcos,
   next to the paper's numbers; N views on the generalized spiral (1e5 as in the paper).
3. Colour fallbacks (B-V / V-I lookups, blackbody) against the Pickles-by-MK-type ratios.
4. Build time of the default catalog (Hipparcos, M 5.0, theta_FOV 7.5 deg) and of table 1's
   largest row, against a baseline measured in the same run: reading the source catalog alone.
5. Upload time of the default catalog image to an in-process device paced at 115 200 baud over a
   pty, against the line-rate minimum (10 bits per payload byte).

Usage: .venv/bin/python bench/bench_catalog.py [--views 100000] [--skip-upload] [--out DIR]
"""

from __future__ import annotations

import argparse
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
from ground.catalog.analyze import TABLE_HEADER, analyze, plot_views, table_row
from ground.catalog.build import DEFAULT_BSC5, borrow_mk_types, build_catalog, load_source
from ground.catalog.colour import ColourModel, ColourSource, ballesteros_temperature, blackbody_ratios
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
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    build_times()
    colour_fallbacks()
    seed001()
    table1(args.views, args.out)
    if not args.skip_upload:
        upload_time()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
