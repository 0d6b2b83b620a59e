"""Solve time from star vectors and whole-sky throughput.

Prints p50 / p99 / max solve time per frame (serial, one process, scenes generated beforehand)
for: the Enright & McVittie reference scenes in colour mode; the same scenes with the paper's plain
consensus (``k_best=1``, ``anchors=1``, no verification) as the in-run baseline; geometric mode;
and stress scenes (hundreds of detections, all-false frames). Then the whole-sky simulation
throughput in poses/s on 1 process and on all cores (ratio = parallel speed-up).

    .venv/bin/python bench/bench_solver.py [--scenes 3000] [--poses 4000]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.ident.consensus import ConsensusParams
from firmware_model.ident.solver import SolveParams
from firmware_model.ident.strategy import solve
from firmware_model.ident.verify import FieldOfView, VerifyParams
from firmware_model.reference_frames import attitude_from_radec_roll
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.sim import whole_sky as skysim


def scenes(catalog, camera, n, seed, model):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        a = attitude_from_radec_roll(
            rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi)
        )
        out.append(skysim.observe(catalog, a, camera, model, rng))
    return out


def stress_scenes(catalog, camera, n, seed):
    """Half: a real scene buried under 300 false detections (the real stars brightest); half:
    30 false detections and no star."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        a = attitude_from_radec_roll(
            rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi)
        )
        m = 300 if k % 2 == 0 else 30
        fake = camera.pixel_to_vector(rng.uniform(0, camera.width, m), rng.uniform(0, camera.height, m))
        pick = rng.integers(0, catalog.n_stars, m)
        fr, fb = catalog.rg[pick] + rng.normal(0, 0.05, m), catalog.bg[pick] + rng.normal(0, 0.05, m)
        if k % 2 == 0:
            sc = skysim.observe(catalog, a, camera, skysim.ErrorModel(), rng)
            out.append(
                skysim.Scene(
                    np.vstack([sc.vectors, fake]),
                    np.concatenate([sc.rg, fr]),
                    np.concatenate([sc.bg, fb]),
                    np.concatenate([sc.truth, np.full(m, -1)]),
                    sc.n_visible,
                )
            )
        else:
            out.append(skysim.Scene(fake, fr, fb, np.full(m, -1), 0))
    return out


def time_solver(catalog, scs, params, colour=True):
    t = np.empty(len(scs))
    wrong = high = 0
    for k, sc in enumerate(scs):
        rg, bg = (sc.rg, sc.bg) if colour else (None, None)
        t0 = time.perf_counter()
        res = solve(sc.vectors, rg, bg, catalog, params)
        t[k] = time.perf_counter() - t0
        if res.status.value == "HIGH_CONFIDENCE":
            high += 1
            wrong += int(np.any(sc.truth[res.matched_det] != res.matched_cat))
    return t, high, wrong


def row(name, t, base=None, high=0, wrong=0):
    p50, p99, mx = np.percentile(t, 50) * 1e3, np.percentile(t, 99) * 1e3, t.max() * 1e3
    ratio = f"{p50 / (np.percentile(base, 50) * 1e3):7.2f}" if base is not None else "       "
    print(f"{name:44s}{p50:9.3f}{p99:9.3f}{mx:9.3f} {ratio}  {high:6d} {wrong:5d}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=3000)
    ap.add_argument("--poses", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    design = CatalogDesign(sigma_rg=0.05, sigma_bg=0.05)
    catalog = build_catalog(design)
    camera = CameraModel.reference_design()
    fov = FieldOfView.from_camera(camera, 0.0)
    ours = SolveParams(sigma_vec=0.2 / camera.f, fov=fov)
    paper = replace(ours, consensus=ConsensusParams(k_best=1, anchors=1), verify=VerifyParams(enabled=False))
    scs = scenes(catalog, camera, args.scenes, args.seed, skysim.ErrorModel())
    stress = stress_scenes(catalog, camera, max(args.scenes // 10, 20), args.seed + 1)
    solve(scs[0].vectors, scs[0].rg, scs[0].bg, catalog, ours)  # warm caches (neighbour table, KD-tree)
    print(
        f"catalog {catalog.n_stars} stars, {catalog.n_pairs} pairs; {len(scs)} reference scenes "
        f"(mean {np.mean([len(s.truth) for s in scs]):.1f} stars), {len(stress)} stress scenes"
    )
    print(
        f"{'solve time per frame (ms)':44s}{'p50':>9s}{'p99':>9s}{'max':>9s} {'p50/base':>7s}  {'HIGH':>6s} {'wrong':>5s}"
    )
    t_paper, h, w = time_solver(catalog, scs, paper)
    row("baseline: paper consensus (k=1, no verify)", t_paper, None, h, w)
    t_ours, h, w = time_solver(catalog, scs, ours)
    row("colour: backtracking + verification", t_ours, t_paper, h, w)
    t_geo, h, w = time_solver(catalog, scs, replace(ours, mode="geometric"), colour=False)
    row("geometric: 4-star + verification", t_geo, t_paper, h, w)
    t_st, h, w = time_solver(catalog, stress, ours)
    row("stress: 300 false + stars / 30 false only", t_st, t_paper, h, w)
    print(
        f"hard bound (counted): {ours.max_verifications} verifications per solve; "
        f"at most {ours.consensus.max_attempts} attempts x {ours.consensus.k_best} growths, "
        f"{ours.consensus.max_stars} stars matched"
    )
    cfg = skysim.ColourSimConfig(n_boresights=args.poses // 4, n_roll=4, seed=args.seed, solve=replace(ours, fov=fov))
    _, wall1 = skysim.execute("colour", catalog, camera, cfg, args.poses, workers=1, progress=False)
    cores = os.cpu_count() or 1
    _, wall_n = skysim.execute("colour", catalog, camera, cfg, args.poses, workers=cores, progress=False)
    print(
        f"whole-sky throughput: 1 process {args.poses / wall1:.0f} poses/s, {cores} processes "
        f"{args.poses / wall_n:.0f} poses/s (speed-up {wall1 / wall_n:.2f}x)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
