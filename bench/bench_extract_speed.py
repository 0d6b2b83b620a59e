"""Extraction speed: detect, fit and detect + fit medians per frame, as
``extract_stars`` runs them (every PSF pass counted), on full 2592 x 1944 RGGB frames rendered from
the real sky (reference design, random attitudes) and on the eight tetra3 mono frames
(../shared/data/frames/tetra3-mono, 1024 x 768), single-threaded.

Each stage is timed by the thread's CPU time (``time.thread_time``, insensitive to other jobs on a
shared machine) and by the wall clock; the baseline, measured in the same loop on the same frame,
is one ``np.sum`` pass over the raw pixels (memory speed): "x sum" is the stage over it.
Targets: full frame detect + fit <= 15 ms, tetra3 <= 10 ms (median).

``--files NAME ...``: instead, a per-stage profile of the file solve of the real frames whose names
contain NAME (../shared/data/frames), as ``bench_peers.py`` runs ours: reading, detection, fit and
identification (the rest of ``run_pipeline``: identification, attitude, optics search), thread
CPU time, median and 90th percentile of ``--repeats`` after one untimed solve. Run with
``PYTHONPATH=DIR`` (an export of an earlier commit) it profiles that code the same way.

    .venv/bin/python bench/bench_extract_speed.py [--rggb-frames 6] [--repeats 5]
    .venv/bin/python bench/bench_extract_speed.py --files pifinder_debug_01 openstartracker_img0 [--repeats 9]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

import firmware_model.pipeline.extract as extract_mod  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TETRA3 = ROOT.parent / "shared" / "data" / "frames" / "tetra3-mono"
STAGES = ("detect", "fit")


class _StageClock:
    """Wraps the detection and fit that ``extract_stars`` calls, adding up CPU and wall time."""

    def __init__(self) -> None:
        self.cpu = dict.fromkeys(STAGES, 0.0)
        self.wall = dict.fromkeys(STAGES, 0.0)
        # detection: the PSF-independent preparation (once per frame, when the code has it) and the
        # detection of each PSF pass
        self._names = {"detect_stars": "detect", "fit_stars": "fit", "prepare_detection": "detect"}
        for name, stage in self._names.items():
            if hasattr(extract_mod, name):
                setattr(extract_mod, name, self._wrap(stage, getattr(extract_mod, name)))

    def _wrap(self, stage: str, fn):
        def timed(*args, **kwargs):
            c0, t0 = time.thread_time(), time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.cpu[stage] += time.thread_time() - c0
                self.wall[stage] += time.perf_counter() - t0

        return timed

    def reset(self) -> None:
        self.cpu = dict.fromkeys(STAGES, 0.0)
        self.wall = dict.fromkeys(STAGES, 0.0)


def rggb_frames(n: int):
    from firmware_model.camera import CameraModel
    from firmware_model.reference_frames import attitude_from_radec_roll
    from ground.sim.sensor_sim import DetectorModel, render_frame
    from ground.sim.sky_model import sky_stars

    cam = CameraModel.reference_design()
    out = []
    for k in range(n):
        rng = np.random.default_rng(1200 + k)
        a = attitude_from_radec_roll(
            rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi)
        )
        out.append(render_frame(sky_stars(), a, cam, DetectorModel(pattern="RGGB"), seed=1200 + k).frame)
    return out


def tetra3_frames():
    from firmware_model.pipeline.frame_readers import read_frame

    return [read_frame(p) for p in sorted(TETRA3.glob("*.tiff"))] if TETRA3.is_dir() else []


def measure(frames, repeats: int, clock: _StageClock) -> dict:
    """Per (frame, repeat) samples: cpu/wall per stage and total, the np.sum baseline, stars, passes."""
    rows: dict[str, list[float]] = {k: [] for k in ("base_cpu", "base_wall", "stars", "passes")}
    for kind in ("cpu", "wall"):
        for s in (*STAGES, "total"):
            rows[f"{s}_{kind}"] = []
    for f in frames:
        extract_mod.extract_stars(f)  # warm caches (and any first-call cost) outside the timing
        for _ in range(repeats):
            c0, t0 = time.thread_time(), time.perf_counter()
            f.pixels.sum()
            rows["base_cpu"].append(time.thread_time() - c0)
            rows["base_wall"].append(time.perf_counter() - t0)
            clock.reset()
            s = extract_mod.extract_stars(f)
            for kind, d in (("cpu", clock.cpu), ("wall", clock.wall)):
                for st in STAGES:
                    rows[f"{st}_{kind}"].append(d[st])
                rows[f"total_{kind}"].append(d["detect"] + d["fit"])
            rows["stars"].append(len(s))
            rows["passes"].append(s.psf_passes)
    return {k: np.asarray(v) for k, v in rows.items()}


def report(name: str, r: dict, target_ms: float) -> None:
    base_cpu, base_wall = np.median(r["base_cpu"]) * 1e3, np.median(r["base_wall"]) * 1e3
    print(
        f"\n{name}: {len(r['stars'])} runs, median {np.median(r['stars']):.0f} stars, "
        f"{np.median(r['passes']):.0f} PSF pass(es); baseline one np.sum pass: CPU {base_cpu:.2f} ms, "
        f"wall {base_wall:.2f} ms"
    )
    print(f"  {'stage':<14}{'CPU ms':>8}{'x sum':>8}{'wall ms':>9}{'x sum':>8}{'CPU p90':>9}")
    for st in (*STAGES, "total"):
        cpu, wall = np.median(r[f"{st}_cpu"]) * 1e3, np.median(r[f"{st}_wall"]) * 1e3
        label = "detect+fit" if st == "total" else st
        print(
            f"  {label:<14}{cpu:8.2f}{cpu / base_cpu:8.1f}{wall:9.2f}{wall / base_wall:8.1f}"
            f"{np.percentile(r[f'{st}_cpu'], 90) * 1e3:9.2f}"
        )
    cpu_total = np.median(r["total_cpu"]) * 1e3
    print(f"  target detect+fit <= {target_ms:.0f} ms: {'met' if cpu_total <= target_ms else 'NOT met'} (CPU median)")


def profile_files(names: list[str], repeats: int, clock: _StageClock) -> None:
    """Per-stage CPU profile of the file solve of each real frame named (module docstring)."""
    import sys

    sys.path.insert(0, str(ROOT / "bench"))
    from bench_realframes import frames

    from firmware_model.camera import CameraModel
    from firmware_model.pipeline.frame_readers import read_frame
    from firmware_model.pipeline.run import run_pipeline
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    print(f"code from {Path(extract_mod.__file__).parents[2]}")
    print(f"  {'frame':<30}{'stage':<16}{'CPU ms':>8}{'p90':>8}")
    for job in [j for j in frames() if any(n in j["path"].name for n in names)]:
        frame = read_frame(job["path"])
        if job.get("datasheet"):
            camera = CameraModel.from_focal(frame.width, frame.height, *job["datasheet"])
        else:
            camera = CameraModel.from_horizontal_fov(frame.width, frame.height, job["fov"])
        catalog = build_catalog(CatalogDesign.for_field(frame.width, frame.height, job["fov"]))
        run_pipeline(frame, camera, catalog)  # warm
        rows: dict[str, list[float]] = {k: [] for k in ("read", "detect", "fit", "identification", "total")}
        status = ""
        for _ in range(repeats):
            c0 = time.thread_time()
            frame = read_frame(job["path"])
            c1 = time.thread_time()
            clock.reset()
            out = run_pipeline(frame, camera, catalog)
            c2 = time.thread_time()
            status = out.status.name
            rows["read"].append(c1 - c0)
            rows["detect"].append(clock.cpu["detect"])
            rows["fit"].append(clock.cpu["fit"])
            rows["identification"].append(c2 - c1 - clock.cpu["detect"] - clock.cpu["fit"])
            rows["total"].append(c2 - c0)
        label = f"{job['path'].name[:22]} {frame.width}x{frame.height} {frame.pattern}"
        for k, (st, v) in enumerate(rows.items()):
            name = label if k == 0 else (status if k == 1 else "")
            print(f"  {name[:29]:<30}{st:<16}{np.median(v) * 1e3:8.2f}{np.percentile(v, 90) * 1e3:8.2f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rggb-frames", type=int, default=6, help="full-size rendered RGGB frames")
    ap.add_argument("--repeats", type=int, default=5, help="timed extractions per frame")
    ap.add_argument("--files", nargs="+", metavar="NAME", help="profile the file solve of these real frames")
    args = ap.parse_args(argv)
    clock = _StageClock()
    print(f"extract_stars, single-threaded; 1-min load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    if args.files:
        profile_files(args.files, args.repeats, clock)
        print(f"1-min load average at the end {os.getloadavg()[0]:.2f}")
        return 0
    report(
        "2592 x 1944 RGGB, real sky, reference design",
        measure(rggb_frames(args.rggb_frames), args.repeats, clock),
        15.0,
    )
    t3 = tetra3_frames()
    if t3:
        report("tetra3 1024 x 768 mono (8 frames)", measure(t3, args.repeats, clock), 10.0)
    else:
        print(f"\n(no tetra3 frames under {TETRA3})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
