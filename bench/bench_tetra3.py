"""Real frames, end to end: our pipeline (frame file -> attitude) against cedar-solve's
``solve_from_image`` on the 8 ESA tetra3 test frames (../shared/data/frames/tetra3-mono).

Prints per frame: our status, method, matches, residual, wall time (read + detect + fit +
identify + attitude), cedar's wall time (open + extract + solve) and the boresight agreement
in arcseconds, then median time ratio. cedar-solve runs in the benchmark venv:

    python3 -m venv .venv-peers && .venv-peers/bin/pip install --no-deps cedar-solve "numpy<2" scipy pillow
    .venv/bin/python bench/bench_tetra3.py
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FRAMES = ROOT.parent / "shared" / "data" / "frames" / "tetra3-mono"
PEER_PYTHON = ROOT / ".venv-peers" / "bin" / "python"


def main() -> int:
    from firmware_model.camera import CameraModel
    from firmware_model.frame_io import read_frame
    from firmware_model.frames import radec_to_vec
    from firmware_model.pipeline import PipelineParams, run_pipeline, with_psf_sigma
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.solve_report import record_from_output

    if not FRAMES.is_dir():
        print(f"no frames at {FRAMES}; nothing to do")
        return 0
    paths = sorted(FRAMES.glob("*.tiff"))
    camera = CameraModel.from_dict(json.loads((ROOT / "fixtures" / "tetra3_camera.json").read_text()))
    t0 = time.perf_counter()
    catalog = build_catalog(CatalogDesign(theta_fov_deg=4.33, sensor_width_px=1024, sensor_height_px=768,
                                          m_thresh=6.0, phi_min_deg=0.05, phi_max_deg=15.0, epoch=2019.6))
    print(f"catalog: Hipparcos V <= 6.0 at 2019.6, {catalog.n_stars} stars, {catalog.n_pairs} pairs, "
          f"built in {time.perf_counter() - t0:.2f} s (cedar's bundled database is loaded from disk)")
    params = with_psf_sigma(PipelineParams(), 0.6)
    ours = {}
    for rep in range(3):  # best of 3, as for the peer: the machine is shared
        for p in paths:
            t = time.perf_counter()
            rec = record_from_output(run_pipeline(read_frame(p), camera, catalog, params))
            wall = time.perf_counter() - t
            if p.name not in ours or wall < ours[p.name][1]:
                ours[p.name] = (rec, wall)
    cedar = {}
    if PEER_PYTHON.exists():
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "cedar.json"
            for rep in range(3):
                subprocess.run([str(PEER_PYTHON), str(ROOT / "bench" / "tetra3_cedar_runner.py"), str(out),
                                *map(str, paths)], check=True, stderr=subprocess.DEVNULL)
                for k, v in json.loads(out.read_text()).items():
                    name = Path(k).name
                    if name not in cedar or v["wall_s"] < cedar[name]["wall_s"]:
                        cedar[name] = v
    else:
        print(f"(cedar-solve not installed in {PEER_PYTHON.parent.parent}; see the module docstring)")
    print(f"\n{'frame':<26}{'status':<9}{'method':<21}{'stars':>6}{'resid as':>9}{'ours ms':>9}{'cedar ms':>10}"
          f"{'cedar rmse as':>14}{'ratio':>7}{'agree as':>9}")
    ratios, agree = [], []
    for p in paths:
        rec, wall = ours[p.name]
        c = cedar.get(p.name)
        sep = ratio = None
        if c and c["ra"] is not None and rec["ra_deg"] is not None:
            a = radec_to_vec(np.radians(rec["ra_deg"]), np.radians(rec["dec_deg"]))
            b = radec_to_vec(np.radians(c["ra"]), np.radians(c["dec"]))
            sep = float(np.degrees(np.arccos(np.clip(a @ b, -1, 1))) * 3600)
            agree.append(sep)
        if c:
            ratio = c["wall_s"] / wall
            ratios.append(ratio)
        res = rec["residual_rms_arcsec"]
        cells = ["-" if res is None else f"{res:.1f}", f"{wall * 1e3:.1f}",
                 "-" if not c else f"{c['wall_s'] * 1e3:.1f}", "-" if not c or c["rmse"] is None else f"{c['rmse']:.1f}",
                 "-" if ratio is None else f"{ratio:.2f}", "-" if sep is None else f"{sep:.1f}"]
        print(f"{p.name[18:44]:<26}{rec['status']:<9}{rec['method'] or '-':<21}{rec['n_matched']:>6}"
              f"{cells[0]:>9}{cells[1]:>9}{cells[2]:>10}{cells[3]:>14}{cells[4]:>7}{cells[5]:>9}")
    solved = sum(ours[p.name][0]["status"] == "OK" for p in paths)
    print(f"\nours: {solved}/{len(paths)} solved (high confidence); median wall {np.median([w for _, w in ours.values()]) * 1e3:.1f} ms")
    if ratios:
        print(f"cedar-solve: {sum(1 for c in cedar.values() if c['ra'] is not None)}/{len(paths)} solved; "
              f"median wall {np.median([c['wall_s'] for c in cedar.values()]) * 1e3:.1f} ms; "
              f"time ratio cedar/ours median {np.median(ratios):.2f} (min {min(ratios):.2f}, max {max(ratios):.2f})")
    if agree:
        print(f"boresight agreement with cedar-solve: median {np.median(agree):.1f} arcsec, max {max(agree):.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
