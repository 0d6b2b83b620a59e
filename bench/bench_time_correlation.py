"""Time correlation as a flight driver does it (docs/ICD.md section 6, TIME; prints figures, no
asserts).

A driver-like client polls TIME (0x13) N times over a span, estimates the device clock's offset and
rate against its own monotonic clock by least squares (the device's latch time estimated from the
host's send time: plus the command frame's UART time when paced, the exchange's midpoint when not),
keeping, as NTP does, only the polls whose round trip is in the fastest quarter (a poll delayed
in either direction says little about when the latch happened), and then maps the epochs of results (GO without a catalog: the result's ``epoch`` is the device
clock at the GO's arrival) to its own clock. Figures: the residual of TIME polls after the fit
window (the prediction error of the fitted model), the residual of mapped result epochs against
the host's estimate of the GO's arrival, the fitted drift against the configured one; all in us
and as arcseconds of pointing error at 1 deg/s (1 us is 0.0036 arcsec). Four devices: unpaced
and paced at 115 200 baud, each with the default clock and with a 50 ppm drift; each against its
own baseline: the same polls' scatter, which no model can beat.

Usage: .venv/bin/python bench/bench_time_correlation.py [--polls 400] [--span 20] [--results 40]
"""

from __future__ import annotations

import argparse
import os
import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import cpu_name  # noqa: E402

from ground.link.client import Client  # noqa: E402
from ground.link.clock_sync import fit as fit_clock  # noqa: E402
from ground.link.clock_sync import latch_estimate  # noqa: E402
from ground.sim.device_process import start_device, stop_device  # noqa: E402
from protocol import nsp  # noqa: E402
from protocol.commands import Code  # noqa: E402

BAUD = 115200
ARCSEC_PER_US_AT_1_DEG_S = 3600.0 * 1e-6  #: 1 us of time-tag error at 1 deg/s, arcsec


def _frame_bytes(code: int, data: bytes = b"") -> int:
    return len(nsp.command(nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, code, data).frame())


def run(paced: bool, drift_ppm: float, polls: int, span: float, results: int) -> dict:
    extra = ["--clock-drift-ppm", str(drift_ppm), "--clock-epoch-s", "1000"]
    if paced:
        extra += ["--pace", "--baud", str(BAUD)]
    with tempfile.TemporaryDirectory() as state:
        proc, port = start_device(Path(state), *extra)
        try:
            with Client(port, baudrate=BAUD) as c:
                c.ping()
                host, dev, rtt = [], [], []
                gap = span / polls
                for _ in tqdm(range(polls), desc=f"TIME polls ({'paced' if paced else 'unpaced'}, {drift_ppm:g} ppm)"):
                    t0 = time.monotonic()
                    d = c.time()
                    t1 = time.monotonic()
                    host.append(latch_estimate(t0, t1, BAUD if paced else None))
                    dev.append(d / 1e6)
                    rtt.append(t1 - t0)
                    time.sleep(max(0.0, gap - (time.monotonic() - t0)))
                c.init()
                n_go = _frame_bytes(Code.GO, b"\x0b")
                mapped = []
                h, d, rt = np.array(host), np.array(dev), np.array(rtt)
                fit = np.arange(polls) < polls // 2
                clock_map = fit_clock(h[fit], d[fit], rt[fit])  # the fastest quarter of the first half
                quick = rt <= np.percentile(rt[fit], 25)
                rate, offset = clock_map.rate, clock_map.offset
                go_rtt = []
                for _ in range(results):
                    t0 = time.monotonic()
                    c.go(0x0B)
                    t1 = time.monotonic()
                    go_rtt.append(t1 - t0)
                    while c.result_length() == 0:
                        time.sleep(0.005)
                    epoch = struct.unpack("<d", c.read_result(0x040, 8))[0]
                    arrival = t0 + n_go * 10.0 / BAUD if paced else 0.5 * (t0 + t1)
                    mapped.append(clock_map.to_host(epoch) - arrival)
        finally:
            stop_device(proc)
    test = ~fit
    res_us = (d - (offset + rate * (h - h[0]))) * 1e6
    return {
        "paced": paced,
        "drift_ppm": drift_ppm,
        "fitted_drift_ppm": (rate - 1.0) * 1e6,
        "poll_residual_us": res_us[test],
        "poll_residual_quick_us": res_us[test & quick],
        "fit_scatter_us": res_us[fit & quick],
        "epoch_residual_us": np.array(mapped) * 1e6,
        "rtt_ms": (np.median(rt) * 1e3, np.median(go_rtt) * 1e3),
    }


def _row(name: str, us: np.ndarray) -> str:
    a = np.abs(us)
    p50, p99, top = np.percentile(a, 50), np.percentile(a, 99), a.max()
    arc = ARCSEC_PER_US_AT_1_DEG_S
    return f"  {name:<26} |err| p50 {p50:8.1f} us  p99 {p99:8.1f} us  max {top:8.1f} us   (p99 {p99 * arc:.4f} arcsec at 1 deg/s)"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--polls", type=int, default=400, help="TIME polls per device (half fit, half test)")
    ap.add_argument("--span", type=float, default=20.0, help="seconds the polls span")
    ap.add_argument("--results", type=int, default=40, help="GO results mapped per device")
    args = ap.parse_args(argv)
    print(f"machine: {cpu_name()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
    print(f"polls {args.polls} over {args.span:g} s (first half fits offset and rate), {args.results} results\n")
    for paced in (False, True):
        for drift in (0.0, 50.0):
            r = run(paced, drift, args.polls, args.span, args.results)
            link = f"paced {BAUD} baud" if paced else "unpaced pty"
            rtt, go_rtt = r["rtt_ms"]
            print(
                f"{link}, clock drift {drift:g} ppm: fitted drift {r['fitted_drift_ppm']:+.2f} ppm; "
                f"median round trip TIME {rtt:.2f} ms, GO {go_rtt:.2f} ms"
            )
            print(_row("baseline: fit scatter", r["fit_scatter_us"]))
            print(_row("TIME poll, fastest quarter", r["poll_residual_quick_us"]))
            print(_row("TIME poll, every one", r["poll_residual_us"]))
            print(_row("result epoch, mapped", r["epoch_residual_us"]))
    print(f"\nload at the end {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
