"""Radiation hits against whole-sky availability: the same seeded attitudes over the real sky
rendered at 0 (the baseline), 5 and 50 cosmic-ray hits per frame (``ground.sim.detector_effects``,
Poisson with that mean; docs/pipeline.md "Detector effects over a mission"), solved by
``run_pipeline`` with the default catalog, scored by ``ground.sim.availability``. High-confidence
wrong answers must stay 0; the bench exits 1 when one does not, after printing it. Each frame has
the same noise seed at every rate, so 'lost vs 0' counts the frames the baseline solved with high
confidence that the hits took away ('-' without a baseline in the run).

    .venv/bin/python bench/bench_radiation.py [--attitudes 200] [--seed 33] [--workers 2]
        [--rates 0,5,50] [--diffusion-px 0.5] [--json]

``--diffusion-px`` sets the tracks' lateral charge diffusion (px; the model's default is an
assumption, and the detector's sharpness test sees it: docs/pipeline.md says how much it decides).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import cpu_name  # noqa: E402


def run(attitudes: int, seed: int, workers: int, rates: list[float], diffusion_px: float | None = None) -> dict:
    """Summary per rate (hits per frame) over frames ``0 .. attitudes - 1`` of ``seed``."""
    from ground.sim import availability as av
    from ground.sim.detector_effects import DIFFUSION_PX, CosmicRays, MissionEffects

    diffusion = DIFFUSION_PX if diffusion_px is None else diffusion_px

    cfg = av.AvailabilityConfig(attitudes, seed=seed)
    out: dict = {
        "attitudes": attitudes,
        "seed": seed,
        "workers": workers,
        "diffusion_px": diffusion,
        "machine": f"{os.cpu_count()} cores, {cpu_name()}",
        "load_start": list(os.getloadavg()),
        "rates": {},
    }
    all_rows = {}
    for rate in rates:
        effects = [MissionEffects(cosmic=CosmicRays(hits_per_frame=rate, diffusion_px=diffusion))] if rate > 0 else []
        t0 = time.perf_counter()
        rows = av.run_availability(cfg, effects, workers=workers)
        s = av.summarise(rows)
        s["wall_s"] = time.perf_counter() - t0
        s["high_confidence_wrong_frames"] = [
            {k: r[k] for k in ("k", "status", "attitude_error_deg", "wrong_ids", "n_hits", "n_matched", "reason")}
            for r in rows
            if r["status"] == "OK" and r["outcome"] == "wrong"
        ]
        out["rates"][f"{rate:g}"] = s
        all_rows[f"{rate:g}"] = rows
    base = all_rows.get("0")
    for key, rows in all_rows.items():  # frames the baseline solved confidently and this rate did not
        out["rates"][key]["lost_to_hits"] = (
            None
            if base is None
            else [
                {
                    "k": r["k"],
                    "status": r["status"],
                    "reason": r["reason"][:120],
                    **{f: r[f] for f in ("n_detections", "n_detections_on_tracks", "n_detections_on_stars")},
                    "n_catalog_in_view": r["n_catalog_in_view"],
                }
                for r, b in zip(rows, base)
                if b["status"] == "OK" and r["status"] != "OK"
            ]
        )
    out["load_end"] = list(os.getloadavg())
    return out


def table(res: dict) -> str:
    lines = [
        f"{res['attitudes']} attitudes (seed {res['seed']}), track diffusion {res['diffusion_px']:g} px, "
        f"{res['workers']} workers; machine: {res['machine']}; "
        f"load {res['load_start'][0]:.2f} at start, {res['load_end'][0]:.2f} at end",
        f"{'hits/frame':>10}{'drawn':>8}{'available':>11}{'correct':>9}{'HC wrong':>10}{'low conf':>10}"
        f"{'no sol':>8}{'lost vs 0':>11}{'wall s':>8}",
    ]
    for key, s in res["rates"].items():
        n = s["frames"]
        lines.append(
            f"{key:>10}{s['mean_hits_per_frame']:>8.1f}{s['availability'] * 100:>10.1f}%{s['correct']:>9}"
            f"{s['high_confidence_wrong']:>10}{s['low_confidence']:>10}{s['no_solution']:>8}"
            f"{'-' if s['lost_to_hits'] is None else len(s['lost_to_hits']):>11}{s['wall_s']:>8.0f}"
        )
        lines.append(f"{'':>10}statuses: {', '.join(f'{k} {v}' for k, v in s['status_counts'].items())} (of {n})")
    for key, s in res["rates"].items():
        lost = s["lost_to_hits"] or []
        if lost:
            lines.append(
                f"lost at {key} hits/frame: detections on tracks / on stars / all, per frame: "
                + ", ".join(
                    f"{f['n_detections_on_tracks']}/{f['n_detections_on_stars']}/{f['n_detections']}" for f in lost
                )
                + f"; catalog stars in view: {', '.join(str(f['n_catalog_in_view']) for f in lost)}"
            )
        for f in s["high_confidence_wrong_frames"]:
            lines.append(f"HIGH-CONFIDENCE WRONG at {key} hits/frame: {f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--attitudes", type=int, default=200)
    p.add_argument("--seed", type=int, default=33)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--rates", default="0,5,50", help="mean hits per frame, comma-separated")
    p.add_argument("--diffusion-px", type=float, default=None, help="track diffusion sigma, px (default: the model's)")
    p.add_argument("--json", action="store_true", help="the results as one JSON document")
    args = p.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    if any(not r >= 0 for r in rates) or args.attitudes < 1 or not (args.diffusion_px or 0) >= 0:
        p.error("rates and --diffusion-px must be at least 0 and --attitudes at least 1")
    res = run(args.attitudes, args.seed, args.workers, rates, args.diffusion_px)
    print(json.dumps(res, indent=2) if args.json else table(res))
    return 1 if any(s["high_confidence_wrong"] for s in res["rates"].values()) else 0


if __name__ == "__main__":
    sys.exit(main())
