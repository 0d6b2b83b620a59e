"""Same answers under load, and what the counted budgets cost at worst on this machine.

Part 1, same answers: the 15 real frames of ../shared/data/frames (8 tetra3 mono, 7 colour-real),
each solved with its field of view only (``ground.api.solve_image``), and the impaired whole sky
(``st16-ground sim colour``, 3 false stars per frame, 10 % dropped, 1000 boresights x 2 rolls,
``--workers 2``), run on a quiet machine and again with ``--busy`` (default 3) busy-loop
processes beside them. Every outcome (status, reason, method, matched stars, quaternion to the
last bit, counted work) must be identical, and the problem rate the same. Each run is a fresh
process, so the loaded run also pays its own start-up under load.

Part 2, the worst case the counts allow (quiet machine, warm kernels): the frame whose optics
search spends its whole seed budget (``colour-real/tree.jpg``, clutter among the brightest
detections), and the solves inside it that spend their whole ``max_verifications``, timed over
``--rounds`` rounds (median and max, wall);
these are the figures that docs/identification.md ("The solve plan") quotes against the device's
2 s GO-to-result budget.

    .venv/bin/python bench/bench_determinism.py [--busy 3] [--boresights 1000] [--rounds 5]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_busy_tests import start_busy, stop_busy  # bench/ is the script's folder

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "frames"
GROUND = [str(ROOT / ".venv" / "bin" / "st16-ground")]
TETRA3_FOV = float(np.degrees(2 * np.arctan(1024 * 6.9e-3 / 2 / 35.0)))  # the datasheet's field


def frame_jobs() -> list[tuple[Path, float]]:
    """(path, horizontal field of view in deg) of the real frames present."""
    jobs = [(p, TETRA3_FOV) for p in sorted((DATA / "tetra3-mono").glob("*.tiff"))]
    ref = DATA / "colour-real" / "reference_pointing.json"
    if ref.exists():
        jobs += [(DATA / "colour-real" / k, v["fov_deg"][0]) for k, v in sorted(json.loads(ref.read_text()).items())]
    return jobs


def solve_frames() -> None:
    """Worker: every real frame solved with its field of view only, one JSON line each."""
    from ground.api import solve_image

    for path, fov in frame_jobs():
        s = solve_image(path, fov_deg=fov)
        q = None if s.q_icrs_to_sensor is None else [float(x).hex() for x in s.q_icrs_to_sensor]
        ids = [st.catalog_id for st in s.stars]
        rec = {"frame": path.name, "status": s.status, "reason": s.reason, "method": s.record.get("method")}
        rec.update(q=q, ids=ids, search=s.record.get("search"))
        print(json.dumps(rec), flush=True)


def same_table(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two structured arrays hold the same values field by field (NaN equal to NaN: an
    unsolved pose has no error angle)."""
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    return all(np.array_equal(a[n], b[n], equal_nan=a.dtype[n].kind == "f") for n in a.dtype.names or ())


def one_run(boresights: int, out: Path) -> dict:
    """The frames and the impaired whole sky, each in a fresh process; their outcomes and wall times."""
    t0 = time.perf_counter()
    frames = subprocess.run(
        [sys.executable, __file__, "--frames-worker"], capture_output=True, text=True, check=True, cwd=ROOT
    ).stdout
    t1 = time.perf_counter()
    sim = [*GROUND, "--no-progress", "sim", "colour", "--boresights", str(boresights), "--rolls", "2"]
    sim += ["--false-stars", "3", "--drop", "0.1", "--workers", "2", "--out", str(out)]
    subprocess.run(sim, capture_output=True, text=True, check=True, cwd=ROOT)
    t2 = time.perf_counter()
    rows = np.load(out / "colour_rows.npy")
    summary = json.loads((out / "colour_summary.json").read_text())
    return {
        "frames": [json.loads(line) for line in frames.splitlines()],
        "rows": rows[[n for n in rows.dtype.names if n != "time_s"]],
        "problem": summary["problem_orientations"] / len(rows),
        "frames_s": t1 - t0,
        "sim_s": t2 - t1,
    }


def worst_case(rounds: int) -> None:
    """Part 2: the frame that spends its whole seed budget, and the most expensive single solve
    inside it (its solves reach their own ``max_verifications``), timed."""
    from firmware_model.ident import strategy
    from firmware_model.pipeline.run import warm_up
    from ground.api import solve_image

    tree = DATA / "colour-real" / "tree.jpg"
    if not tree.exists():
        print("tree.jpg absent: the worst case is not measured")
        return
    warm_up()
    fov = json.loads((tree.parent / "reference_pointing.json").read_text())["tree.jpg"]["fov_deg"][0]
    solve_image(tree, fov_deg=fov)  # its catalog and pattern index: set-up, not the search
    solves: list[tuple[float, int]] = []
    plain = strategy.solve

    def timed(*a, **k):
        t = time.perf_counter()
        out = plain(*a, **k)
        solves.append((time.perf_counter() - t, out.verifications))
        return out

    strategy.solve = timed
    times, last = [], None
    try:
        for _ in range(rounds):
            t = time.perf_counter()
            last = solve_image(tree, fov_deg=fov)
            times.append(time.perf_counter() - t)
    finally:
        strategy.solve = plain
    assert last is not None
    search = last.record["search"]
    full = [dt for dt, n in solves if n >= strategy.SolveParams().max_verifications]
    print(
        f"  one frame, tree.jpg: {search['seeds']} seeds, {search['verifications']} verifications, budget reached "
        f"{search['budget_reached']}; {last.status}; wall median {np.median(times) * 1e3:.0f} ms, "
        f"max {max(times) * 1e3:.0f} ms (file to answer, extraction included)"
    )
    print(
        f"  one solve: {len(solves) // rounds} solves a frame, {len(full) // rounds} of them spending all "
        f"{strategy.SolveParams().max_verifications} verifications; those took median "
        f"{np.median(full) * 1e3 if full else float('nan'):.0f} ms, max {max(full, default=float('nan')) * 1e3:.0f} ms"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--busy", type=int, default=3, help="busy-loop processes in the loaded run")
    ap.add_argument("--boresights", type=int, default=1000, help="impaired whole-sky boresights (x 2 rolls)")
    ap.add_argument("--rounds", type=int, default=5, help="rounds of the worst-case timings")
    ap.add_argument("--frames-worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.frames_worker:
        solve_frames()
        return 0
    print(f"machine: {os.cpu_count()} cores; load before the run: {os.getloadavg()[0]:.2f}")
    if not frame_jobs():
        print("../shared/data/frames absent: part 1 runs on the whole sky only")
    with tempfile.TemporaryDirectory() as tmp:
        quiet = one_run(args.boresights, Path(tmp) / "quiet")
        procs = start_busy(args.busy, 3600.0)
        try:
            loaded = one_run(args.boresights, Path(tmp) / "loaded")
        finally:
            stop_busy(procs)
    same_frames = quiet["frames"] == loaded["frames"]
    same_rows = same_table(quiet["rows"], loaded["rows"])
    print(f"part 1: quiet, then {args.busy} busy processes beside the run")
    print(f"  real frames: {len(quiet['frames'])}; outcomes identical: {same_frames}")
    for q, lo in zip(quiet["frames"], loaded["frames"]):
        mark = "" if q == lo else "   <- differs: " + json.dumps(lo)[:160]
        print(f"    {q['frame'][:40]:40s} {q['status']:15s} {str(q['method']):20s}{mark}")
    n = len(quiet["rows"])
    print(f"  impaired whole sky: {n} poses; rows identical: {same_rows}")
    print(f"    problem orientations: quiet {quiet['problem'] * 100:.3f} %, loaded {loaded['problem'] * 100:.3f} %")
    print(
        f"  wall s (frames, sim): quiet {quiet['frames_s']:.1f}, {quiet['sim_s']:.1f}; "
        f"loaded {loaded['frames_s']:.1f}, {loaded['sim_s']:.1f}"
    )
    print("part 2: the worst case the counted budgets allow (quiet)")
    worst_case(args.rounds)
    return 0 if same_frames and same_rows else 1


if __name__ == "__main__":
    sys.exit(main())
