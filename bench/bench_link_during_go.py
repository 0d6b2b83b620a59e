"""PING latency over the link while the device works (prints figures; no asserts).

The device runs as a separate process on a pty (``st16-device --pty --state DIR``, as the demo
starts it) and is PINGed every ``--interval`` s (default 10 ms) while it

* starts up (the first seconds after ``listening on``): with no catalog, and with a stored one;
* commits a catalog (the demo's: Hipparcos V <= 6.5 for the reference design) with an empty
  pattern-index cache: the COMMIT round trip itself, then the PINGs of the following seconds;
* runs GOs on an uploaded frame: one rendered at a known attitude (as the demo renders them),
  a dense synthetic frame with ``--blobs`` star-like blobs, one with ``--hot`` hot pixels (both at
  the reference design's 2592 x 1944);
* runs GOs from a ``--frames`` capture source: the real tetra3 frames of ../shared/data (skipped
  when absent) with their datasheet camera, and large legal images (an RGB JPEG and a zlib TIFF
  of ``--big-side``\\ ² uint16 px, under frame_readers.MAX_FRAME_PIXELS: decoded, then refused as
  the wrong size for the camera).

Per phase it prints the number of PINGs, median, p99 and max round trip (target: p99 <= 50 ms).
Run it quiet and beside three busy loops
(``for i in 1 2 3; do timeout 300 sh -c 'while :; do :; done' & done``) and state the load.

Usage: .venv/bin/python bench/bench_link_during_go.py [--interval 0.01] [--phases start,commit,...]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ground.link.client import Client
from ground.testing.device_proc import DeviceProcess

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
PHASES = ("start", "commit", "go", "real", "big")


class Pinger:
    """PINGs ``client`` every ``interval`` s and keeps the round trips (s)."""

    def __init__(self, client: Client, interval: float):
        self.client = client
        self.interval = interval
        client.ping()  # not timed: a client's first command drains the line first (~50 ms)

    def until(self, done: Callable[[str], bool], limit: float) -> tuple[list[float], float]:
        """PING until ``done(banner)`` or ``limit`` s; (round trips, seconds it took)."""
        times: list[float] = []
        t_start = time.perf_counter()
        while True:
            t0 = time.perf_counter()
            banner = self.client.ping()
            t1 = time.perf_counter()
            times.append(t1 - t0)
            if done(banner) or t1 - t_start > limit:
                return times, t1 - t_start
            time.sleep(max(0.0, self.interval - (time.perf_counter() - t0)))

    def for_s(self, seconds: float) -> list[float]:
        return self.until(lambda _: False, seconds)[0]


def row(label: str, times: list[float], note: str = "") -> None:
    if not times:
        print(f"{label:<44} no PINGs")
        return
    ms = np.array(times) * 1e3
    print(
        f"{label:<44}{len(ms):>6}{np.median(ms):>10.2f}{np.percentile(ms, 99):>10.2f}{ms.max():>10.1f}"
        f"{'  ' + note if note else ''}",
        flush=True,
    )


def header() -> None:
    print(f"{'phase':<44}{'PINGs':>6}{'median':>10}{'p99':>10}{'max':>10}  (ms)", flush=True)


def demo_catalog_image() -> bytes:
    from firmware_model.catalog.image_io import catalog_to_image
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    return catalog_to_image(build_catalog(CatalogDesign()))


def rendered_frame():
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_from_image
    from ground.sim.device_process import pick_attitudes
    from ground.sim.sensor_sim import DetectorModel, render_frame
    from ground.sim.sky_model import sky_stars

    camera = CameraModel.reference_design()
    catalog = catalog_from_image(demo_catalog_image())
    (a,) = pick_attitudes(catalog, camera, 1, np.random.default_rng(2026))
    return render_frame(sky_stars(), a, camera, DetectorModel(pattern="RGGB"), seed=2026).frame


def dense_frame(blobs: int = 0, hot: int = 0, seed: int = 0):
    """A reference-design RGGB frame with ``blobs`` star-like blobs (sigma ~1.2 px) and ``hot``
    single hot pixels on a noisy background."""
    from firmware_model.camera import REFERENCE_HEIGHT, REFERENCE_WIDTH
    from firmware_model.pipeline.raw_frame import Frame

    rng = np.random.default_rng(seed)
    h, w = REFERENCE_HEIGHT, REFERENCE_WIDTH
    img = rng.normal(100.0, 4.0, (h, w))
    if blobs:
        yy, xx = np.mgrid[-3:4, -3:4]
        kernel = np.exp(-(xx**2 + yy**2) / (2 * 1.2**2))
        ys = rng.integers(3, h - 4, blobs)
        xs = rng.integers(3, w - 4, blobs)
        amp = rng.uniform(200, 3000, blobs)
        for y, x, a in zip(ys, xs, amp):
            img[y - 3 : y + 4, x - 3 : x + 4] += a * kernel
    if hot:
        img.flat[rng.choice(h * w, hot, replace=False)] = rng.uniform(1000, 4095, hot)
    pixels = np.clip(img, 0, 4095).astype(np.uint16)
    return Frame(pixels=pixels, pattern="RGGB", black_level=64, white_level=4095)


def go_phase(c: Client, pinger: Pinger, label: str, limit: float = 180.0) -> None:
    c.go()
    times, took = pinger.until(lambda banner: banner.endswith("IDLE"), limit)
    rec = c.read_result_record()
    from protocol import result

    status = result.status_of(int(rec["return_code"]))
    name = status.name if isinstance(status, result.Status) else str(status)
    row(label, times, f"GO {took:.2f} s, {name}")


def start_device(state: Path, *extra: str, env: dict[str, str]) -> tuple[DeviceProcess, float]:
    t0 = time.perf_counter()
    old = dict(os.environ)
    os.environ.update(env)
    try:
        dev = DeviceProcess("--pty", "--state", str(state), *extra)
    finally:
        os.environ.clear()
        os.environ.update(old)
    return dev, time.perf_counter() - t0


def bench(args, env: dict[str, str], work: Path) -> None:
    from firmware_model.pipeline.raw_frame import frame_to_bytes
    from protocol.commands import Slot

    interval = args.interval
    state = work / "state"
    image = demo_catalog_image()
    phases = set(args.phases.split(","))
    header()
    dev, up = start_device(state, env=env)
    try:
        with Client(dev.path, timeout=30.0) as c:
            pinger = Pinger(c, interval)
            if "start" in phases:
                row("start-up, no catalog: first 5 s", pinger.for_s(5.0), f"listening after {up:.1f} s")
            c.init()
            c.upload(Slot.CATALOG, image, progress=False, commit=False)
            t0 = time.perf_counter()
            c.xfer_commit(Slot.CATALOG)
            commit_s = time.perf_counter() - t0
            if "commit" in phases:
                row("catalog COMMIT (the reply)", [commit_s])
                row("after COMMIT: next 10 s", pinger.for_s(10.0))
            if "go" in phases:
                frames = [
                    ("GO, rendered frame (demo)", rendered_frame()),
                    (f"GO, dense frame: {args.blobs} blobs", dense_frame(blobs=args.blobs)),
                    (f"GO, dense frame: {args.hot} hot pixels", dense_frame(hot=args.hot, seed=1)),
                ]
                for label, frame in frames:
                    c.upload(Slot.FRAME, frame_to_bytes(frame), progress=False)
                    go_phase(c, pinger, label)
    finally:
        dev.stop()
    if "start" in phases:
        dev, up = start_device(state, env=env)
        try:
            with Client(dev.path, timeout=30.0) as c:
                row(
                    "start-up, stored catalog: first 5 s", Pinger(c, interval).for_s(5.0), f"listening after {up:.1f} s"
                )
        finally:
            dev.stop()
    if "real" in phases:
        real(args, env, work)
    if "big" in phases:
        big(args, env, work, image)


def real(args, env: dict[str, str], work: Path) -> None:
    frames = SHARED / "frames" / "tetra3-mono"
    if not frames.is_dir():
        print("real frames: ../shared/data/frames/tetra3-mono absent; skipped")
        return
    from firmware_model.catalog.image_io import catalog_to_image
    from ground.catalog.build import build_catalog
    from ground.testing import tetra3 as tetra3_setup
    from protocol.commands import Slot

    camera = tetra3_setup.DATASHEET_CAMERA
    cam = work / "tetra3.json"
    cam.write_text(json.dumps(camera.to_dict()))
    design = tetra3_setup.catalog_design()
    image = catalog_to_image(build_catalog(design))
    paths = sorted(frames.glob("*.tiff"))[: args.real]
    dev, _ = start_device(work / "state-real", "--camera", str(cam), "--frames", str(frames), env=env)
    try:
        with Client(dev.path, timeout=30.0) as c:
            pinger = Pinger(c, args.interval)
            c.init()
            c.upload(Slot.CATALOG, image, progress=False, commit=False)
            t0 = time.perf_counter()
            c.xfer_commit(Slot.CATALOG)
            row("tetra3 catalog COMMIT (the reply)", [time.perf_counter() - t0])
            for p in paths:
                go_phase(c, pinger, f"GO, real tetra3 {p.name[-26:-5]}")
    finally:
        dev.stop()


def big(args, env: dict[str, str], work: Path, image: bytes) -> None:
    """GOs from a ``--frames`` folder of two large legal images (under MAX_FRAME_PIXELS, the wrong
    size for the camera: decoded, then BAD_FRAME): an RGB JPEG and a zlib uint16 TIFF."""
    import tifffile
    from PIL import Image

    from protocol.commands import Slot

    side = args.big_side
    folder = work / "big"
    folder.mkdir()
    rng = np.random.default_rng(3)
    Image.fromarray(rng.integers(0, 256, (side * 3 // 4, side, 3), dtype=np.uint8)).save(folder / "a.jpg", quality=90)
    pixels = rng.integers(0, 4096, (side, side), dtype=np.uint16)
    tifffile.imwrite(folder / "b.tiff", pixels, compression="zlib")
    del pixels
    sizes = [(folder / name).stat().st_size >> 20 for name in ("a.jpg", "b.tiff")]
    dev, _ = start_device(work / "state-big", "--frames", str(folder), env=env)
    try:
        with Client(dev.path, timeout=30.0) as c:
            pinger = Pinger(c, args.interval)
            c.init()
            c.upload(Slot.CATALOG, image, progress=False)
            pinger.for_s(3.0)  # the index is built
            go_phase(c, pinger, f"GO, {side}x{side * 3 // 4} RGB JPEG ({sizes[0]} MB)")
            go_phase(c, pinger, f"GO, {side}^2 uint16 zlib TIFF ({sizes[1]} MB)")
    finally:
        dev.stop()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--interval", type=float, default=0.01, help="seconds between PINGs")
    ap.add_argument("--phases", default=",".join(PHASES), help=f"comma-separated, of {','.join(PHASES)}")
    ap.add_argument("--blobs", type=int, default=30_000)
    ap.add_argument("--hot", type=int, default=500_000)
    ap.add_argument("--real", type=int, default=3, help="real tetra3 frames to solve")
    ap.add_argument("--big-side", type=int, default=11_000, help="side of the large legal TIFF (px)")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}, {os.cpu_count()} cores", flush=True)
    with tempfile.TemporaryDirectory(prefix="st16-bench-latency-") as tmp:
        work = Path(tmp)
        # an empty pattern-index cache: the COMMIT builds the index (as for a catalog never seen)
        env = {"XDG_CACHE_HOME": str(work / "cache")}
        bench(args, env, work)
    print(f"load average {os.getloadavg()[0]:.2f} at the end", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
