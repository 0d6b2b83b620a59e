"""End-to-end figures (printed; nothing here is a unit test).

A. Solve rate and attitude error over N rendered frames at uniformly random attitudes with the
   Enright & McVittie reference design (2592 x 1944, 7.5 deg half-angle minor axis, 100 ms), by method:
   RGGB frames (colour method) and MONO frames (geometric), through the device pipeline
   in-process (the code the device runs), frames rendered from the real sky to V 6.5.
B. GO to result ready on full-size frames on the device over a pty (capture source --frames,
   so no upload), per stage, unpaced; and the whole exchange (GO, polling, READ RESULT) at a
   paced 115200 baud, with the line-rate minimum of the result read as the baseline.

    .venv/bin/python bench/bench_e2e.py [--frames 200] [--workers 2] [--out out/bench_e2e]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402


def _one(args):
    k, pattern, seed = args
    from firmware_model.camera import CameraModel
    from firmware_model.pipeline.run import run_pipeline
    from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat
    from ground.analysis.replay import Truth, score
    from ground.link.solve_report import record_from_output
    from ground.sim.sensor_sim import DetectorModel, render_frame
    from ground.sim.sky_model import sky_stars

    cat = _catalog()
    cam = CameraModel.reference_design()
    rng = np.random.default_rng(seed + k)
    a = attitude_from_radec_roll(rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi))
    r = render_frame(sky_stars(), a, cam, DetectorModel(pattern=pattern), seed=seed + k)
    t0 = time.perf_counter()
    out = run_pipeline(r.frame, cam, cat)
    wall = time.perf_counter() - t0
    rec = record_from_output(out)
    truth = Truth(
        matrix_to_quat(a),
        np.array([s["id"] for s in r.truth["stars"]], dtype=np.int64),
        np.array([s["x"] for s in r.truth["stars"]]),
        np.array([s["y"] for s in r.truth["stars"]]),
    )
    n_cat = sum(1 for s in r.truth["stars"] if s["vmag"] <= 5.0)
    return {
        "pattern": pattern,
        "status": rec["status"],
        "method": rec["method"],
        "wall_s": wall,
        "timings": rec["timings_s"],
        "n_catalog_in_view": n_cat,
        **score(rec, truth),
    }


_CAT = None


def _catalog():
    global _CAT
    if _CAT is None:
        from ground.catalog.build import build_catalog
        from ground.catalog.design import CatalogDesign

        _CAT = build_catalog(CatalogDesign())
    return _CAT


def part_a(n: int, workers: int, seed: int, out: Path) -> None:
    jobs = [(k, p, seed) for p in ("RGGB", "MONO") for k in range(n)]
    with ProcessPoolExecutor(workers) as ex:
        rows = list(tqdm(ex.map(_one, jobs, chunksize=4), total=len(jobs), desc="render+solve"))
    (out / "part_a.json").write_text(json.dumps(rows))
    print(f"\nA. {n} random attitudes per pattern, reference design, real sky to V 6.5, catalog Hipparcos V <= 5.0")
    print(
        f"{'frames':<8}{'method(s)':<30}{'correct':>9}{'wrong':>7}{'wrong&OK':>10}{'no att.':>9}"
        f"{'OK':>6}{'LOW':>6}{'err p50 (as)':>14}{'p90':>8}{'<=0.01deg':>11}"
    )
    for pattern in ("RGGB", "MONO"):
        rs = [r for r in rows if r["pattern"] == pattern]
        methods = sorted({r["method"] for r in rs if r["method"]})
        correct = sum(r["outcome"] == "correct" for r in rs)
        wrong = [r for r in rs if r["outcome"] == "wrong"]
        wrong_ok = sum(r["status"] == "OK" for r in wrong)
        errs = np.array([r["attitude_error_deg"] for r in rs if r["outcome"] == "correct"]) * 3600
        within = np.mean([r["outcome"] == "correct" and r["attitude_error_deg"] <= 0.01 for r in rs])
        print(
            f"{pattern:<8}{','.join(methods):<30}{correct / n:>9.1%}{len(wrong) / n:>7.1%}{wrong_ok:>10}"
            f"{sum(r['outcome'] == 'no_match' for r in rs) / n:>9.1%}{sum(r['status'] == 'OK' for r in rs):>6}"
            f"{sum(r['status'] == 'LOW_CONFIDENCE' for r in rs):>6}"
            f"{np.median(errs):>14.2f}{np.percentile(errs, 90):>8.2f}{within:>11.1%}"
        )
        few = [r for r in rs if r["outcome"] == "no_match"]
        if few:
            print(
                f"        no attitude: median {np.median([r['n_catalog_in_view'] for r in few]):.0f} catalog stars "
                f"in view (all frames: {np.median([r['n_catalog_in_view'] for r in rs]):.0f})"
            )
        for stage in ("detect", "fit", "identify", "attitude", "total"):
            t = np.array([r["timings"][stage] for r in rs]) * 1e3
            print(
                f"        {stage:<9} median {np.median(t):7.1f} ms   p95 {np.percentile(t, 95):7.1f} ms   max {t.max():7.1f} ms"
            )


def part_b(n: int, out: Path) -> None:
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_to_image
    from ground.link.client import Client
    from ground.link.solve_report import solve_record
    from ground.sim.device_process import pick_attitudes, start_device, stop_device
    from ground.sim.frame_writer import write_frame
    from ground.sim.sensor_sim import DetectorModel, render_frame
    from ground.sim.sky_model import sky_stars
    from protocol import result

    cat = _catalog()
    image = catalog_to_image(cat)
    atts = pick_attitudes(cat, CameraModel.reference_design(), n, np.random.default_rng(5))
    frames = out / "device_frames"
    frames.mkdir(exist_ok=True)
    for k, a in enumerate(atts):
        r = render_frame(sky_stars(), a, CameraModel.reference_design(), DetectorModel(), seed=k)
        write_frame(r.frame, frames / f"g{k:03d}.dng")
    print(
        f"\nB. GO to result on the device (st16-device --pty --frames: {n} full-size RGGB DNG frames read by the device)"
    )
    with tempfile.TemporaryDirectory() as state:
        for paced in (False, True):
            extra = ["--frames", str(frames)] + (["--baud", "115200", "--pace"] if paced else [])
            proc, pty = start_device(Path(state), *extra)
            try:
                with Client(pty, timeout=5.0) as c:
                    c.init()
                    if not paced:  # the paced run finds the catalog persisted in the state directory
                        c.upload(0, image, progress=False)
                    assert c.slot_info(0).active
                    go_to_ready, exchange, stages = [], [], []
                    for _ in range(n):
                        t0 = time.perf_counter()
                        c.go()
                        while c.result_length() == 0:
                            time.sleep(0.002)
                        t1 = time.perf_counter()
                        rec = solve_record(result.parse(c.read_result()))
                        t2 = time.perf_counter()
                        go_to_ready.append(t1 - t0)
                        exchange.append(t2 - t0)
                        stages.append(rec["timings_s"])
            finally:
                stop_device(proc)
            go_to_ready, exchange = np.array(go_to_ready) * 1e3, np.array(exchange) * 1e3
            label = "paced 115200 baud" if paced else "unpaced pty"
            print(
                f"  {label}: GO -> result ready median {np.median(go_to_ready):.0f} ms (p95 "
                f"{np.percentile(go_to_ready, 95):.0f}); whole exchange incl. READ RESULT of {result.TOTAL_LENGTH} B "
                f"median {np.median(exchange):.0f} ms (p95 {np.percentile(exchange, 95):.0f})"
            )
            if paced:
                line_min = result.TOTAL_LENGTH * 10 / 115200 * 1e3
                print(
                    f"    baseline: READ RESULT payload alone at line rate {line_min:.0f} ms; "
                    f"exchange / (device total + line minimum) = "
                    f"{np.median(exchange) / (np.median([s['total'] for s in stages]) * 1e3 + line_min):.2f}"
                )
            else:
                for stage in ("detect", "fit", "vectors", "identify", "attitude", "total"):
                    t = np.array([s[stage] for s in stages]) * 1e3
                    print(
                        f"    device stage {stage:<9} median {np.median(t):7.1f} ms  p95 {np.percentile(t, 95):7.1f} ms"
                    )
                print("    (GO -> ready adds reading the DNG file: the capture)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200, help="random attitudes per pattern (part A)")
    ap.add_argument("--device-frames", type=int, default=10, help="GO cycles on the device (part B)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--out", default="out/bench_e2e")
    ap.add_argument("--skip-a", action="store_true")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.skip_a:
        part_a(args.frames, args.workers, args.seed, out)
    part_b(args.device_frames, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
