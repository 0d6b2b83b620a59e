"""The link keeps answering while the device works: a catalog COMMIT is answered without waiting
for the catalog's pattern index (built in another process, seconds for this catalog), PINGs are
answered while it is built, and while a GO sequence solves a dense frame (thousands of blobs and
hot pixels). The device is a separate process on a pty, as in flight.

The bounds are generous (0.5 s where the figures are ~1-30 ms, bench/bench_link_during_go.py): they
catch work done on the link thread or a call holding the GIL for seconds, not a slow machine."""

import json
import time

import numpy as np
import pytest

from firmware_model.catalog.image_io import catalog_to_image
from firmware_model.pipeline.raw_frame import Frame, frame_to_bytes
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.link.client import Client
from ground.testing import tetra3 as tetra3_setup
from ground.testing.device_proc import DeviceProcess
from protocol import result
from protocol.commands import Slot

BOUND_S = 0.5  #: the longest a PING may take
#: the longest the COMMIT may take: it parses the 2.9 MB image (~10 ms) and writes it with an fsync;
#: building the index here as well would take 2.6 s or more (~4 s of building, in another process)
COMMIT_BOUND_S = 1.5
CAMERA = tetra3_setup.DATASHEET_CAMERA


@pytest.fixture(scope="module")
def catalog_image() -> bytes:
    """A catalog whose image parses in hundredths of a second but whose pattern index for CAMERA
    takes ~4 s to build: 8 800 stars to V 6.5, pairs up to 6 deg."""
    design = CatalogDesign(
        theta_fov_deg=4.33, sensor_width_px=1024, sensor_height_px=768, m_thresh=6.5, phi_max_deg=6.0, epoch=2019.6
    )
    return catalog_to_image(build_catalog(design))


def dense_frame(blobs: int, hot: int) -> Frame:
    rng = np.random.default_rng(7)
    h, w = CAMERA.height, CAMERA.width
    img = rng.normal(100.0, 4.0, (h, w))
    yy, xx = np.mgrid[-3:4, -3:4]
    kernel = np.exp(-(xx**2 + yy**2) / (2 * 1.2**2))
    for y, x, a in zip(rng.integers(3, h - 4, blobs), rng.integers(3, w - 4, blobs), rng.uniform(200, 3000, blobs)):
        img[y - 3 : y + 4, x - 3 : x + 4] += a * kernel
    img.flat[rng.choice(h * w, hot, replace=False)] = rng.uniform(1000, 4095, hot)
    return Frame(pixels=np.clip(img, 0, 4095).astype(np.uint16), pattern="RGGB", black_level=64, white_level=4095)


def timed(call):
    t0 = time.perf_counter()
    value = call()
    return value, time.perf_counter() - t0


def test_pings_are_answered_during_the_index_build_and_a_dense_frame_go(catalog_image, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # no cached index: the COMMIT builds it
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps(CAMERA.to_dict()))
    frame = frame_to_bytes(dense_frame(blobs=3000, hot=40_000))
    with DeviceProcess("--pty", "--state", str(tmp_path / "state"), "--camera", str(camera)) as dev:
        with Client(dev.path, timeout=10.0) as c:
            c.ping()  # a client's first command drains the line first
            c.init()
            c.upload(Slot.CATALOG, catalog_image, progress=False, commit=False)
            reply, commit_s = timed(lambda: c.xfer_commit(Slot.CATALOG))
            assert reply.active and commit_s < COMMIT_BOUND_S, commit_s
            during_build = []
            t_end = time.monotonic() + 2.0
            while time.monotonic() < t_end:
                during_build.append(timed(c.ping)[1])
                time.sleep(0.01)
            c.upload(Slot.FRAME, frame, progress=False)
            c.go()
            during_go = []
            t_end = time.monotonic() + 120.0
            while time.monotonic() < t_end:
                banner, seconds = timed(c.ping)
                during_go.append(seconds)
                if banner.endswith("IDLE"):
                    break
                time.sleep(0.01)
            status = result.status_of(int(c.read_result_record()["return_code"]))
        assert dev.alive, dev.stderr()
    assert banner.endswith("IDLE") and status != result.Status.SOLVER_ERROR, (banner, status, dev.stderr())
    assert len(during_go) > 3  # the GO waited for the index, then solved: PINGed throughout
    assert max(during_build) < BOUND_S, sorted(during_build)[-5:]
    assert max(during_go) < BOUND_S, sorted(during_go)[-5:]
