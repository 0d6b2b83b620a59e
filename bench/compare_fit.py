"""Old versus new centroid fit in one run: the per-star fit of a git revision of
``firmware_model/pipeline/centroid.py`` (default aa69eb2, the last one with one
``scipy.optimize.least_squares`` call per star) against the working tree's batched fit, on
the same detections.

Prints fit time per frame (median of repeats, BLAS threads limited to one) for rendered
2592 x 1944 reference frames (~20 stars) and for a real tetra3 frame, the agreement of the
two fits star by star, and centroid / colour RMS against truth on rendered frames.

Run: ``.venv/bin/python bench/compare_fit.py [--rev aa69eb2] [--frames 6] [--speed-frames 3]``.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from firmware_model.camera import CameraModel  # noqa: E402
from firmware_model.pipeline import centroid as new  # noqa: E402
from firmware_model.pipeline.detect import DetectParams, detect_stars  # noqa: E402
from firmware_model.pipeline.frame_readers import read_frame  # noqa: E402
from firmware_model.reference_frames import attitude_from_radec_roll  # noqa: E402
from ground.sim.sensor_sim import DetectorModel, random_star_field, render_frame  # noqa: E402
from protocol.star_flags import StarFlag  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared/data/frames/tetra3-mono/2019-07-29T204726_Alt40_Azi135_Try1.tiff"


def load_old(rev: str):
    src = subprocess.run(
        ["git", "-C", str(ROOT), "show", f"{rev}:firmware_model/pipeline/centroid.py"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    path = Path(tempfile.mkdtemp()) / "centroid_old.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("centroid_old", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["centroid_old"] = mod
    spec.loader.exec_module(mod)
    return mod


def timed(mod, frame, det, sigma, repeats):
    params = mod.FitParams(psf_sigma_px=sigma)
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = mod.fit_stars(frame, det, params)
        t.append(time.perf_counter() - t0)
    return res, float(np.median(t))


def agreement(a, b):
    both = np.isfinite(a.x) & np.isfinite(b.x)
    d = np.hypot(a.x - b.x, a.y - b.y)[both]
    drg = np.abs(a.rg - b.rg)
    drg = drg[np.isfinite(drg)]
    failed = lambda r: int(np.count_nonzero(r.flags & int(StarFlag.FIT_FAILED)))  # noqa: E731
    return (
        f"max |centre diff| {d.max() if len(d) else float('nan'):.2e} px, max |rg diff| "
        f"{drg.max() if len(drg) else float('nan'):.2e}, flags differ on {int(np.count_nonzero(a.flags != b.flags))}, "
        f"sharp differ on {int(np.count_nonzero(a.sharp != b.sharp))}, FIT_FAILED old/new {failed(a)}/{failed(b)}"
    )


def rms(v):
    v = np.asarray(v)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v**2))) if len(v) else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rev", default="aa69eb2", help="git revision of the per-star fit")
    ap.add_argument("--frames", type=int, default=6, help="rendered frames per sensor for accuracy")
    ap.add_argument("--speed-frames", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    old = load_old(args.rev)
    cam = CameraModel.reference_design()

    print(f"speed: old = {args.rev} per-star least_squares, new = working tree batched LM; median of {args.repeats}")
    det_model = DetectorModel()
    for k in range(args.speed_frames):
        att = attitude_from_radec_roll(0.3 * k, 0.2, 0.0)
        stars = random_star_field(cam, att, 20, vmag_range=(2.0, 6.0), seed=500 + k, min_separation_px=30)
        frame = render_frame(stars, att, cam, det_model, seed=600 + k).frame
        d = detect_stars(frame)
        a, ta = timed(old, frame, d, 1.0, args.repeats)
        b, tb = timed(new, frame, d, 1.0, args.repeats)
        print(
            f"  rendered 2592x1944 #{k}: {len(d)} stars: old {1e3 * ta:.1f} ms, new {1e3 * tb:.1f} ms "
            f"({ta / tb:.1f}x); {agreement(a, b)}"
        )
    if REAL.exists():
        frame = read_frame(REAL)
        d = detect_stars(frame, DetectParams(psf_sigma_px=0.6))
        a, ta = timed(old, frame, d, 0.6, args.repeats)
        b, tb = timed(new, frame, d, 0.6, args.repeats)
        print(
            f"  real {REAL.name} (psf 0.6): {len(d)} stars: old {1e3 * ta:.1f} ms, new {1e3 * tb:.1f} ms "
            f"({ta / tb:.1f}x); {agreement(a, b)}"
        )

    for name, dm, seed0 in (("colour", DetectorModel(pattern="RGGB"), 0), ("mono", DetectorModel(pattern="MONO"), 50)):
        errs = {"old": [], "new": []}
        for k in range(args.frames):
            rng = np.random.default_rng(seed0 + k)
            att = attitude_from_radec_roll(rng.uniform(0, 2 * np.pi), rng.uniform(-1.3, 1.3), rng.uniform(0, 2 * np.pi))
            stars = random_star_field(cam, att, 30, vmag_range=(1.0, 7.5), seed=seed0 + k, min_separation_px=30)
            res = render_frame(stars, att, cam, dm, seed=seed0 + 1000 + k)
            d = detect_stars(res.frame)
            for label, mod in (("old", old), ("new", new)):
                f = mod.fit_stars(res.frame, d, mod.FitParams(psf_sigma_px=dm.psf_sigma_px))
                for t in res.truth["stars"]:
                    dist = np.hypot(f.x - t["x"], f.y - t["y"])
                    if len(dist) and dist.min() < 2.0:
                        j = int(np.argmin(dist))
                        errs[label].append(
                            (
                                dist[j],
                                f.rg[j] - t["rg"],
                                f.bg[j] - t["bg"],
                                t["vmag"],
                                bool(f.flags[j] & int(StarFlag.FIT_FAILED)),
                            )
                        )
        for label in ("old", "new"):
            e = np.array(errs[label], float)
            bright = e[:, 3] < 4.5
            line = (
                f"[{name}] {label}: {len(e)} matched, FIT_FAILED {int(e[:, 4].sum())}; centroid RMS all "
                f"{rms(e[:, 0]):.4f} px, V<4.5 {rms(e[bright, 0]):.4f} px"
            )
            if name == "colour":
                line += (
                    f"; rg RMS all {rms(e[:, 1]):.4f}, V<4.5 {rms(e[bright, 1]):.4f}; "
                    f"bg RMS all {rms(e[:, 2]):.4f}, V<4.5 {rms(e[bright, 2]):.4f}"
                )
            print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
