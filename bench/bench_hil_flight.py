"""Issue 41's figures (docs/hil.md "The flight side", "Lockstep", "NASA 42"): the closed loop with
and without the tracker at the default gyro, lockstep identity across speeds, and NASA 42 in the loop.

    .venv/bin/python bench/bench_hil_flight.py [--parts tracker,lockstep,nasa42] [--long 300]
        [--lockstep-duration 8] [--nasa42-dir DIR] [--nasa42-seconds 60]

* ``tracker``: ``run_hil`` (the demo's library, Basilisk when installed) for ``--long`` s with the
  tracker, with ``--tracker-off-after 0`` (the control: never a fix) and with the tracker off after
  30 s (coasting on the gyro): the pointing error (truth to target) at 30, 60 and 300 s, the
  acquisition time, the estimate's error at the end, and the pass mark's verdict.
* ``lockstep``: the same short run at 0.25x, 1x, 4x real time and unpaced: statuses, attitudes
  and time tags (GO time, exposure mid-time, the device's epoch) compared with the unpaced run's.
* ``nasa42``: a 42 built by ``../shared/tools/nasa42/build.sh`` (``--nasa42-dir``, else built
  here) runs ``--nasa42-seconds`` in FAST mode paced by the device (``speed=1``); GO back to back:
  each OK answer against 42's own ``qbn.42`` at the exposure mid-time (median, p99, arcsec), and
  GO -> result ready (real ms).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import socket
import subprocess
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _verdict(summary: dict) -> str:
    from ground.cli.hil import PASS_MARK_DEG, tracker_failure

    why = tracker_failure(summary)
    if why is None and not summary["pointing_error_deg_last"] < PASS_MARK_DEG:
        why = f"final pointing error {summary['pointing_error_deg_last']:.3g} deg over {PASS_MARK_DEG}"
    return "pass" if why is None else f"fail: {why}"


def part_tracker(long_s: float) -> None:
    from ground.hil.run import run_hil

    print(f"== with and without the tracker ({long_s:g} s, default gyro, default epoch, seed 15)")
    print("| run | acquisition s | error at 30 s | at 60 s | at 300 s | estimate vs truth at end | verdict |")
    print("|---|---|---|---|---|---|---|")
    for label, off in (("tracker", None), ("tracker off after 30 s", 30.0), ("tracker off after 0 (control)", 0.0)):
        with tempfile.TemporaryDirectory() as out:
            t0 = time.monotonic()
            s = run_hil(out, long_s, progress=False, tracker_off_after=off)
            wall = time.monotonic() - t0
        at = s["pointing_error_deg_at"]
        est = s["estimate_error_arcsec_last"]
        cells = [f"{at[k]:.4f} deg" if k in at else "-" for k in ("30", "60", "300")]
        acq = "never" if s["acquisition_s"] is None else f"{s['acquisition_s']:.2f}"
        print(
            f"| {label} | {acq} | {' | '.join(cells)} | {'-' if est is None else f'{est:.1f} arcsec'} "
            f"| {_verdict(s)} |  ({wall:.0f} s real, {s['ok_updates']} OK answers, {s['dynamics'].split(':')[0]})"
        )


def part_lockstep(duration_s: float) -> None:
    from ground.hil.run import run_hil

    print(f"== lockstep identity ({duration_s:g} s of loop, the same run at each speed)")
    runs = {}
    for speed in (0.0, 0.25, 1.0, 4.0):
        with tempfile.TemporaryDirectory() as out:
            t0 = time.monotonic()
            s = run_hil(out, duration_s, progress=False, speed=speed)
            wall = time.monotonic() - t0
            rows = [json.loads(x) for x in (Path(out) / "hil_log.jsonl").read_text().splitlines()]
        runs[speed] = (rows, s, wall)
    base = runs[0.0][0]
    keys = ("status", "sent", "received", "t_mid", "epoch", "q")
    print("| speed | real s | updates | statuses | identical to unpaced (status, attitude, GO time, mid-time, epoch) |")
    print("|---|---|---|---|---|")
    for speed, (rows, s, wall) in runs.items():
        same = len(rows) == len(base) and all(all(r.get(k) == b.get(k) for k in keys) for r, b in zip(rows, base))
        diffs = sum(any(r.get(k) != b.get(k) for k in keys) for r, b in zip(rows, base))
        name = "unpaced" if speed == 0 else f"{speed:g}x"
        print(
            f"| {name} | {wall:.1f} | {len(rows)} | {s['statuses']} | {'yes' if same else f'NO ({diffs} rows differ)'} |"
        )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def part_nasa42(dest: Path | None, seconds: float) -> None:
    from firmware_model.catalog.image_io import catalog_to_image
    from firmware_model.reference_frames import quat_to_matrix, rotation_angle
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.link.client import Client
    from ground.sim.device_process import start_device, stop_device
    from ground.sim.nasa42 import body_quaternion, run_folder
    from protocol import result

    work = Path(tempfile.mkdtemp())
    if dest is None:
        dest = work / "nasa42"
        t0 = time.monotonic()
        subprocess.run(
            ["sh", str(ROOT.parent / "shared/tools/nasa42/build.sh"), str(dest)], check=True, capture_output=True
        )
        print(f"(42 built in {time.monotonic() - t0:.1f} s)")
    port = _free_port()
    run = run_folder(dest, f"bench-{port}", port, seconds)
    state = work / "state"
    state.mkdir()
    proc, pty = start_device(state)
    try:
        with Client(pty, timeout=10.0) as c:
            c.init()
            c.upload(0, catalog_to_image(build_catalog(CatalogDesign())), progress=False)
    finally:
        stop_device(proc)
    log = open(work / "42.log", "w")
    p42 = subprocess.Popen([str(dest / "42"), run.name], cwd=dest, stdout=log, stderr=subprocess.STDOUT)
    answers, lat = [], []
    proc, pty = start_device(state, "--attitude-feed", f"42://127.0.0.1:{port}?speed=1")
    try:
        with Client(pty, timeout=30.0) as c:
            c.init()
            end = time.monotonic() + seconds - 3.0
            while time.monotonic() < end:
                t0 = time.monotonic()
                r = c.go_and_wait(0x0B, timeout=60.0, interval=0.002)
                lat.append((time.monotonic() - t0) * 1e3)
                status = result.status_of(int(r["return_code"]))
                answers.append((status, np.array(r["quaternion"], float), float(r["ext"]["utc_epoch"])))
            p42.wait(timeout=120)
    finally:
        stop_device(proc)
        if p42.poll() is None:
            p42.kill()
        log.close()
    start = datetime(2024, 4, 8, tzinfo=UTC).timestamp()
    t_rec = np.loadtxt(run / "time.42", ndmin=1) + start
    q_rec = np.loadtxt(run / "qbn.42", ndmin=2)
    n = min(len(t_rec), len(q_rec))
    t_rec, q_rec = t_rec[:n], q_rec[:n]
    errs = []
    for status, q, t in answers:
        if status != result.Status.OK or not t_rec[0] <= t <= t_rec[-1]:
            continue
        k = int(np.clip(np.searchsorted(t_rec, t), 1, n - 1))
        f = (t - t_rec[k - 1]) / (t_rec[k] - t_rec[k - 1])
        qa, qb = q_rec[k - 1], q_rec[k] if np.dot(q_rec[k - 1], q_rec[k]) >= 0 else -q_rec[k]
        qn = (1 - f) * qa + f * qb
        truth = quat_to_matrix(body_quaternion(qn / np.linalg.norm(qn)))
        errs.append(math.degrees(rotation_angle(quat_to_matrix(q), truth)) * 3600)
    statuses: dict[str, int] = {}
    for s, _, _ in answers:
        statuses[getattr(s, "name", str(s))] = statuses.get(getattr(s, "name", str(s)), 0) + 1
    print(
        f"== NASA 42 in the loop ({seconds:g} s of 42's default scenario, 2024-04-08, FAST, device speed=1, position on)"
    )
    print(f"GOs {len(answers)}: {statuses}")
    if errs:
        e = np.array(errs)
        print(
            f"tracker vs 42 truth (qbn.42): median {np.median(e):.1f} arcsec, p99 {np.percentile(e, 99):.1f} arcsec, max {e.max():.1f} (n={len(e)})"
        )
    la = np.array(lat)
    print(f"GO -> result ready (real): p50 {np.median(la):.1f} ms, p99 {np.percentile(la, 99):.1f} ms")
    shutil.rmtree(run, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", default="tracker,lockstep,nasa42")
    ap.add_argument("--long", type=float, default=300.0)
    ap.add_argument("--lockstep-duration", type=float, default=8.0)
    ap.add_argument("--nasa42-dir", type=Path, default=None)
    ap.add_argument("--nasa42-seconds", type=float, default=60.0)
    args = ap.parse_args()
    parts = args.parts.split(",")
    print(f"bench_hil_flight {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    if "tracker" in parts:
        part_tracker(args.long)
    if "lockstep" in parts:
        part_lockstep(args.lockstep_duration)
    if "nasa42" in parts:
        part_nasa42(args.nasa42_dir, args.nasa42_seconds)


if __name__ == "__main__":
    main()
