"""The bright-body exclusion against the Sun's glare: per Sun exclusion angle, seeded random
attitudes with the Sun at 0.5, 0.9, 1.1, 1.5 and 3 times that angle from the boresight (to its
disc edge, as the check measures), rendered with the Sun's and the Moon's light
(``ground.sim.exposure.ExposureRenderer`` with the exposure's time: ``ground.sim.glare``), solved
offline by ``run_pipeline`` with the check (``DeviceParams(sun_exclusion_deg=L,
moon_exclusion_deg=0, earth_exclusion_deg=0)``: the Sun alone decides; no spacecraft position:
no Earth) and, on the same frames, without it (``exclusion=None``). Per cell: frames with an
attitude (OK or LOW_CONFIDENCE), the statuses, and high-confidence wrong attitudes (status OK,
more than ``CORRECT_DEG`` from the truth), which must be 0: the bench exits 1 when one is not,
after printing it.

    .venv/bin/python bench/bench_exclusion.py [--n 1000] [--limits 30] [--seed 33] [--workers 1] [--json]

Frame ``k`` of a cell draws from ``default_rng([seed, limit index, factor index, k])``: the
same frames whatever the worker count. The reference-design camera, ``DetectorModel()`` and the
default catalog (``CatalogDesign()``), at one epoch (:data:`EPOCH`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import cpu_name  # noqa: E402

EPOCH = "2026-03-20T12:00:00+00:00"  #: the exposure mid-time of every frame (UTC)
FACTORS = (0.5, 0.9, 1.1, 1.5, 3.0)  #: the Sun's edge angle from the boresight over the limit
CORRECT_DEG = 0.1  #: attitude error bound of a correct solve (deg), ground.analysis.replay.CORRECT_DEG

_CTX: dict = {}


def _context():
    """(camera, detector, catalog, renderer, Sun), built once per process."""
    if not _CTX:
        from firmware_model.camera import CameraModel
        from firmware_model.pipeline.sky_bodies import sky_bodies
        from ground.catalog.build import build_catalog
        from ground.catalog.design import CatalogDesign
        from ground.sim.exposure import ExposureRenderer
        from ground.sim.sensor_sim import DetectorModel

        camera = CameraModel.reference_design()
        _CTX.update(
            camera=camera,
            det=DetectorModel(),
            catalog=build_catalog(CatalogDesign()),
            renderer=ExposureRenderer(camera),
            sun=sky_bodies(EPOCH)["sun"],
        )
    return _CTX


def attitude_near_sun(rng: np.random.Generator, sun, edge_deg: float) -> np.ndarray:
    """A matrix A whose boresight is ``edge_deg`` from the Sun's disc edge, in a uniformly drawn
    direction around it, with a uniformly drawn roll."""
    from firmware_model.reference_frames import attitude_from_radec_roll, vec_to_radec

    s = sun.direction
    u = rng.standard_normal(3)
    u -= (u @ s) * s
    u /= np.linalg.norm(u)
    theta = np.radians(edge_deg) + sun.angular_radius
    b = np.cos(theta) * s + np.sin(theta) * u
    ra, dec = vec_to_radec(b)
    return attitude_from_radec_roll(float(ra), float(dec), rng.uniform(0, 2 * np.pi))


def _outcome(out, a_true: np.ndarray) -> dict:
    from firmware_model.reference_frames import quat_to_matrix, rotation_angle

    sol = out.solution
    row = {"status": out.status.name, "reason": out.reason[:100], "error_deg": None}
    if sol is not None and sol.q_icrs_to_sensor is not None:
        row["error_deg"] = float(np.degrees(rotation_angle(quat_to_matrix(sol.q_icrs_to_sensor), a_true)))
    return row


def run_frame(job: tuple) -> dict:
    """One frame: (seed, limit index, limit deg, factor index, k) -> its outcome with and without the check."""
    from firmware_model.device.sensor_input import DeviceParams
    from firmware_model.pipeline.run import run_pipeline
    from firmware_model.pipeline.solve_types import PipelineParams

    seed, li, limit, fi, k = job
    ctx = _context()
    rng = np.random.default_rng([seed, li, fi, k])
    a = attitude_near_sun(rng, ctx["sun"], FACTORS[fi] * limit)
    frame = ctx["renderer"].render(a, ctx["det"], seed=int(rng.integers(2**31)), epoch_utc=EPOCH)
    checked = DeviceParams(sun_exclusion_deg=limit, moon_exclusion_deg=0.0, earth_exclusion_deg=0.0)
    on = run_pipeline(frame, ctx["camera"], ctx["catalog"], checked.apply(PipelineParams()))
    off = run_pipeline(frame, ctx["camera"], ctx["catalog"], PipelineParams(exclusion=None))
    return {"limit": limit, "factor": FACTORS[fi], "k": k, "on": _outcome(on, a), "off": _outcome(off, a)}


def _summary(rows: list[dict], key: str) -> dict:
    outs = [r[key] for r in rows]
    with_attitude = [o for o in outs if o["error_deg"] is not None]
    wrong = [o for o in outs if o["status"] == "OK" and o["error_deg"] > CORRECT_DEG]
    return {
        "frames": len(outs),
        "with_attitude": len(with_attitude),
        "correct": sum(o["error_deg"] <= CORRECT_DEG for o in with_attitude),
        "statuses": dict(Counter(o["status"] for o in outs).most_common()),
        "high_confidence_wrong": len(wrong),
        "low_confidence_wrong": sum(o["status"] == "LOW_CONFIDENCE" and o["error_deg"] > CORRECT_DEG for o in outs),
    }


def run(n: int, limits: list[float], seed: int, workers: int) -> dict:
    jobs = [(seed, li, lim, fi, k) for li, lim in enumerate(limits) for fi in range(len(FACTORS)) for k in range(n)]
    load0, t0 = list(os.getloadavg()), time.perf_counter()
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            rows = list(pool.map(run_frame, jobs, chunksize=max(1, len(jobs) // (4 * workers))))
    else:
        rows = [run_frame(j) for j in jobs]
    cells = []
    for lim in limits:
        for f in FACTORS:
            cell = [r for r in rows if r["limit"] == lim and r["factor"] == f]
            wrong = [r for r in cell if r["on"]["status"] == "OK" and r["on"]["error_deg"] > CORRECT_DEG]
            cells.append(
                {
                    "limit_deg": lim,
                    "factor": f,
                    "sun_edge_deg": f * lim,
                    "check": _summary(cell, "on"),
                    "no_check": _summary(cell, "off"),
                    "high_confidence_wrong_frames": wrong,
                }
            )
    return {
        "n_per_cell": n,
        "seed": seed,
        "workers": workers,
        "epoch": EPOCH,
        "machine": f"{os.cpu_count()} cores, {cpu_name()}",
        "load_start": load0,
        "load_end": list(os.getloadavg()),
        "wall_s": time.perf_counter() - t0,
        "cells": cells,
    }


def table(res: dict) -> str:
    lines = [
        f"{res['n_per_cell']} frames per cell (seed {res['seed']}), {res['workers']} workers, {res['wall_s']:.0f} s; "
        f"machine: {res['machine']}; load {res['load_start'][0]:.2f} at start, {res['load_end'][0]:.2f} at end",
        "with the check: frames with an attitude (correct of them), high- and low-confidence wrong; the same"
        " frames without it; the statuses with it",
        f"{'limit':>6}{'Sun edge':>10}{'attitude':>17}{'HC wrong':>10}{'LC wrong':>10}  |{'no check':>17}"
        f"{'HC wrong':>10}{'LC wrong':>10}  statuses",
    ]
    for c in res["cells"]:
        on, off = c["check"], c["no_check"]
        cells = []
        for s in (on, off):
            got = f"{s['with_attitude']}/{s['frames']} ({s['correct']})"
            cells.append(f"{got:>17}{s['high_confidence_wrong']:>10}{s['low_confidence_wrong']:>10}")
        lines.append(
            f"{c['limit_deg']:>6g}{c['sun_edge_deg']:>8.1f} deg{cells[0]}  |{cells[1]}  "
            + ", ".join(f"{k} {v}" for k, v in on["statuses"].items())
        )
    for c in res["cells"]:
        for f in c["high_confidence_wrong_frames"]:
            lines.append(f"HIGH-CONFIDENCE WRONG (limit {c['limit_deg']:g}, x{c['factor']:g}): {f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=1000, help="frames per limit and Sun angle (the issue asks 1000)")
    p.add_argument("--limits", default="30", help="Sun exclusion angles, deg, comma-separated (0-90)")
    p.add_argument("--seed", type=int, default=33)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--json", action="store_true", help="the results as one JSON document")
    args = p.parse_args(argv)
    try:
        limits = [float(v) for v in args.limits.split(",")]
    except ValueError:
        p.error(f"--limits must be numbers, got {args.limits!r}")
    if args.n < 1 or args.workers < 1 or not all(0 < v <= 90 for v in limits):
        p.error("--n and --workers must be at least 1 and each limit in (0, 90] deg")
    res = run(args.n, limits, args.seed, args.workers)
    print(json.dumps(res, indent=2) if args.json else table(res))
    return 1 if any(c["check"]["high_confidence_wrong"] for c in res["cells"]) else 0


if __name__ == "__main__":
    sys.exit(main())
