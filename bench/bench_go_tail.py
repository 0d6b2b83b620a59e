"""GO -> result under ``--timing realistic`` with COMBINATIONs mixed in (prints figures, no asserts).

A device runs as a child on a pty (``st16-device --pty --sky SCHEDULE --timing realistic``). The
host loops over cycles: every ``--every``-th cycle is a COMBINATION (GO code 0x0B, mask
``--mask``), the others a GO, then EDAC 0x004C polled every ``--poll-ms`` until the result length
reads non-zero, then READ RESULT; a PING goes out whenever ``--ping-ms`` have passed since the
last one (between polls, and while a COMBINATION waits none can: the line has one client). GO ->
result is timed from just before the GO is written to the poll that reads the result ready, and
reported apart for a GO after a COMBINATION and a GO after a GO (p50, p90, p99, max, and how many
went over ``--threshold-ms``, default the hold + 50 ms; ``--processing-ms 100`` gives the
200 ms hold of earlier defaults), with the device's own solve time
(``ext.solve_time``) of those cycles and the load average before and after. The two populations
share the run (and the machine's load), so their difference is the figure to read.

    .venv/bin/python bench/bench_go_tail.py [--minutes 3] [--every 5] [--device-arg=--log-level=debug]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from firmware_model.device.sequence import Timing  # noqa: E402
from protocol.commands import GO_OPERATIONAL  # noqa: E402

TIMING = Timing()  #: --timing realistic's defaults


def _schedule(n: int, work: Path):
    """A ``--sky`` schedule of ``n`` attitudes whose fields hold enough catalog stars, and the
    catalog's image to upload."""
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_to_image
    from firmware_model.reference_frames import matrix_to_quat
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.sim.device_process import pick_attitudes

    cat = build_catalog(CatalogDesign())
    atts = pick_attitudes(cat, CameraModel.reference_design(), n, np.random.default_rng(44))
    path = work / "schedule.csv"
    rows = "".join(",".join(f"{v:.12f}" for v in matrix_to_quat(a)) + f",RGGB,{k}\n" for k, a in enumerate(atts))
    path.write_text("qw,qx,qy,qz,pattern,seed\n" + rows)
    return path, catalog_to_image(cat)


class Loop:
    """The host side of the soak: one client, PINGs interleaved every ``ping_s``."""

    def __init__(self, client, poll_s: float, ping_s: float):
        self.client, self.poll_s, self.ping_s = client, poll_s, ping_s
        self.last_ping = time.perf_counter()
        self.pings: list[float] = []

    def ping_if_due(self) -> None:
        now = time.perf_counter()
        if now - self.last_ping >= self.ping_s:
            self.client.ping()
            self.last_ping = time.perf_counter()
            self.pings.append(self.last_ping - now)

    def go(self) -> float:
        """GO, poll until the result is ready, READ RESULT; GO -> ready in s."""
        t0 = time.perf_counter()
        self.client.go(GO_OPERATIONAL)
        self.trace = [("GO", 0.0, time.perf_counter() - t0)]
        while True:
            time.sleep(self.poll_s)
            t1 = time.perf_counter()
            n = self.client.result_length()
            self.trace.append(("poll", t1 - t0, time.perf_counter() - t1))
            if n != 0:
                ready = time.perf_counter() - t0
                break
            t1 = time.perf_counter()
            self.ping_if_due()
            if time.perf_counter() - t1 > 1e-4:
                self.trace.append(("ping", t1 - t0, time.perf_counter() - t1))
        return ready

    def combination(self, mask: int) -> None:
        self.client.combination(GO_OPERATIONAL, mask, timeout=30.0)
        self.ping_if_due()


def _row(label: str, ms: np.ndarray, solve_ms: np.ndarray, threshold: float) -> str:
    if not len(ms):
        return f"{label:<22} none"
    over = int(np.count_nonzero(ms > threshold))
    return (
        f"{label:<22}{len(ms):>6}{np.median(ms):>9.1f}{np.percentile(ms, 90):>9.1f}{np.percentile(ms, 99):>9.1f}"
        f"{ms.max():>9.1f}{over:>7} ({100.0 * over / len(ms):4.1f} %)   solve p50 {np.median(solve_ms):.0f} ms, "
        f"max {solve_ms.max():.0f} ms"
    )


def run(args: argparse.Namespace) -> None:
    from ground.link.client import Client
    from ground.link.solve_report import solve_record
    from ground.sim.device_process import start_device, stop_device

    hold_ms = 1e3 * TIMING.exposure_s + args.processing_ms
    threshold = hold_ms + 50.0 if args.threshold_ms is None else args.threshold_ms
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        schedule, image = _schedule(args.frames, work)
        (work / "state").mkdir()
        device_args = ["--sky", str(schedule), "--timing", "realistic", "--processing-ms", f"{args.processing_ms:g}"]
        device_args += args.device_arg
        proc, pty = start_device(work / "state", *device_args)
        prev = "GO"
        times: dict[str, list[float]] = {"after COMBINATION": [], "after GO": []}
        solves: dict[str, list[float]] = {k: [] for k in times}
        statuses: dict[str, int] = {}
        cycles = combinations = 0
        load0 = os.getloadavg()
        try:
            with Client(pty, timeout=5.0) as client:
                client.init()
                client.upload(0, image, progress=False)
                client.go_and_wait(timeout=60)  # warm-up: first capture
                loop = Loop(client, args.poll_ms / 1e3, args.ping_ms / 1e3)
                end = time.monotonic() + 60.0 * args.minutes
                while time.monotonic() < end:
                    cycles += 1
                    if cycles % args.every == 0:
                        loop.combination(args.mask)
                        combinations += 1
                        prev = "COMBINATION"
                        continue
                    ready = loop.go()
                    raw = client.read_result_record()
                    rec = solve_record(raw)
                    statuses[rec["status"]] = statuses.get(rec["status"], 0) + 1
                    key = f"after {prev}"
                    times[key].append(ready * 1e3)
                    if args.trace:
                        steps = " ".join(f"{k}@{1e3 * t:.0f}+{1e3 * d:.0f}" for k, t, d in loop.trace)
                        slow = "slow " if ready * 1e3 > threshold else ""
                        print(
                            f"{slow}GO {key} seq {int(raw['sequence'])} {ready * 1e3:.0f} ms: {steps}",
                            file=sys.stderr,
                            flush=True,
                        )
                    solves[key].append(1e3 * float(raw["ext"]["solve_time"]))
                    prev = "GO"
                    loop.ping_if_due()
        finally:
            rc = stop_device(proc)
        load1 = os.getloadavg()
    pings = np.array(loop.pings) * 1e3
    print(
        f"\nGO -> result ready, --sky --timing realistic (hold {hold_ms:.0f} ms), {args.minutes:g} min, "
        f"{cycles} cycles, a COMBINATION (mask 0x{args.mask:X}) every {args.every}th ({combinations}), "
        f"poll every {args.poll_ms:g} ms, PING every {args.ping_ms:g} ms; device args {' '.join(args.device_arg) or '-'}"
    )
    print(f"load average before {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, after {load1[0]:.2f} {load1[1]:.2f}")
    print(f"{'GO':<22}{'n':>6}{'p50 ms':>9}{'p90 ms':>9}{'p99 ms':>9}{'max ms':>9}{'> ' + f'{threshold:.0f} ms':>15}")
    for key in times:
        print(_row(key, np.array(times[key]), np.array(solves[key]), threshold))
    print(
        f"PINGs {len(pings)}: p50 {np.median(pings):.1f} ms, p99 {np.percentile(pings, 99):.1f} ms; "
        f"statuses {statuses}; device exit {rc}"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=3.0, help="length of the loop (the issue's soak: 25)")
    ap.add_argument("--every", type=int, default=5, help="every Nth cycle is a COMBINATION (the issue's soak: 10)")
    ap.add_argument("--mask", type=lambda s: int(s, 0), default=0x7E, help="COMBINATION section mask")
    ap.add_argument("--poll-ms", type=float, default=20.0, help="EDAC 0x004C poll interval (Client.go_and_wait's)")
    ap.add_argument("--ping-ms", type=float, default=100.0)
    ap.add_argument(
        "--processing-ms", type=float, default=1e3 * TIMING.processing_s, help="the device's (the hold: 100 ms + this)"
    )
    ap.add_argument("--threshold-ms", type=float, help="count GOs over this (default the hold + 50 ms)")
    ap.add_argument("--frames", type=int, default=20, help="attitudes in the sky schedule")
    ap.add_argument(
        "--trace",
        action="store_true",
        help="print each GO's exchanges to stderr, marking those over the threshold slow",
    )
    ap.add_argument("--device-arg", action="append", default=[], help="extra st16-device argument (repeatable)")
    args = ap.parse_args(argv)
    if args.every < 2:
        ap.error("--every must be >= 2")
    run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
