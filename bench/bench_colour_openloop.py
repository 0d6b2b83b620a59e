"""Open-loop colour in the whole-sky run: colour matching against geometric (mono)
matching when the observed colours come from the catalog's own model (closed loop) and from a
model the catalog did not use, with channel gain errors and scintillation (open loop).

One run, the same boresights, rolls, seeds, centroid noise, dropped and false stars in every
variant (``ground.sim.whole_sky``; the open-loop draws come from a stream of their own):

* ``colour closed``: catalog colours + Gaussian noise ``--sigma-colour`` (today's run);
* ``colour blackbody``: Planck colours at the Ballesteros T(B-V) through the catalog's QE + noise;
* ``colour gain+scint``: catalog colours x channel gains (``--gain-error``) x scintillation
  (``--scintillation``) + noise;
* ``colour open``: blackbody x gains x scintillation + noise;
* ``colour open, told``: the same frames, the solver told ``--solver-sigma-colour`` (the
  measurement noise and the colour model's error together) instead of ``--sigma-colour``;
* ``colour open, device``: the same frames in the device's ``auto`` order: colour, then geometry
  when colour is not high-confidence (``StrategyParams.colour_fallback``);
* ``mono``: no colours, the device's geometric order. A mono frame observes no colour, so one
  run serves both loops (its scenes are the same draws in either; ``tests/test_true_colours.py``).

Except in ``colour open, told`` the solver is told ``--sigma-colour`` alone. Prints the outcome
table per variant, then where colour helps and hurts: by true stars in view, by the worst
blackbody-vs-catalog colour error of the stars in view, by spectral class, and the poses one
method solves and the other does not.

    .venv/bin/python bench/bench_colour_openloop.py [--boresights 4000] [--rolls 4] [--workers 2]
        [--false-stars 3] [--drop 0.1] [--gain-error 0.05] [--scintillation 0.03] [--out out/bench_colour_openloop]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: Bins of true stars in view: (label, lowest, highest inclusive).
N_TRUE_BINS = (("0-1", 0, 1), ("2", 2, 2), ("3", 3, 3), ("4-5", 4, 5), ("6+", 6, 10**6))
#: Bins of the median relative blackbody-vs-catalog colour error of the true stars in view.
ERROR_BINS = (("< 3 %", 0.0, 0.03), ("3-6 %", 0.03, 0.06), ("6-10 %", 0.06, 0.10), (">= 10 %", 0.10, np.inf))
#: B-V limits of the spectral classes: hot (O/B/early A), cool (K/M).
BV_HOT, BV_COOL = 0.3, 1.0


def variants(args) -> dict:
    """Name -> (TrueColours, colour mode, solver's colour sigma or None, colour fallback) of every run."""
    from ground.sim.true_colours import TrueColours

    g, s = args.gain_error, args.scintillation
    return {
        "colour closed": (TrueColours(), True, None, False),
        "colour blackbody": (TrueColours("blackbody"), True, None, False),
        "colour gain+scint": (TrueColours("catalog", g, s), True, None, False),
        "colour open": (TrueColours("blackbody", g, s), True, None, False),
        "colour open, told": (TrueColours("blackbody", g, s), True, args.solver_sigma_colour, False),
        "colour open, device": (TrueColours("blackbody", g, s), True, None, True),
        "mono": (TrueColours(), False, None, False),
    }


def colour_model_error(catalog, colours, frames: int = 200, seed: int = 0) -> float:
    """RMS (absolute, rg and bg together) of noise-free open-loop colours minus the catalog's over
    every catalog star and ``frames`` draws of gains and scintillation."""
    from ground.sim.true_colours import impair, true_colour_table

    rg, bg = true_colour_table(catalog, colours.source)
    rng = np.random.default_rng(seed)
    d = [
        np.concatenate([r - catalog.rg, b - catalog.bg])
        for r, b in (impair(rg, bg, colours, rng) for _ in range(frames))
    ]
    return float(np.sqrt(np.mean(np.concatenate(d) ** 2)))


def outcomes(rows: np.ndarray, high_error_deg: float = 1.0) -> dict[str, np.ndarray]:
    """Per-pose masks: correct (solved, no wrong star, error <= 1 deg), wrong, none, HC wrong."""
    solved = rows["status"] > 0
    wrong = solved & ((rows["n_wrong"] > 0) | ~(rows["err_deg"] <= high_error_deg))
    return {"correct": solved & ~wrong, "wrong": wrong, "none": ~solved, "hc_wrong": wrong & (rows["status"] == 2)}


def pose_features(catalog, camera, cfg, n_poses: int) -> dict[str, np.ndarray]:
    """Per pose (geometry only, the same in every variant): the median relative blackbody-vs-catalog
    colour error (the larger of rg and bg per star) and the B-V class ('hot' / 'cool' / 'mixed' by
    majority) of its true detections."""
    from tqdm import tqdm

    from ground.sim import whole_sky as skysim
    from ground.sim.true_colours import true_colour_table

    bb_rg, bb_bg = true_colour_table(catalog, "blackbody")
    star_err = np.maximum(np.abs(bb_rg / catalog.rg - 1), np.abs(bb_bg / catalog.bg - 1))
    bv = np.asarray(catalog.meta["bv"], float)
    boresights = skysim.spiral_boresights(cfg.n_boresights)
    mono = replace(cfg, colour=False)
    median_err = np.zeros(n_poses)
    cls = np.full(n_poses, "mixed", dtype=object)
    for pid in tqdm(range(n_poses), desc="features", unit="pose", disable=not sys.stderr.isatty()):
        _, _, scene = skysim.pose_scene(catalog, camera, mono, pid, boresights)
        t = scene.truth[scene.truth >= 0]
        if len(t) == 0:
            continue
        median_err[pid] = np.nanmedian(star_err[t]) if np.isfinite(star_err[t]).any() else 0.0
        b = bv[t][np.isfinite(bv[t])]
        if len(b) and np.mean(b < BV_HOT) > 0.5:
            cls[pid] = "hot"
        elif len(b) and np.mean(b > BV_COOL) > 0.5:
            cls[pid] = "cool"
    return {"median_err": median_err, "cls": cls}


def run_all(catalog, camera, base, names: dict, n_poses: int, workers: int) -> tuple[dict, dict]:
    """Rows (pose order) and wall seconds of every variant."""
    from ground.sim import whole_sky as skysim

    rows, walls = {}, {}
    for name, (colours, colour, solver_sigma, fallback) in names.items():
        model = replace(base.model, colours=colours)
        cfg = replace(base, colour=colour, model=model, solver_sigma_colour=solver_sigma, colour_fallback=fallback)
        r, wall = skysim.execute("colour", catalog, camera, cfg, n_poses, workers=workers, progress=sys.stderr.isatty())
        rows[name] = r  # pose order: execute sorts by boresight, then roll
        walls[name] = wall
    return rows, walls


def print_outcomes(rows: dict, walls: dict) -> None:
    """Outcome counts, the whole-sky problem rate (docs/identification.md) and the causes of no solution."""
    from ground.sim.whole_sky import colour_summary

    head = f"{'variant':20s}{'poses':>7s}{'correct':>9s}{'wrong':>7s}{'no sol':>8s}{'HC wrong':>10s}{'problem':>10s}"
    print(head + "   no sol: few true / verif. rejects truth / budget / matcher missed   wall s")
    for name, r in rows.items():
        o, s = outcomes(r), colour_summary(r)
        causes = " / ".join(str(v) for v in s["no_solution_by_cause"].values())
        print(
            f"{name:20s}{len(r):7d}{o['correct'].sum():9d}{o['wrong'].sum():7d}{o['none'].sum():8d}"
            f"{o['hc_wrong'].sum():10d}{s['problem_fraction'] * 100:9.3f}%   {causes:61s}{walls[name]:6.0f}"
        )


def print_split(title: str, masks: dict[str, np.ndarray], rows: dict) -> None:
    """Failures (wrong + no solution) per bin and variant, as count and percent of the bin."""
    print(f"\n{title}: failures (wrong + no solution) per bin, count (% of bin)")
    print(f"{'bin':10s}{'poses':>7s}" + "".join(f"{name:>20s}" for name in rows))
    fail = {name: ~outcomes(r)["correct"] for name, r in rows.items()}
    for label, m in masks.items():
        n = int(m.sum())
        cells = "".join(
            f"{int((fail[name] & m).sum()):>10d} ({(fail[name] & m).sum() / max(n, 1) * 100:5.2f}%)" for name in rows
        )
        print(f"{label:10s}{n:7d}{cells}")


def print_versus(rows: dict, n_true: np.ndarray) -> None:
    """Poses colour solves correctly and mono does not, and vice versa, per loop and n_true bin."""
    mono = outcomes(rows["mono"])["correct"]
    print("\ncolour vs mono, pose by pose: colour correct & mono not / mono correct & colour not")
    print(f"{'bin':10s}" + "".join(f"{name:>22s}" for name in rows if name != "mono"))
    bins = [(label, (n_true >= lo) & (n_true <= hi)) for label, lo, hi in N_TRUE_BINS] + [("all", n_true >= 0)]
    for label, m in bins:
        cells = ""
        for name, r in rows.items():
            if name == "mono":
                continue
            col = outcomes(r)["correct"]
            cells += f"{int((col & ~mono & m).sum()):>14d} / {int((mono & ~col & m).sum()):<5d}"
        print(f"{label:10s}{cells}")


def main(argv=None) -> int:
    from ground.arg_types import ranged

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boresights", type=int, default=4000)
    ap.add_argument("--rolls", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--false-stars", type=float, default=3.0, help="mean false detections per frame")
    ap.add_argument("--drop", type=float, default=0.1, help="probability of missing a true star")
    ap.add_argument("--sigma-colour", type=float, default=0.05, help="colour measurement noise (solver's sigma)")
    ap.add_argument("--gain-error", type=ranged(float, 0.0, 0.5, "a gain error"), default=0.05)
    ap.add_argument("--scintillation", type=ranged(float, 0.0, 1.0, "a scintillation sigma"), default=0.03)
    ap.add_argument(
        "--solver-sigma-colour", type=float, default=0.1, help="colour sigma the solver is told in 'colour open, told'"
    )
    ap.add_argument("--out", default="out/bench_colour_openloop")
    args = ap.parse_args(argv)

    from firmware_model.camera import CameraModel
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.sim import whole_sky as skysim
    from ground.sim.true_colours import true_colour_table

    t0 = time.perf_counter()
    catalog = build_catalog(CatalogDesign(sigma_rg=args.sigma_colour, sigma_bg=args.sigma_colour))
    camera = CameraModel.reference_design()
    base = skysim.ColourSimConfig(
        n_boresights=args.boresights,
        n_roll=args.rolls,
        seed=args.seed,
        model=skysim.ErrorModel(0.2, args.sigma_colour, args.false_stars, args.drop),
    )
    n = args.boresights * args.rolls
    names = variants(args)
    rows, walls = run_all(catalog, camera, base, names, n, args.workers)
    n_true = rows["mono"]["n_true"]
    for name, r in rows.items():  # the same scenes in every variant
        assert np.array_equal(r["n_true"], n_true) and np.array_equal(r["n_det"], rows["mono"]["n_det"]), name
    feats = pose_features(catalog, camera, base, n)

    print(f"$ {shlex.join([sys.executable.split('/')[-1], *sys.argv])}")
    print(
        f"{n} poses ({args.boresights} boresights x {args.rolls} rolls), seed {args.seed}, catalog V <= 5 "
        f"({catalog.n_stars} stars), reference camera; sigma_pix 0.2, sigma_colour {args.sigma_colour:g}, "
        f"false stars {args.false_stars:g}, drop {args.drop:g}; open loop: blackbody T(B-V), gain error "
        f"+-{args.gain_error:g}, scintillation {args.scintillation:g}"
    )
    open_colours = names["colour open"][0]
    bb_rg, bb_bg = true_colour_table(catalog, "blackbody")
    d_rg, d_bg = np.abs(bb_rg / catalog.rg - 1), np.abs(bb_bg / catalog.bg - 1)
    print(
        f"blackbody vs catalog colours per star: median {np.median(d_rg) * 100:.1f} % (rg) / "
        f"{np.median(d_bg) * 100:.1f} % (bg), 90th percentile {np.percentile(d_rg, 90) * 100:.1f} % / "
        f"{np.percentile(d_bg, 90) * 100:.1f} %"
    )
    print(
        f"noise-free colour error vs the catalog (rms, rg and bg): blackbody "
        f"{colour_model_error(catalog, replace(open_colours, gain_error=0.0, scintillation=0.0)):.3f}, open loop "
        f"{colour_model_error(catalog, open_colours):.3f}; 'told': solver sigma {args.solver_sigma_colour:g}"
    )
    print_outcomes(rows, walls)
    nt = {label: (n_true >= lo) & (n_true <= hi) for label, lo, hi in N_TRUE_BINS}
    print_split("by true stars in view", nt, rows)
    err = {
        label: (feats["median_err"] >= lo) & (feats["median_err"] < hi) & (n_true > 0) for label, lo, hi in ERROR_BINS
    }
    print_split("by the median blackbody-vs-catalog colour error of the true stars in view", err, rows)
    cls = {
        "hot": feats["cls"] == "hot",
        "mixed": (feats["cls"] == "mixed") & (n_true > 0),
        "cool": feats["cls"] == "cool",
    }
    print_split(f"by spectral class (majority B-V < {BV_HOT:g} hot, > {BV_COOL:g} cool)", cls, rows)
    print_versus(rows, n_true)
    print(f"\nwall {time.perf_counter() - t0:.0f} s on {args.workers} process(es)")

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, r in rows.items():
        np.save(out / f"{name.replace(' ', '_').replace('+', '_')}.npy", r)
    (out / "args.json").write_text(json.dumps(vars(args), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
