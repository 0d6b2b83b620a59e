"""Two heads behind one pty (issue 45, docs/ICD.md section 14): GO -> result per head, and PING
round trips while both heads solve.

``st16-device --pty --heads FILE --sky SCHEDULE`` with two heads: 0x0E looking along the body's
+z, 0x0F mounted 90 degrees about the body's y axis. Each cycle sends GO to both heads back to
back (both solve at once), then PINGs the heads alternately until both results are ready; every
reply is read by the one client on the line and checked for its head's address (a reply from the
wrong head, or two replies interleaved on the line, fails the client's CRC and address checks).
Prints per head: GO -> result ready p50/p99/max and the statuses; PING p50/p99/max while solving.

    .venv/bin/python bench/bench_heads.py [--n 20]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

HEADS = {
    "heads": [
        {"address": "0x0E", "mount_q": [1, 0, 0, 0]},
        {"address": "0x0F", "mount_q": [0.7071068, 0, 0.7071068, 0]},
    ]
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20, help="GO cycles (each: both heads)")
    args = ap.parse_args()

    from bench_timing import _catalog_and_attitudes, _sky_args

    from firmware_model.catalog.image_io import catalog_to_image
    from ground.link.client import Client
    from ground.link.solve_report import solve_record
    from ground.sim.device_process import start_device, stop_device

    cat, atts = _catalog_and_attitudes(10)
    image = catalog_to_image(cat)
    heads = [0x0E, 0x0F]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        (work / "heads.json").write_text(json.dumps(HEADS))
        t0 = time.monotonic()
        proc, pty = start_device(work / "state", "--heads", str(work / "heads.json"), *_sky_args(atts, work))
        print(f"two heads listening after {time.monotonic() - t0:.1f} s on {pty}")
        client = Client(pty, timeout=5.0)
        try:
            for h in heads:
                client.device_address = h
                client.init()
                client.upload(0, image, progress=False)
                client.go_and_wait(timeout=120)  # warm-up: first capture, catalog index
            go_ms: dict[int, list[float]] = {h: [] for h in heads}
            status: dict[int, dict[str, int]] = {h: {} for h in heads}
            ping_ms: list[float] = []
            for _ in range(args.n):
                started = {}
                for h in heads:
                    client.device_address = h
                    client.go()
                    started[h] = time.perf_counter()
                pending = set(heads)
                k = 0
                while pending:
                    h = heads[k % 2]
                    k += 1
                    client.device_address = h
                    t = time.perf_counter()
                    client.ping()  # the client accepts only a reply from device_address, CRC checked
                    ping_ms.append((time.perf_counter() - t) * 1e3)
                    if h in pending and client.result_length() != 0:
                        go_ms[h].append((time.perf_counter() - started[h]) * 1e3)
                        rec = solve_record(client.read_result_record())
                        status[h][rec["status"]] = status[h].get(rec["status"], 0) + 1
                        pending.discard(h)
        finally:
            client.close()
            stop_device(proc)
    print(f"\n{args.n} cycles, GO to both heads back to back, then PINGs alternately until both results are ready")
    print(f"{'head':<8}{'GO->ready p50':>14}{'p99':>9}{'max':>9}   statuses")
    for h in heads:
        t = np.array(go_ms[h])
        print(f"0x{h:02X}    {np.median(t):>14.1f}{np.percentile(t, 99):>9.1f}{t.max():>9.1f}   {status[h]}")
    p = np.array(ping_ms)
    print(
        f"PING while both solve: n={p.size} p50 {np.median(p):.1f} ms, p99 {np.percentile(p, 99):.1f} ms, "
        f"max {p.max():.1f} ms; every reply came from the head addressed (the client checks source and CRC)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
