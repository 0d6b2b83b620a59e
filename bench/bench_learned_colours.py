"""Learned star colours against the eq. 24 correction: Enright & McVittie table 5 again.

Frames are rendered with known truth and split in two halves. The training half is solved by the
device pipeline (auto: colour, then geometry) against the catalog; from its high-confidence
answers (no truth used) come the eq. 24 fit (``ColourCorrection.fit``) and the learned colours
(``ground.calibration.learned_colours``: raw ratios, and ratios through the fitted eq. 24 for
"both"), written into the catalog image and read back as the device would. The test half is then
solved four ways: basic (catalog, no correction), eq. 24 alone, learned colours alone, both; by
colour matching alone (table 5: no geometric fallback) and by the device's auto order. Printed
per way: correct / incorrect / no match and the colour RMS of the test stars against the colours
the matcher compares (truth-associated detections).

Scenarios:

* ``field``: ``bench_field``'s Orion belt (atmosphere, scintillation, chromatic aberration),
  the atmosphere's departure from the identity scaled by ``--atmosphere-scale``;
* ``openloop``: pointings anywhere within 20 deg of Orion's belt, colours the catalog did not
  model: a Planck spectrum at the star's T(B-V) (``blackbody_sky_stars``) times fixed channel
  gain errors (a mis-modelled QE, ``--gain-rg``/``--gain-bg``) and scintillation.

    .venv/bin/python bench/bench_learned_colours.py [--scenario field openloop] [--frames 70 120]
        [--atmosphere-scale 1] [--out out/bench_learned_colours]
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import bench_field  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

WAYS = ("basic", "eq. 24 alone", "learned alone", "learned + eq. 24")
OPENLOOP_CENTRE_DEG = (84.05, -1.20)
OPENLOOP_RADIUS_DEG = 20.0


def render_openloop(
    frames_dir: Path,
    n_frames: int,
    camera,
    gains: tuple[float, float],
    scint: float,
    m_limit=None,
    wrong_type: float = 0.0,
    seed=13,
):
    """Frames at random pointings within :data:`OPENLOOP_RADIUS_DEG` of the belt, blackbody colours
    times channel gains ``(rg, bg)`` and per-star scintillation (relative, per ratio); stars to V
    ``m_limit`` (None: the sky model's default). A fraction ``wrong_type`` of the stars shows the
    colours of another random star: the catalog's spectral type is wrong for them."""
    from firmware_model.reference_frames import attitude_from_radec_roll, radec_to_vec
    from ground.sim.frame_writer import write_rendered
    from ground.sim.openloop import blackbody_sky_stars
    from ground.sim.sensor_sim import DetectorModel, render_frame

    frames_dir.mkdir(parents=True, exist_ok=True)
    sky = blackbody_sky_stars() if m_limit is None else blackbody_sky_stars(m_limit)
    centre = radec_to_vec(*np.radians(OPENLOOP_CENTRE_DEG))
    rng = np.random.default_rng(seed)
    swap = np.flatnonzero(rng.random(len(sky.ids)) < wrong_type)
    other = rng.integers(0, len(sky.ids), len(swap))
    rg, bg = sky.rg.copy(), sky.bg.copy()
    rg[swap], bg[swap] = sky.rg[other], sky.bg[other]
    sky = replace(sky, rg=rg, bg=bg)
    for k in tqdm(range(n_frames), desc="render"):
        while True:  # uniform on the cap
            v = rng.standard_normal(3)
            v /= np.linalg.norm(v)
            if v @ centre > np.cos(np.radians(OPENLOOP_RADIUS_DEG)):
                break
        ra, dec = np.arctan2(v[1], v[0]) % (2 * np.pi), np.arcsin(v[2])
        a = attitude_from_radec_roll(ra, dec, rng.uniform(0, 2 * np.pi))
        near = np.flatnonzero(sky.vectors @ v > np.cos(np.radians(12)))
        sub = replace(
            sky,
            ids=sky.ids[near],
            vectors=sky.vectors[near],
            vmag=sky.vmag[near],
            rg=sky.rg[near] * gains[0] * (1 + scint * rng.standard_normal(len(near))),
            bg=sky.bg[near] * gains[1] * (1 + scint * rng.standard_normal(len(near))),
        )
        write_rendered(render_frame(sub, a, camera, DetectorModel(), seed=k), frames_dir / f"open_{k:03d}.dng")


def _counts(outcomes) -> dict:
    key = {"correct": "correct", "wrong": "incorrect"}
    c = {"correct": 0, "incorrect": 0, "no_match": 0}
    for o in outcomes:
        c[key.get(o, "no_match")] += 1
    return c


def _colour_rms(frames, catalog, beta, learned_ids: set) -> tuple[float, float]:
    """RMS over rg and bg of (observed, through ``beta``) - catalog for truth-associated stars:
    those in ``learned_ids``, and the others."""
    from firmware_model.pipeline.frame_identification import apply_colour_correction
    from protocol.star_flags import StarFlag

    bad = int(StarFlag.SATURATED | StarFlag.BLEND)
    row = {int(s): k for k, s in enumerate(catalog.star_id)}
    d: list[list] = [[], []]
    for stars, truth in frames:
        for i in range(len(stars)):
            near = truth.stars_near(stars.x[i], stars.y[i])
            sid = next(iter(near)) if len(near) == 1 else None
            if sid is None or (k := row.get(sid)) is None or stars.flags[i] & bad:
                continue
            rg, bg = stars.rg[i], stars.bg[i]
            if beta is not None:
                rg, bg = apply_colour_correction(rg, bg, beta)
            d[sid not in learned_ids].extend([rg - catalog.rg[k], bg - catalog.bg[k]])
    rms = [float(np.sqrt(np.nanmean(np.square(x)))) if x else float("nan") for x in d]
    return rms[0], rms[1]


def run(name: str, paths, camera, catalog, image: bytes, figure: Path) -> None:
    from firmware_model.catalog.image_io import catalog_from_image
    from firmware_model.pipeline.extract import extract_stars
    from firmware_model.pipeline.frame_readers import read_frame
    from firmware_model.pipeline.run import identify_stars
    from firmware_model.pipeline.solve_types import PipelineParams
    from ground.analysis.replay import Truth, score
    from ground.calibration.corrections import ColourCorrection
    from ground.calibration.learned_colours import learn_image, observations_from_records, plot_learned
    from ground.link.solve_report import record_from_output

    auto = PipelineParams()
    colour_only = replace(auto, colour_fallback=False, geometric_fallback=False, optics=None)
    frames = [
        (extract_stars(read_frame(p), camera, auto.extract), Truth.for_frame(p))
        for p in tqdm(paths, desc=f"{name}: extract")
    ]
    half = len(frames) // 2
    train, test = frames[:half], frames[half:]
    records = [record_from_output(identify_stars(s, camera, catalog, auto)) for s, _ in tqdm(train, desc="train")]
    obs = observations_from_records(records)
    row = {int(s): k for k, s in enumerate(catalog.star_id)}
    ok = obs.usable()
    ref = np.array([(catalog.rg[row[int(i)]], catalog.bg[row[int(i)]]) for i in obs.star_id[ok]])
    fit = ColourCorrection.fit(np.column_stack([obs.rg[ok], obs.bg[ok]]), ref)
    learned, img_raw = learn_image(image, obs)
    learned_c, img_corr = learn_image(image, observations_from_records(records, beta=fit.beta))
    n_ok = sum(r["status"] == "OK" for r in records)
    print(
        f"\n{name}: {len(train)} training frames ({n_ok} high-confidence), {len(test)} test frames\n"
        f"  eq. 24 from {fit.n_used} matched stars ({fit.n_rejected} rejected): training RMS {fit.rms_before:.3f} -> "
        f"{fit.rms_after:.3f}\n"
        f"  learned (raw): {learned.summary()}\n  learned (through eq. 24): {learned_c.summary()}"
    )
    if img_raw is None or img_corr is None:
        print(f"  nothing learned: {learned.reason or learned_c.reason}")
        return
    plot_learned(learned_c, figure, f"{name}: colours learned through eq. 24 from {len(train)} frames")
    print(f"  figure: {figure}")
    ways = {
        "basic": (catalog, None),
        "eq. 24 alone": (catalog, tuple(fit.beta)),
        "learned alone": (catalog_from_image(img_raw), None),
        "learned + eq. 24": (catalog_from_image(img_corr), tuple(fit.beta)),
    }
    seen = {s.star_id for s in learned.updated}
    print(
        f"  {'test frames':<18}{'colour matching alone (table 5)':>34}{'device auto order':>30}"
        f"{'colour RMS, stars learned / not':>34}"
    )
    print(f"  {'':<18}{'correct incorrect no-match':>34}{'correct incorrect no-match':>30}")
    for way, (cat, beta) in ways.items():
        cells = []
        for params in (colour_only, auto):
            p = replace(params, colour_beta=beta)
            outs = [score(record_from_output(identify_stars(s, camera, cat, p)), t)["outcome"] for s, t in test]
            c = _counts(outs)
            cells.append(f"{c['correct']:>7} {c['incorrect']:>9} {c['no_match']:>8}")
        rms = _colour_rms(test, cat, beta, seen)
        print(f"  {way:<18}{cells[0]:>34}{cells[1]:>30}{rms[0]:>24.3f} / {rms[1]:.3f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", nargs="+", choices=("field", "openloop"), default=["field", "openloop"])
    ap.add_argument("--frames", type=int, nargs="+", default=[70, 120], help="frames per scenario, in order")
    ap.add_argument("--atmosphere-scale", type=float, default=1.0, help="field: scale of (B - I) and c")
    ap.add_argument("--gain-rg", type=float, default=1.12, help="openloop: rg gain error of the detector")
    ap.add_argument("--gain-bg", type=float, default=0.85, help="openloop: bg gain error")
    ap.add_argument("--scintillation", type=float, default=0.03, help="openloop: per-ratio relative jitter")
    ap.add_argument(
        "--wrong-type", type=float, default=0.2, help="openloop: fraction of stars with another star's colours"
    )
    ap.add_argument(
        "--m-limit",
        type=float,
        help="a star-poor sensor: render only stars to this V and build the catalog to it (the paper's prototype saw "
        "few stars); default: the sky model's stars and the default catalog",
    )
    ap.add_argument("--out", default="out/bench_learned_colours")
    ap.add_argument("--figures", default="docs/figures", help="where the learned-colour plots go")
    args = ap.parse_args(argv)

    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_to_image
    from firmware_model.pipeline.frame_readers import frame_files
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    camera = CameraModel.reference_design()
    catalog = build_catalog(CatalogDesign() if args.m_limit is None else CatalogDesign(m_thresh=args.m_limit))
    image = catalog_to_image(catalog, created_unix=0)
    out = Path(args.out)
    frames = dict(zip(args.scenario, args.frames + args.frames[-1:] * len(args.scenario)))
    for name in args.scenario:
        d = out / name
        for old in d.glob("*"):  # a fresh render: stale frames would mix runs
            old.unlink()
        if name == "field":
            s = args.atmosphere_scale
            b, c = bench_field.ATMOSPHERE
            bench_field.ATMOSPHERE = (np.eye(2) + s * (b - np.eye(2)), s * c)
            bench_field.render_orion(d, frames[name], camera, m_limit=args.m_limit)
            print(
                f"\nfield: atmosphere B = {np.round(bench_field.ATMOSPHERE[0], 3).tolist()}, c = "
                f"{np.round(bench_field.ATMOSPHERE[1], 3).tolist()}, scintillation {bench_field.SCINTILLATION:.0%}, "
                f"chromatic {bench_field.CHROMATIC_PX_PER_BG} px per unit bg"
            )
        else:
            gains = (args.gain_rg, args.gain_bg)
            render_openloop(d, frames[name], camera, gains, args.scintillation, args.m_limit, args.wrong_type)
            print(
                f"\nopenloop: blackbody colours ({args.wrong_type:.0%} of stars another star's) x gains rg {args.gain_rg}, "
                f"bg {args.gain_bg}, "
                f"scintillation {args.scintillation:.0%}, pointings within {OPENLOOP_RADIUS_DEG} deg of the belt"
            )
        run(name, frame_files(d), camera, catalog, image, Path(args.figures) / f"learned_colours_{name}.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
