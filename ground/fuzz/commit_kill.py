"""SIGKILL of ``st16-device`` while it commits a catalog, at random moments: every restart must
find the old catalog or the new one, intact, in SLOT_INFO and in ``slot0/active.img``."""

from __future__ import annotations

import random
import signal
import tempfile
import time
from pathlib import Path

from firmware_model.device.slots import unpack_image
from ground.fuzz.checks import ping_check, stderr_check
from ground.fuzz.device_proc import DeviceProcess
from ground.fuzz.tally import Tally
from ground.fuzz.upload_faults import catalog_image
from ground.link.client import Client, LinkError
from protocol import nsp
from protocol.commands import Code, SlotRequest
from protocol.crc import crc32

WINDOW = 0.03  #: seconds after the COMMIT within which the kill lands (uniformly)


def run(seed: int, kills: int) -> tuple[Tally, dict[str, int]]:
    """``kills`` commits killed at random moments; the tally and how many restarts found the old
    and the new catalog."""
    rng = random.Random(seed)
    found = {"old": 0, "new": 0}
    images = [catalog_image(seed * 10 + 1, n=2000), catalog_image(seed * 10 + 2, n=2000)]
    tally = Tally()
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp)
        device = DeviceProcess("--pty", "--state", str(state))
        with Client(device.path, timeout=5.0, retries=0) as c:
            c.upload(0, images[0], progress=False)
        active = {crc32(images[0])}
        for k in range(kills):
            new = images[(k + 1) % 2]
            with Client(device.path, timeout=5.0, retries=0) as c:
                c.upload(0, new, progress=False, commit=False)
                tally.messages += len(new) // 4096 + 2
                c.write_raw(
                    nsp.command(nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, Code.XFER_COMMIT, SlotRequest(0).pack()).frame()
                )
                time.sleep(rng.uniform(0.0, WINDOW))
                device.stop(signal.SIGKILL)
            tally.faults += 1
            stderr_check(device, tally)
            allowed = active | {crc32(new)}
            device = DeviceProcess("--pty", "--state", str(state))
            with Client(device.path, timeout=5.0, retries=0) as c:
                try:
                    info = c.slot_info(0)
                    tally.messages += 1
                    if not info.active or info.crc32 not in allowed:
                        tally.fail("state_corruptions", f"kill {k}: slot 0 {info.active} 0x{info.crc32:08X}")
                    found["new" if info.crc32 == crc32(new) else "old"] += 1
                    active = {info.crc32}
                except LinkError as exc:
                    tally.fail("unanswered_pings", f"kill {k}: {exc}")
                ping_check(c, tally, device)
            try:
                if crc32(unpack_image((state / "slot0" / "active.img").read_bytes())) not in allowed:
                    tally.fail("state_corruptions", f"kill {k}: active.img holds another image")
            except (OSError, ValueError) as exc:
                tally.fail("state_corruptions", f"kill {k}: active.img {exc}")
        if device.stop() != 0:
            tally.fail("crashes", "exit code at stop")
        stderr_check(device, tally)
    return tally, found
