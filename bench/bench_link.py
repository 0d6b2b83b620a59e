"""Link benchmarks over a real pty between two processes (prints figures; no asserts).

1. PING round trip, unpaced: median and p99, against a baseline measured in the same run: a
   bare pty echo process (same Python I/O, no protocol).
2. Upload through the transfer extension to a device paced at 115 200 baud: payload throughput
   as a fraction of the line rate (baseline: the line rate itself).
3. Soak: N mixed commands (default 100 000) with content checks; device resident memory after
   warm-up vs at the end; lost (timeouts) and misattributed (wrong content / stale) replies.

Usage: .venv/bin/python bench/bench_link.py [--pings 3000] [--upload-kib 96] [--soak 100000]
"""

from __future__ import annotations

import argparse
import json
import random
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ground.link.client import Client, LinkError, Nack
from protocol import nsp, slip
from protocol.commands import Code

ECHO = r"""
import os, select, sys, tty
m, s = os.openpty(); tty.setraw(s); print("listening on " + os.ttyname(s), flush=True)
buf = b""
while True:
    select.select([m], [], [])
    buf += os.read(m, 65536)
    while b"\xc0" in buf[1:]:
        end = buf.index(b"\xc0", 1) + 1
        os.write(m, buf[:end]); buf = buf[end:]
"""


def start(cmd: list[str]) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    line = proc.stdout.readline().strip()
    if not line.startswith("listening on "):
        raise RuntimeError(f"device did not start: {line!r}")
    return proc, line.split(" ", 2)[2]


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    proc.wait(timeout=10)


def device_cmd(*extra: str) -> list[str]:
    script = Path(sys.executable).parent / "st16-device"
    base = [str(script)] if script.exists() else [sys.executable, "-m", "firmware_model.device.cli"]
    return base + ["--pty", *extra]


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def percentiles(samples: list[float]) -> tuple[float, float]:
    arr = np.array(samples) * 1e3
    return float(np.median(arr)), float(np.percentile(arr, 99))


def bench_ping(n: int) -> None:
    proc, path = start(device_cmd())
    try:
        with Client(path) as c:
            for _ in range(200):
                c.ping()
            times = []
            for _ in range(n):  # no progress bar inside the timed loop (a fraction of a second)
                t0 = time.perf_counter()
                c.ping()
                times.append(time.perf_counter() - t0)
    finally:
        stop(proc)
    echo, echo_path = start([sys.executable, "-c", ECHO])
    try:
        import serial

        frame = nsp.command(0x0E, 0x11, Code.PING).frame()
        with serial.Serial(echo_path, timeout=1) as ser:
            base = []
            for i in range(n + 200):
                t0 = time.perf_counter()
                ser.write(frame)
                got = ser.read(len(frame))
                if i >= 200:
                    base.append(time.perf_counter() - t0)
                assert got == frame
    finally:
        stop(echo)
    med, p99 = percentiles(times)
    bmed, bp99 = percentiles(base)
    print(
        f"PING round trip over pty, unpaced ({n} samples): median {med:.3f} ms, p99 {p99:.3f} ms (target median < 1 ms)"
    )
    print(
        f"  baseline bare pty echo of the same frame: median {bmed:.3f} ms, p99 {bp99:.3f} ms; "
        f"ratio median {med / bmed:.2f}x"
    )


def bench_upload(kib: int, baud: int = 115200) -> None:
    """A frame of random pixels into slot 1 (the device validates what it receives), sized to
    about ``kib`` KiB with a small camera model."""
    import tempfile

    from firmware_model.camera import CameraModel
    from firmware_model.pipeline.raw_frame import Frame, frame_to_bytes

    width = 256
    height = max(2, (kib * 1024 // (2 * width)) // 2 * 2)
    camera = CameraModel.from_fov(width, height, 7.5)
    pixels = np.random.default_rng(0).integers(0, 4096, (height, width), dtype=np.uint16)
    data = frame_to_bytes(Frame(pixels=pixels, pattern="RGGB", black_level=64, white_level=4095))
    cam_file = Path(tempfile.mkdtemp()) / "camera.json"
    cam_file.write_text(json.dumps(camera.to_dict()))
    proc, path = start(device_cmd("--pace", "--baud", str(baud), "--camera", str(cam_file)))
    try:
        with Client(path, timeout=2.0) as c:
            report = c.upload(1, data, progress=True)
            info = c.slot_info(1)
    finally:
        stop(proc)
    line_bytes = baud / 10
    frac = len(data) / report.seconds / line_bytes
    wire = len(slip.escape(data)) + (len(data) // 4096 + 1) * 12
    print(
        f"paced upload at {baud} baud: {len(data)} B payload in {report.seconds:.2f} s = "
        f"{len(data) / report.seconds:.0f} B/s; line rate {line_bytes:.0f} B/s; fraction {frac:.3f} "
        f"(target >= 0.90); committed CRC-32 0x{info.crc32:08X} active={info.active}"
    )
    print(f"  framing-only bound for this payload (escaping + 12 B/message): {len(data) / wire:.3f}")


def bench_soak(n: int) -> None:
    rng = random.Random(1)
    proc, path = start(device_cmd())
    lost = misattributed = nacks_expected = nacks_seen = 0
    scratch = bytearray(256)
    ram = bytearray(4096)
    rss_warm = None
    kinds = ["ping", "read_edac", "write_edac", "diag", "peek", "poke", "result", "status", "unknown", "silent"]
    counts = dict.fromkeys(kinds, 0)
    t0 = time.perf_counter()
    try:
        with Client(path, timeout=1.0, retries=0) as c:
            c.init()
            for i in tqdm(range(n), desc="soak", leave=False):
                if i == n // 10:
                    rss_warm = rss_kib(proc.pid)
                kind = rng.choice(kinds)
                counts[kind] += 1
                try:
                    if kind == "ping":
                        ok = c.ping().startswith("ST16-EMU APPLICATION")
                    elif kind == "read_edac":
                        a = rng.randrange(0x100, 0x1F0)
                        k = rng.randrange(1, 0x200 - a)
                        ok = c.read_edac(a, k) == scratch[a - 0x100 : a - 0x100 + k]
                    elif kind == "write_edac":
                        a = rng.randrange(0x100, 0x1F0)
                        v = rng.randbytes(rng.randrange(1, 0x200 - a))
                        ok = c.write_edac(a, v) == len(v)
                        scratch[a - 0x100 : a - 0x100 + len(v)] = v
                    elif kind == "diag":
                        ok = c.diagnostic().accepted > 0
                    elif kind == "peek":
                        a = rng.randrange(0, 4000)
                        ok = c.peek(0x20000000 + a, 64) == ram[a : a + 64]
                    elif kind == "poke":
                        a = rng.randrange(0, 4000)
                        v = rng.randbytes(64)
                        ok = c.poke(0x20000000 + a, v) == 64
                        ram[a : a + 64] = v
                    elif kind == "result":
                        ok = len(c.read_result(0, 2616)) == 2616
                    elif kind == "status":
                        ok = c.xfer_status(0).slot == 0
                    elif kind == "unknown":
                        nacks_expected += 1
                        try:
                            c.transact(0x0C)
                            ok = False
                        except Nack as exc:
                            nacks_seen += 1
                            ok = exc.reason == 1
                    else:
                        a = rng.randrange(0x100, 0x1F0)
                        v = rng.randbytes(8)
                        c.send_silent(Code.WRITE_EDAC, struct.pack("<H", a) + v)
                        scratch[a - 0x100 : a - 0x100 + 8] = v
                        ok = True
                    if not ok:
                        misattributed += 1
                except Nack:
                    misattributed += 1
                except LinkError:
                    lost += 1
            stale = c.stale_replies
            diag = c.diagnostic()
            rss_end = rss_kib(proc.pid)
    finally:
        stop(proc)
    seconds = time.perf_counter() - t0
    growth = (rss_end - rss_warm) / rss_warm
    print(
        f"soak: {n} mixed commands in {seconds:.1f} s ({n / seconds:.0f}/s): lost {lost}, misattributed "
        f"{misattributed}, stale replies discarded {stale}, NACKs {nacks_seen}/{nacks_expected} as expected"
    )
    print(
        f"  device RSS after warm-up ({n // 10} commands) {rss_warm} KiB, at end {rss_end} KiB: growth "
        f"{100 * growth:+.2f} % (limit 10 %)"
    )
    print(
        f"  device counters: accepted {diag.accepted}, nacked {diag.nacked}, silent {diag.silent}, "
        f"errors framing/runt/oversize/badcrc {diag.framing}/{diag.runt}/{diag.oversize}/{diag.bad_crc}"
    )
    print(f"  mix: {counts}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pings", type=int, default=3000)
    ap.add_argument("--upload-kib", type=int, default=96)
    ap.add_argument("--soak", type=int, default=100_000)
    args = ap.parse_args()
    bench_ping(args.pings)
    bench_upload(args.upload_kib)
    if args.soak:
        bench_soak(args.soak)
    return 0


if __name__ == "__main__":
    sys.exit(main())
