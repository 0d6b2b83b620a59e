"""SIGKILL of ``st16-device`` while it commits a catalog, at random moments: every restart must
find the old catalog or the new one, intact, in SLOT_INFO and in ``slot0/active.img``.

Every other kill cuts the COMMIT of a catalog *patch* (slot 3, applied to slot 0's catalog) instead
of a whole catalog. A patch left pending by the kill is committed again after the restart: that
COMMIT must succeed and leave the patched catalog active, whether the killed one had installed it
already or not (it used to answer BASE_MISMATCH when the kill came after the new catalog was
installed and before the transfer was dropped: a patch stuck until an XFER ABORT by hand).
"""

from __future__ import annotations

import random
import signal
import tempfile
import time
from pathlib import Path

from firmware_model.device.slots import unpack_image
from ground.link.client import Client, LinkError, Nack
from ground.testing.checks import ping_check, stderr_check
from ground.testing.device_proc import DeviceProcess
from ground.testing.tally import Tally
from ground.testing.upload_faults import catalog_image
from protocol import nsp
from protocol.catalog_image import parse_image, with_star_colours
from protocol.catalog_patch import make_patch
from protocol.commands import Code, Slot, SlotRequest, XferState
from protocol.crc import crc32

WINDOW = 0.03  #: seconds after the COMMIT within which the kill lands (uniformly)


def recoloured(image: bytes, rng: random.Random) -> bytes:
    """``image`` with the colours of a few stars changed (what a patch of learned colours makes)."""
    stars = parse_image(image).stars
    rg, bg = stars["rg"].copy(), stars["bg"].copy()
    rows = rng.sample(range(len(rg)), 4)
    scale = rng.uniform(1.01, 1.1)
    rg[rows] *= scale
    bg[rows] /= scale
    return with_star_colours(image, rg, bg)


def _commit_and_kill(device: DeviceProcess, slot: int, data: bytes, rng: random.Random, tally: Tally) -> None:
    with Client(device.path, timeout=5.0, retries=0) as c:
        c.upload(slot, data, progress=False, commit=False)
        tally.messages += len(data) // 4096 + 2
        c.write_raw(
            nsp.command(nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, Code.XFER_COMMIT, SlotRequest(slot).pack()).frame()
        )
        time.sleep(rng.uniform(0.0, WINDOW))
        device.stop(signal.SIGKILL)
    tally.faults += 1


def _recommit_patch(c: Client, k: int, new: bytes, tally: Tally, found: dict[str, int]) -> int | None:
    """COMMIT slot 3 again if the kill left the patch pending; the CRC-32 of slot 0 after it."""
    status = c.xfer_status(Slot.CATALOG_PATCH)
    tally.messages += 1
    if status.state == XferState.NONE:
        return None
    found["patch_pending"] += 1
    found["patch_installed"] += c.slot_info(Slot.CATALOG).crc32 == crc32(new)  # killed between the two steps
    tally.messages += 1
    try:
        reply = c.xfer_commit(Slot.CATALOG_PATCH)
        tally.messages += 1
    except Nack as exc:
        found["stuck"] += 1
        tally.fail("bad_replies", f"kill {k}: the pending patch's COMMIT after the restart: {exc}")
        return None
    if reply.crc32 != crc32(new):
        tally.fail("state_corruptions", f"kill {k}: the re-committed patch left 0x{reply.crc32:08X} active")
    return reply.crc32


def run(seed: int, kills: int) -> tuple[Tally, dict[str, int]]:
    """``kills`` commits killed at random moments (every other one a patch's); the tally and how
    many restarts found the old and the new catalog, how many found a patch pending (of those, with
    its result installed already) and how many of those could not be committed again ("stuck")."""
    rng = random.Random(seed)
    found = {"old": 0, "new": 0, "patch_pending": 0, "patch_installed": 0, "stuck": 0}
    images = [catalog_image(seed * 10 + 1, n=2000), catalog_image(seed * 10 + 2, n=2000)]
    known = {crc32(image): image for image in images}
    tally = Tally()
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp)
        device = DeviceProcess("--pty", "--state", str(state))
        with Client(device.path, timeout=5.0, retries=0) as c:
            c.upload(0, images[0], progress=False)
        active = crc32(images[0])
        for k in range(kills):
            patching = k % 2 == 1
            if patching:
                new = recoloured(known[active], rng)
                known[crc32(new)] = new
                _commit_and_kill(device, Slot.CATALOG_PATCH, make_patch(known[active], new), rng, tally)
            else:
                new = images[1] if active == crc32(images[0]) else images[0]
                _commit_and_kill(device, Slot.CATALOG, new, rng, tally)
            stderr_check(device, tally)
            allowed = {active, crc32(new)}
            device = DeviceProcess("--pty", "--state", str(state))
            with Client(device.path, timeout=5.0, retries=0) as c:
                try:
                    info = c.slot_info(0)
                    tally.messages += 1
                    if not info.active or info.crc32 not in allowed:
                        tally.fail("state_corruptions", f"kill {k}: slot 0 {info.active} 0x{info.crc32:08X}")
                    found["new" if info.crc32 == crc32(new) else "old"] += 1
                    active = info.crc32 if info.crc32 in allowed else active
                    if patching:
                        active = _recommit_patch(c, k, new, tally, found) or active
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
