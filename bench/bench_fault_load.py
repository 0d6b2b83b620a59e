"""How long a FAULT load holds the link thread (docs/ICD.md section 13, "A load is bounded"): the
worst scripts the limits let through, against a 1.7 MB and a 64 MiB catalog, each loaded
``--repeat`` times in process (Device.receive of the FAULT frame to its reply); prints the median
and the maximum per script, with the load average.

Usage: .venv/bin/python bench/bench_fault_load.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import cpu_name  # noqa: E402
from firmware_model.device.device import Device  # noqa: E402
from firmware_model.device.faults import MAX_UPSET_WORDS  # noqa: E402
from protocol import nsp  # noqa: E402
from protocol.commands import MAX_FAULT_SCRIPT, Code, FaultAction, FaultRequest, Slot  # noqa: E402

CATALOGS = {"1.7 MB": 1_711_896, "64 MiB": 64 << 20}  #: catalog image sizes (bytes)


REGIONS = ("scratch", "ram", "result", "catalog")


def _fill(line: str, limit: int = MAX_FAULT_SCRIPT) -> str:
    """``line`` (with ``{i}`` and ``{r}``, the regions in turn) repeated for as many whole lines
    as one FAULT load carries."""
    text, i = "", 0
    while len(text) + len(line.format(i=i, r=REGIONS[i % 4])) <= limit:
        text += line.format(i=i, r=REGIONS[i % 4])
        i += 1
    return text


SCRIPTS = {
    f"1 line count={MAX_UPSET_WORDS}": f"edac_upset region=catalog bits=2 count={MAX_UPSET_WORDS}\n",
    "count=12800 a line": _fill("edac_upset region=catalog bits=1 count=12800 seed={i}\n"),
    "every region in turn, count=3000 a line": _fill("edac_upset region={r} bits=2 count=3000 seed={i}\n"),
}


def frame(action: FaultAction, script: str = "") -> bytes:
    return nsp.command(
        nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, Code.FAULT, FaultRequest(action, script.encode()).pack()
    ).frame()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    print(f"bench_fault_load --repeat {args.repeat}: {cpu_name()}, load average {os.getloadavg()[0]:.1f} at start")
    worst = 0.0
    for cat, size in CATALOGS.items():
        dev = Device(fault_injection=True)
        dev.store.set_active(Slot.CATALOG, bytes(size))
        for name, script in SCRIPTS.items():
            times = []
            for _ in range(args.repeat):
                dev.receive(frame(FaultAction.CLEAR))
                t0 = time.perf_counter()
                (reply,) = dev.receive(frame(FaultAction.LOAD, script))
                times.append(time.perf_counter() - t0)
            times.sort()
            worst = max(worst, times[-1])
            lines = script.count("\n")
            print(
                f"{cat} catalog: {name} ({lines} lines, {len(script)} bytes): armed {dev.faults.armed}, "
                f"median {1e3 * times[len(times) // 2]:.0f} ms, max {1e3 * times[-1]:.0f} ms"
            )
    print(f"worst FAULT load: {1e3 * worst:.0f} ms; load average {os.getloadavg()[0]:.1f} at the end")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
