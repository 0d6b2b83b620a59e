"""Frame uploads over the link (slot 1): an upload cut short never leaks into the next frame's."""

import numpy as np

from firmware_model.pipeline.raw_frame import Frame, frame_to_bytes
from ground.link.client import Client
from ground.testing.device_proc import DeviceProcess
from protocol.commands import Slot, XferState
from protocol.crc import crc32


def _frame(seed: int) -> Frame:
    pixels = np.random.default_rng(seed).integers(0, 4096, (1944, 2592), dtype=np.uint16)  # the device's camera
    return Frame(pixels, "RGGB", (64.0,) * 4, 4095.0, exposure_s=0.1)


def test_an_upload_cut_short_is_not_resumed_by_a_different_frame():
    """Frame A's upload stops part way (the client was interrupted); frame B, of the same size,
    is uploaded and commits. Version-1 frame blobs all had one CRC-32, so B's BEGIN resumed A's
    bytes and the COMMIT failed CRC_MISMATCH (Ctrl-C during replay, then solve)."""
    first, second = frame_to_bytes(_frame(1)), frame_to_bytes(_frame(2))
    assert len(first) == len(second) and crc32(first) != crc32(second)
    with DeviceProcess("--pty") as device, Client(device.path, timeout=5.0) as client:
        client.init()
        client.xfer_begin(Slot.FRAME, len(first), crc32(first))
        client.xfer_data(Slot.FRAME, 0, first[:4000])
        begun = client.xfer_begin(Slot.FRAME, len(second), crc32(second))
        assert begun.received == 0 and begun.crc32 == crc32(second)  # A's leftover cleared, not resumed
        report = client.upload(Slot.FRAME, second, progress=False)
        assert report.resumed_from == 0
        image = client.slot_info(Slot.FRAME)
        assert image.active and image.crc32 == crc32(second)
        assert client.xfer_status(Slot.FRAME).state == XferState.NONE
