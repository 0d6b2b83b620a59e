"""The link keeps answering while the device works: a catalog COMMIT is answered (its pattern
index built in another process, seconds for this catalog), PINGs are answered while it is built,
and while a GO sequence solves a dense frame (thousands of blobs and hot pixels) they are answered
with the sequence still running (BUSY). The device is a separate process on a pty, as in flight.

No clock decides: every wait is a hang guard (tests/guards.py), and "answered during the GO" is
shown by the banners (BUSY while the sequence runs), not by a round-trip time. The round trips
themselves (~1-30 ms) and the COMMIT's (~10 ms, not the ~4 s of building the index) are
bench/bench_link_during_go.py's figures; that the COMMIT leaves the build to another process and a
GO waits for it is tests/test_ready.py's (the build held open by a gate)."""

import json
import time

import numpy as np
import pytest
from guards import HANG_S, REPLY_S

from firmware_model.catalog.image_io import catalog_to_image
from firmware_model.pipeline.raw_frame import Frame, frame_to_bytes
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.link.client import Client
from ground.testing import tetra3 as tetra3_setup
from ground.testing.device_proc import DeviceProcess
from protocol import result
from protocol.commands import Slot

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


def test_pings_are_answered_during_the_index_build_and_a_dense_frame_go(catalog_image, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # no cached index: the COMMIT builds it
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps(CAMERA.to_dict()))
    frame = frame_to_bytes(dense_frame(blobs=3000, hot=40_000))
    with DeviceProcess("--pty", "--state", str(tmp_path / "state"), "--camera", str(camera)) as dev:
        with Client(dev.path, timeout=REPLY_S) as c:
            c.ping()  # a client's first command drains the line first
            c.init()
            c.upload(Slot.CATALOG, catalog_image, progress=False, commit=False)
            assert c.xfer_commit(Slot.CATALOG).active
            during_build = [c.ping() for _ in range(20)]  # answered while the index is built elsewhere
            c.upload(Slot.FRAME, frame, progress=False)
            c.go()
            during_go = []
            deadline = time.monotonic() + HANG_S * 4  # a hang guard: the solve takes seconds
            while time.monotonic() < deadline:
                during_go.append(c.ping())
                if during_go[-1].endswith("IDLE"):
                    break
                time.sleep(0.01)
            status = result.status_of(int(c.read_result_record()["return_code"]))
        assert dev.alive, dev.stderr()
    assert all(b.startswith("ST16-EMU") for b in during_build), during_build
    assert during_go[-1].endswith("IDLE") and status != result.Status.SOLVER_ERROR, (during_go[-1], status)
    # the link answered while the sequence ran (it waited for the index, then solved), not only after it
    assert sum("BUSY" in b for b in during_go) >= 3, during_go
