"""The NAND model's figures (issue 45, docs/ICD.md section 15), through the link of a device in
maintenance mode: the flash error counts after N read cycles of the application image, and after
Rewrite NAND; and a kill -9 during erases and writes that loses nothing acknowledged.

    .venv/bin/python bench/bench_nand.py [--cycles 1000,5000,20000] [--kills 5]

Part A runs the NAND Read Disturbance Test (subcommand 13) over the image's first block (64 pages)
for each cycle count on a fresh device, then reads every page (Read NAND Page: the counts), Rewrite
NAND, and reads them again. Part B starts a child that erases and programs one block after another,
printing each once the call returned, kills it -9 after a random number of them, reloads the NAND
from its folder and checks every printed page.
"""

from __future__ import annotations

import argparse
import os
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _send(dev, data: bytes):
    from protocol import nsp, slip
    from protocol.commands import Code

    frames = dev.receive(nsp.command(0x0E, 0x11, Code.CRC, data).frame())
    return nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(frames[0])[0].data)


def part_a(cycles: list[int]) -> None:
    from firmware_model.device.device import Device
    from firmware_model.device.nand import APP_BLOCK, MAINTENANCE_ADDRESS
    from protocol import flash, nsp, slip
    from protocol.commands import Code
    from protocol.flash import PAGES_PER_BLOCK, Sub

    first = APP_BLOCK * PAGES_PER_BLOCK
    last = first + PAGES_PER_BLOCK - 1
    print(f"A. read disturbance over pages {first}-{last} (one block), one bit per 100 000 page reads of a block")
    print(f"{'cycles':>8}{'reads':>11}{'test':>20}{'corrected':>11}{'uncorr.':>9}{'bad':>5}   after Rewrite NAND")
    for n in cycles:
        dev = Device()
        dev.receive(nsp.command(0x0E, 0x11, Code.INIT, struct.pack("<I", MAINTENANCE_ADDRESS)).frame())
        t0 = time.perf_counter()
        frames = dev.receive(
            nsp.command(0x0E, 0x11, Code.CRC, flash.command(Sub.READ_DISTURB_TEST, first, last, n)).frame()
        )
        rep = nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(frames[0])[0].data)
        took = time.perf_counter() - t0
        outcome = "ok" if rep.ack else f"ECC p{flash.unpack_failure(rep.data)[3]}"
        for page in range(first, last + 1):  # the flight software reads every page: the counts
            _send(dev, flash.command(Sub.READ_PAGE, page))
        before = dev.maintenance.nand.error_counts()
        _send(dev, flash.command(Sub.REWRITE_NAND, first, last))
        for page in range(first, last + 1):
            _send(dev, flash.command(Sub.READ_PAGE, page))
        after = dev.maintenance.nand.error_counts()
        print(
            f"{n:>8}{n * PAGES_PER_BLOCK:>11}{outcome:>14} {took:>4.1f}s{before[0]:>11}{before[1]:>9}{before[2]:>5}"
            f"   {after[0]} / {after[1]} / {after[2]}"
        )


CHILD = """
import sys
from firmware_model.device.nand import Nand
from protocol.flash import PAGES_PER_BLOCK, PAGE_BYTES
nand = Nand(sys.argv[1])
for k in range(100000):
    block = 100 + k % 500
    nand.erase_block(block)
    nand.write_page(block * PAGES_PER_BLOCK, (k % 256).to_bytes(1, "little") * PAGE_BYTES)
    print(k, flush=True)
"""


def part_b(kills: int) -> None:
    from firmware_model.device.nand import Nand
    from protocol.flash import PAGE_BYTES, PAGES_PER_BLOCK

    rng = np.random.default_rng(45)
    print(f"\nB. kill -9 during erases and writes, {kills} runs")
    for run in range(kills):
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp) / "nand"
            stop_after = int(rng.integers(5, 60))
            child = subprocess.Popen([sys.executable, "-c", CHILD, str(root)], stdout=subprocess.PIPE, text=True)
            acked: dict[int, int] = {}
            assert child.stdout is not None
            while len(acked) < stop_after:
                line = child.stdout.readline()
                if not line:
                    break
                k = int(line)
                acked[100 + k % 500] = k
            time.sleep(float(rng.uniform(0, 0.05)))  # into the next erase or write
            os.kill(child.pid, signal.SIGKILL)
            child.wait()
            nand = Nand(root)
            lost = [b for b, k in acked.items() if nand.read_page(b * PAGES_PER_BLOCK) != bytes([k % 256]) * PAGE_BYTES]
            leftovers = len(list(root.glob("*.tmp")))
            print(
                f"  run {run + 1}: {len(acked)} acknowledged writes, killed, reloaded: {len(lost)} lost; {leftovers} .tmp left"
            )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", default="1000,5000,20000", help="read cycles of the disturbance test, comma-separated")
    ap.add_argument("--kills", type=int, default=5)
    args = ap.parse_args()
    part_a([int(c) for c in args.cycles.split(",")])
    part_b(args.kills)
    return 0


if __name__ == "__main__":
    sys.exit(main())
