"""Blind and wide (issue 28): ``ground.api.solve_image`` on real frames with a field-of-view hint,
blind, and with a wrong hint, against cedar-solve in the same run.

Frames: the 15 real frames of ``bench_realframes.frames()`` (../shared/data/frames: the 8 ESA
tetra3 frames, 16-bit mono TIFF, and the 7 colour-real frames, demosaiced PNG/JPEG), each with its
true horizontal field of view F. Ours: ``solve_image(path, fov_deg=F)`` (the FOV given, a hint:
the field is searched within F / 1.4 to 1.4 F against the whole-sky pattern database),
``solve_image(path)`` (blind, 5-60 deg), and ``fov_deg=0.75 F`` and ``1.25 F`` (a wrong hint).
cedar-solve 0.5.1: ``solve_from_image(image, fov_estimate=F)`` with its bundled database and
default settings (its recommended use), in a long-lived ``peer_worker.py cedar`` process of the
benchmark-only venv (``bench_peers.Worker``; its pattern cache kept between requests, as in
bench_peers' ``cedar``). Every process single-threaded (BLAS, OpenMP, numba at 1 thread).

Correct: the returned boresight within 5 px of the reference centre (astrometry.net for
colour-real, fixtures/tetra3_cedar_reference.json for tetra3: agreement, not truth); ``HC wrong``:
status OK and not correct; counts from the last round (``varied`` counts frames whose status or
correctness changed between rounds).

Time: file to attitude, wall, reading the image included: ours timed around ``solve_image``,
cedar by its worker around opening the file and ``solve_from_image`` (the JSON round trip left
out). Warm: one untimed solve of every frame in every mode, and by cedar, first. Then ``--rounds``
rounds, each frame in turn solved in the five ways (ours F, cedar, ours blind, ours 0.75 F,
ours 1.25 F; the order rotated by one each round); the median per frame over the rounds, then
per set the median and p90 over the frames, and the ratios ours / cedar of those (and the median
and p90 over the frames of the per-frame ratio ours F / cedar).

First solve: before the warm rounds, per set and for the FOV given and blind, a fresh
``.venv/bin/python`` solves the set's first frame: the import of ``ground.api`` and the
``solve_image`` call (from call to return) timed apart, with the record's ``timings_s`` (the sky
database already on disk in the user cache, the compiled kernels cached).

    python3 -m venv .venv-peers && .venv-peers/bin/pip install --no-deps cedar-solve "numpy<2" scipy pillow
    .venv/bin/python bench/bench_sky.py [--rounds 3] [--json out/bench_sky.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from jsonl_worker import SINGLE_THREAD  # noqa: E402  (standard library only)

for _name, _value in SINGLE_THREAD.items():  # before numpy: ours runs in this process
    os.environ.setdefault(_name, _value)

import numpy as np  # noqa: E402
from bench_peers import PEER_PYTHON, Worker, revision  # noqa: E402
from bench_realframes import DATA, frames, separation_px  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OURS_PYTHON = ROOT / ".venv" / "bin" / "python"
CORRECT_PX = 5.0
#: Our modes: name -> factor on the true FOV given as the hint (None: blind).
OURS_MODES: dict[str, float | None] = {"fov": 1.0, "blind": None, "x0.75": 0.75, "x1.25": 1.25}
#: The interleaved order within a frame (rotated by one per round).
ORDER = ["fov", "cedar", "blind", "x0.75", "x1.25"]
SETS = ("tetra3", "colour")

FIRST_SOLVE = """
import json, sys, time
t0 = time.perf_counter()
from ground.api import solve_image
t1 = time.perf_counter()
kw = {} if sys.argv[2] == "blind" else {"fov_deg": float(sys.argv[2])}
s = solve_image(sys.argv[1], **kw)
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "call_s": t2 - t1, "status": s.status, "ra": s.ra_deg, "dec": s.dec_deg,
                  "timings_s": s.record.get("timings_s", {})}))
"""


def machine(label: str) -> None:
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"{label}: load average {load} (1/5/15 min), {os.cpu_count()} CPUs")


def ours(job: dict, mode: str) -> dict:
    """One solve of ours: status, correctness and wall seconds from the call to its return."""
    from ground.api import solve_image

    factor = OURS_MODES[mode]
    kw = {} if factor is None else {"fov_deg": factor * job["fov"]}
    t0 = time.perf_counter()
    s = solve_image(str(job["path"]), **kw)
    wall = time.perf_counter() - t0
    sep = separation_px(s.ra_deg, s.dec_deg, job) if s.solved else None
    sky = s.record.get("sky") or {}
    return {
        "status": s.status,
        "sep_px": sep,
        "correct": sep is not None and sep < CORRECT_PX,
        "wall_s": wall,
        "fov_deg": sky.get("fov_deg"),
        "reason": s.reason,
    }


def cedar(worker: Worker | None, job: dict) -> dict | None:
    """One cedar-solve file request: the worker's own wall time of opening and solving the file."""
    if worker is None:
        return None
    rep = worker.call("file", path=str(job["path"]), fov=job["fov"])
    if "error" in rep:
        return {"status": "ERROR", "sep_px": None, "correct": False, "wall_s": None, "reason": rep["error"]}
    sep = separation_px(rep["ra"], rep["dec"], job) if rep.get("ra") is not None else None
    return {
        "status": rep["status"],
        "sep_px": sep,
        "correct": sep is not None and sep < CORRECT_PX,
        "wall_s": rep["wall_s"],
        "fov_deg": rep.get("fov"),
        "reason": "",
    }


def first_solves(jobs: list[dict]) -> dict:
    """Per set and mode (FOV given, blind): a fresh process's first solve of the set's first frame."""
    env = {**os.environ, **SINGLE_THREAD, "PYTHONPATH": str(ROOT)}
    res: dict[str, dict] = {}
    print("\nFirst solve in a fresh process (the set's first frame):")
    for set_name in SETS:
        job = next((j for j in jobs if j["set"] == set_name), None)
        if job is None:
            continue
        for mode, arg in (("fov", f"{job['fov']!r}"), ("blind", "blind")):
            t0 = time.perf_counter()
            p = subprocess.run(
                [str(OURS_PYTHON), "-c", FIRST_SOLVE, str(job["path"]), arg],
                capture_output=True,
                text=True,
                env=env,
                cwd=ROOT,
            )
            process_s = time.perf_counter() - t0
            lines = p.stdout.strip().splitlines()
            if p.returncode or not lines:
                print(f"  {set_name} {mode}: failed (exit {p.returncode})\n{p.stderr.strip()}")
                continue
            r = json.loads(lines[-1])
            sep = separation_px(r["ra"], r["dec"], job) if r["ra"] is not None else None
            r.update(process_s=process_s, sep_px=sep, frame=job["path"].name)
            res[f"{set_name} {mode}"] = r
            stages = ", ".join(f"{k} {v:.3f}" for k, v in r["timings_s"].items())
            print(
                f"  {set_name:<7}{mode:<6}{job['path'].name[:30]:<31}{r['status']:<15}sep {fmt(sep, '.2f')} px; "
                f"solve_image {r['call_s']:.2f} s (import {r['import_s']:.2f} s, process {process_s:.2f} s)"
            )
            print(f"  {'':<13}timings_s: {stages}")
    return res


def fmt(v: float | None, spec: str = ".0f") -> str:
    return "-" if v is None or not np.isfinite(v) else format(v, spec)


def med(values: list) -> float:
    v = [x for x in values if x is not None and np.isfinite(x)]
    return float(np.median(v)) if v else float("nan")


def p90(values: list) -> float:
    v = [x for x in values if x is not None and np.isfinite(x)]
    return float(np.percentile(v, 90)) if v else float("nan")


def short(r: dict | None) -> str:
    if r is None:
        return "-"
    st = {"OK": "OK", "LOW_CONFIDENCE": "LOW"}.get(r["status"], r["status"][:8])
    mark = "" if r["sep_px"] is None else ("" if r["correct"] else "!")
    return f"{st}{mark} {fmt(r['sep_px'], '.1f')}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3, help="timed rounds (median per frame over them)")
    ap.add_argument("--json", type=Path, help="also write the summary to this file")
    args = ap.parse_args(argv)
    print("command: " + " ".join([os.path.relpath(sys.executable), *sys.argv]))
    machine("start")
    load_start = os.getloadavg()
    if not DATA.is_dir():
        print(f"no frames under {DATA}; nothing to do")
        return 0
    jobs = frames()
    if not jobs:
        print(f"no frames under {DATA}; nothing to do")
        return 0
    print(f"code {revision()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {args.rounds} rounds")
    first = first_solves(jobs)

    worker = None
    if not PEER_PYTHON.exists():
        print(f"cedar-solve: not run: no benchmark venv {PEER_PYTHON.parent.parent} (see the module docstring)")
    else:
        logdir = ROOT / "out" / "bench_sky"
        logdir.mkdir(parents=True, exist_ok=True)
        worker = Worker(
            "cedar", [str(PEER_PYTHON), str(ROOT / "bench" / "peer_worker.py"), "cedar"], logdir / "cedar.log"
        )
    try:
        if worker is not None:
            rep = worker.call("setup", fovs=sorted({j["fov"] for j in jobs}))
            print(f"peer: {rep.get('version', rep.get('error'))}, single-threaded in its own process")
        t0 = time.perf_counter()
        for j in jobs:  # warm, untimed: every frame in every mode
            for mode in OURS_MODES:
                ours(j, mode)
            cedar(worker, j)
        print(f"warm-up (every frame, every mode, untimed): {time.perf_counter() - t0:.0f} s")
        runs: dict[tuple[int, str], list[dict]] = {}
        t0 = time.perf_counter()
        for rnd in range(args.rounds):
            order = ORDER[rnd % len(ORDER) :] + ORDER[: rnd % len(ORDER)]
            for k, j in enumerate(jobs):
                for mode in order:
                    r = cedar(worker, j) if mode == "cedar" else ours(j, mode)
                    if r is not None:
                        runs.setdefault((k, mode), []).append(r)
        print(f"timed rounds: {time.perf_counter() - t0:.0f} s")
    finally:
        if worker is not None:
            worker.close()

    modes = [m for m in ORDER if any((k, m) in runs for k in range(len(jobs)))]
    print("\nPer frame (last round's status and boresight error in px, '!' not within 5 px; median ms over rounds):")
    head = "".join(f"{m:>14}{'ms':>7}" for m in modes)
    print(f"{'frame':<31}{'set':<7}{'F deg':>6}{head}")
    per_frame: list[dict] = []
    for k, j in enumerate(jobs):
        row: dict = {"frame": j["path"].name, "set": j["set"], "fov_deg": j["fov"], "modes": {}}
        cells = ""
        for m in modes:
            rs = runs.get((k, m), [])
            last = rs[-1] if rs else None
            ms = 1e3 * med([r["wall_s"] for r in rs])
            varied = len({(r["status"], r["correct"]) for r in rs}) > 1
            row["modes"][m] = {**(last or {}), "ms": ms, "varied": varied}
            cells += f"{short(last):>14}{fmt(ms):>7}"
        per_frame.append(row)
        print(f"{j['path'].name[:30]:<31}{j['set']:<7}{j['fov']:>6.2f}{cells}")
        for m in modes:
            last = row["modes"][m]
            if last.get("status") not in (None, "OK") and last.get("reason"):
                print(f"{'':<31}{m}: {last['status']}: {last['reason'][:100]}")

    summary: dict = {
        "command": sys.argv,
        "revision": revision(),
        "rounds": args.rounds,
        "cpus": os.cpu_count(),
        "load_start": load_start,
        "first_solve": first,
        "sets": {},
    }
    print("\nPer set: times (ms, median over rounds per frame, then over the frames)")
    print(
        f"{'set':<8}{'n':>3}{'ours F p50':>11}{'p90':>7}{'cedar p50':>10}{'p90':>7}{'p50 ratio':>10}{'p90 ratio':>10}"
        f"{'frame ratio p50':>16}{'p90':>6}{'blind p50':>10}{'p90':>7}{'/cedar':>7}"
        f"{'x0.75 p50':>10}{'x1.25 p50':>10}"
    )
    for set_name in SETS:
        rows = [r for r in per_frame if r["set"] == set_name]
        if not rows:
            continue
        t = {m: [r["modes"][m]["ms"] for r in rows] for m in modes}
        frame_ratio = [r["modes"]["fov"]["ms"] / r["modes"]["cedar"]["ms"] for r in rows if "cedar" in r["modes"]]
        cedar_ms = t.get("cedar", [])
        s: dict[str, Any] = {
            "n": len(rows),
            "ms": {m: {"p50": med(v), "p90": p90(v)} for m, v in t.items()},
            "ratio_p50": med(t["fov"]) / med(cedar_ms) if cedar_ms else None,
            "ratio_p90": p90(t["fov"]) / p90(cedar_ms) if cedar_ms else None,
            "frame_ratio_p50": med(frame_ratio),
            "frame_ratio_p90": p90(frame_ratio),
            "blind_over_cedar_p50": med(t["blind"]) / med(cedar_ms) if cedar_ms else None,
            "counts": {},
        }
        print(
            f"{set_name:<8}{len(rows):>3}{fmt(s['ms']['fov']['p50']):>11}{fmt(s['ms']['fov']['p90']):>7}"
            f"{fmt(med(cedar_ms)):>10}{fmt(p90(cedar_ms)):>7}{fmt(s['ratio_p50'], '.2f'):>10}"
            f"{fmt(s['ratio_p90'], '.2f'):>10}{fmt(s['frame_ratio_p50'], '.2f'):>16}{fmt(s['frame_ratio_p90'], '.2f'):>6}"
            f"{fmt(s['ms']['blind']['p50']):>10}{fmt(s['ms']['blind']['p90']):>7}"
            f"{fmt(s['blind_over_cedar_p50'], '.2f'):>7}{fmt(s['ms']['x0.75']['p50']):>10}"
            f"{fmt(s['ms']['x1.25']['p50']):>10}"
        )
        summary["sets"][set_name] = s
    print("(ratio: ours / cedar-solve; ours F, x0.75, x1.25: that FOV given as the hint; blind: no FOV)")

    print("\nPer set and mode: answers (last round; correct = within 5 px of the reference)")
    print(
        f"{'set':<8}{'mode':<7}{'OK correct':>11}{'LOW_CONF':>9}{'LOW correct':>12}{'HC wrong':>9}{'none':>5}{'varied':>7}"
    )
    for set_name in SETS:
        rows = [r for r in per_frame if r["set"] == set_name]
        for m in modes:
            got = [r["modes"][m] for r in rows if r["modes"][m].get("status") is not None]
            if not got:
                continue
            c = {
                "frames": len(got),
                "ok_correct": sum(g["status"] == "OK" and g["correct"] for g in got),
                "low_confidence": sum(g["status"] == "LOW_CONFIDENCE" for g in got),
                "low_correct": sum(g["status"] == "LOW_CONFIDENCE" and g["correct"] for g in got),
                "hc_wrong": sum(g["status"] == "OK" and not g["correct"] for g in got),
                "none": sum(g["sep_px"] is None for g in got),
                "varied": sum(g["varied"] for g in got),
            }
            summary["sets"].setdefault(set_name, {}).setdefault("counts", {})[m] = c
            label = "cedar" if m == "cedar" else m
            print(
                f"{set_name:<8}{label:<7}{c['ok_correct']:>8}/{c['frames']:<2}{c['low_confidence']:>9}"
                f"{c['low_correct']:>12}{c['hc_wrong']:>9}{c['none']:>5}{c['varied']:>7}"
            )
    print("(cedar-solve: OK = a solution returned, it has no lower-confidence answer)")
    summary["frames"] = per_frame
    machine("end")
    summary["load_end"] = os.getloadavg()
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1, default=str) + "\n")
        print(f"written {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
