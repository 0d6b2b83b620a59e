"""Runs a peer solver on centroid sets; executed by bench_peers.py inside .venv-peers (peer code
never enters the project environment).

    .venv-peers/bin/python bench/peer_runner.py {cedar|tetra3rs} IN.npz OUT.npz

``IN.npz``: pixel centroids ``x``, ``y`` in our convention (zero-based, pixel centres at integer
coordinates), brightest first, ``offsets`` delimiting frames, ``size`` (H, W), ``fov_deg``
(horizontal), ``targets`` (K, 2) pixels (x, y) in our convention. ``OUT.npz``: per frame the solved
flag, RA/Dec (deg) of each target pixel, matches and wall time (s). Serial, database load excluded.

Conventions converted here: cedar takes (y, x) from the top-left corner of the array with pixel
centres at +0.5; tetra3rs takes (x, y) from the array centre, +x right, +y down.
"""

import sys
import time
from pathlib import Path

import numpy as np


def cedar_solver(size, fov):
    import tetra3

    t3 = tetra3.Tetra3()  # bundled database (10-30 deg)

    def run(x, y, tx, ty):
        r = t3.solve_from_centroids(
            np.stack([y + 0.5, x + 0.5], axis=1),
            size,
            fov_estimate=fov,
            fov_max_error=0.01 * fov,
            distortion=0,
            target_pixel=np.stack([ty + 0.5, tx + 0.5], axis=1),
        )
        if r.get("RA") is None:
            return None
        return np.array(r["RA_target"]), np.array(r["Dec_target"]), int(r["Matches"])

    return run


def tetra3rs_solver(size, fov):
    import tetra3rs

    h, w = size
    path = Path(__file__).resolve().parents[1] / ".venv-peers" / f"tetra3rs_db_{fov:g}.bin"
    if path.exists():
        db = tetra3rs.SolverDatabase.load_from_file(str(path))
    else:
        db = tetra3rs.SolverDatabase.generate_from_gaia(max_fov_deg=fov * 1.05, min_fov_deg=fov * 0.95)
        db.save_to_file(str(path))
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0

    def run(x, y, tx, ty):
        r = db.solve_from_centroids(
            np.stack([x - cx, y - cy], axis=1),
            fov_estimate_deg=fov,
            image_width=w,
            image_height=h,
            fov_max_error_deg=0.01 * fov,
            match_max_error=0.002,
        )
        if not r:
            return None
        ra, dec = r.pixel_to_world(tx - cx, ty - cy)
        return np.asarray(ra), np.asarray(dec), int(r.num_matches)

    return run


def main(peer, inp, out):
    d = np.load(inp)
    size = tuple(int(v) for v in d["size"])
    fov = float(d["fov_deg"])
    run = {"cedar": cedar_solver, "tetra3rs": tetra3rs_solver}[peer](size, fov)
    x, y, off, targets = d["x"], d["y"], d["offsets"], d["targets"]
    n = len(off) - 1
    solved = np.zeros(n, bool)
    radec = np.full((n, len(targets), 2), np.nan)
    matches = np.zeros(n, int)
    wall = np.zeros(n)
    for k in range(n):
        s = slice(off[k], off[k + 1])
        t0 = time.perf_counter()
        res = run(x[s], y[s], targets[:, 0], targets[:, 1])
        wall[k] = time.perf_counter() - t0
        if res is not None:
            solved[k] = True
            radec[k, :, 0], radec[k, :, 1], matches[k] = res
    np.savez(out, solved=solved, radec=radec, matches=matches, wall=wall)


if __name__ == "__main__":
    main(*sys.argv[1:4])
