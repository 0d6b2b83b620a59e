"""Transfer (upload) faults against a device holding a catalog: interrupted, corrupted,
truncated, wrong version, out-of-order, overlapping and conflicting chunks, commit without all data, data
out of range or without BEGIN, a device killed mid-transfer.

Each scenario knows whether it must leave the active catalog as it was ("kept") or replace it
with the image it sent ("replaced": a valid image sent out of order or in overlapping chunks,
or with chunks carrying other bytes over received ones in between, which are NACKed CONFLICT).
After each one, SLOT_INFO and the state file ``slot0/active.img`` must hold exactly the
expected image, and a PING must be answered.
"""

from __future__ import annotations

import random
import signal
import struct
import tempfile
from pathlib import Path

import numpy as np

from firmware_model.device.slots import unpack_image
from ground.link.client import Client, LinkError, Nack
from ground.testing.checks import ping_check, stderr_check
from ground.testing.device_proc import DeviceProcess
from ground.testing.tally import Tally
from protocol.catalog_image import HEADER_SIZE, Reason
from protocol.commands import Code, NackReason, XferBegin, XferData
from protocol.crc import crc32

SLOT = 0
CHUNK = 2048


def catalog_image(seed: int, n: int = 300) -> bytes:
    """A valid catalog image of ``n`` random stars (the device validates slot 0)."""
    from firmware_model.catalog.image_io import catalog_to_image
    from firmware_model.catalog.onboard import OnboardCatalog
    from firmware_model.reference_frames import radec_to_vec

    rng = np.random.default_rng(seed)
    vec = radec_to_vec(rng.uniform(0, 2 * np.pi, n), np.arcsin(rng.uniform(-1, 1, n)))
    cat = OnboardCatalog.build(
        np.arange(1, n + 1),
        vec,
        rng.uniform(0, 5, n),
        rng.uniform(0.7, 1.3, n),
        rng.uniform(0.6, 1.1, n),
        phi_min=1e-3,
        phi_max=0.35,
        n_h=128,
        meta={"epoch": 2025.0, "source": "hipparcos", "colour_source": np.full(n, 2)},
    )
    return catalog_to_image(cat, created_unix=1_700_000_000 + seed)


def wrong_version(image: bytes, version: int = 2) -> bytes:
    """``image`` claiming another format version, its header CRC re-signed."""
    out = bytearray(image)
    out[8:10] = struct.pack("<H", version)
    out[HEADER_SIZE - 4 : HEADER_SIZE] = struct.pack("<I", crc32(bytes(out[: HEADER_SIZE - 4])))
    return bytes(out)


def _send(c: Client, data: bytes, pieces: list[tuple[int, int]], tally: Tally) -> None:
    for off, n in pieces:
        c.xfer_data(SLOT, off, data[off : off + n])
        tally.messages += 1


def _chunks(length: int, size: int = CHUNK) -> list[tuple[int, int]]:
    return [(o, min(size, length - o)) for o in range(0, length, size)]


def _expect_nack(tally: Tally, reasons: tuple[int, ...], call, *args) -> None:
    tally.messages += 1
    try:
        call(*args)
    except Nack as exc:
        if exc.reason not in reasons:
            tally.fail("bad_replies", f"NACK {exc} where {[hex(r) for r in reasons]} was expected")
        return
    tally.fail("bad_replies", f"{call.__name__} accepted where a NACK {[hex(r) for r in reasons]} was expected")


def _upload_expect(c: Client, tally: Tally, image: bytes, announced_crc: int, pieces, reasons) -> None:
    """BEGIN with ``announced_crc``, send ``pieces`` of ``image``, COMMIT: refused with ``reasons``."""
    c.xfer_begin(SLOT, len(image), announced_crc)
    tally.messages += 1
    _send(c, image, pieces, tally)
    _expect_nack(tally, reasons, c.xfer_commit, SLOT)


# Scenarios: fn(client, rng, tally, good image) -> "kept" or "replaced".


def corrupted(c, rng, tally, image):
    bad = bytearray(image)
    bad[rng.randrange(len(bad))] ^= 1 << rng.randrange(8)
    _upload_expect(c, tally, bytes(bad), crc32(image), _chunks(len(image)), (NackReason.CRC_MISMATCH,))
    return "kept"


def corrupted_and_resigned(c, rng, tally, image):
    bad = bytearray(image)
    bad[rng.randrange(HEADER_SIZE, len(bad))] ^= 1 << rng.randrange(8)
    _upload_expect(c, tally, bytes(bad), crc32(bytes(bad)), _chunks(len(bad)), tuple(Reason))
    return "kept"


def truncated(c, rng, tally, image):
    short = image[: rng.randrange(1, len(image))]
    _upload_expect(c, tally, short, crc32(short), _chunks(len(short)), tuple(Reason))
    return "kept"


def wrong_version_image(c, rng, tally, image):
    v = wrong_version(image, rng.choice([0, 2, 3, 0xFFFF]))
    _upload_expect(c, tally, v, crc32(v), _chunks(len(v)), (Reason.BAD_VERSION,))
    return "kept"


def commit_incomplete(c, rng, tally, image):
    pieces = _chunks(len(image))
    del pieces[rng.randrange(len(pieces))]
    rng.shuffle(pieces)
    _upload_expect(c, tally, image, crc32(image), pieces, (NackReason.INCOMPLETE,))
    c.xfer_abort(SLOT)
    return "kept"


def overlapping_conflicting(c, rng, tally, image):
    """Part of the image sent, then chunks carrying other bytes over received ones (a stale
    retransmission, another client's image): each NACKed CONFLICT, the received bytes kept, so
    the rest of the image commits."""
    pieces = _chunks(len(image))
    half = rng.randrange(1, len(pieces))
    c.xfer_begin(SLOT, len(image), crc32(image))
    _send(c, image, pieces[:half], tally)
    received = pieces[half - 1][0] + pieces[half - 1][1]
    for _ in range(3):  # over received bytes only, or reaching past them into missing ones
        off = rng.randrange(received)
        n = min(rng.randrange(1, 3000), len(image) - off)
        _expect_nack(
            tally, (NackReason.CONFLICT,), c.xfer_data, SLOT, off, bytes(b ^ 0xFF for b in image[off : off + n])
        )
    _send(c, image, pieces[half:], tally)
    c.xfer_commit(SLOT)
    tally.messages += 2
    return "replaced"


def interrupted(c, rng, tally, image):
    """Part of an image, then ABORT or a new BEGIN for another image that is never finished."""
    c.xfer_begin(SLOT, len(image), crc32(image))
    _send(c, image, _chunks(len(image))[: rng.randrange(1, 4)], tally)
    if rng.random() < 0.5:
        c.xfer_abort(SLOT)
        _expect_nack(tally, (NackReason.NO_TRANSFER,), c.xfer_commit, SLOT)
    else:
        c.xfer_begin(SLOT, len(image) + 1, 0)
        _expect_nack(tally, (NackReason.INCOMPLETE,), c.xfer_commit, SLOT)
    tally.messages += 2
    return "kept"


def out_of_range(c, rng, tally, image):
    """Data beyond the announced length, to an unknown slot, without BEGIN; BEGIN too large."""
    c.xfer_begin(SLOT, len(image), crc32(image))
    _expect_nack(tally, (NackReason.OUT_OF_RANGE,), c.xfer_data, SLOT, len(image) - 1, b"xy")
    _expect_nack(tally, (NackReason.BAD_SLOT,), c.xfer_begin, 9, 10, 0)
    _expect_nack(tally, (NackReason.TOO_LARGE,), c.xfer_begin, SLOT, (64 << 20) + 1, 0)
    c.xfer_abort(SLOT)
    _expect_nack(tally, (NackReason.NO_TRANSFER,), c.xfer_data, SLOT, 0, b"x")
    tally.messages += 2
    return "kept"


def raw_damage(c, rng, tally, image):
    """Transfer commands with data fields of the wrong size (refused as BAD_LENGTH)."""
    for code, data in (
        (Code.XFER_BEGIN, XferBegin(SLOT, 5, 0).pack()[:-1]),
        (Code.XFER_DATA, XferData(SLOT, 0, b"").pack()),
        (Code.XFER_COMMIT, b""),
        (Code.XFER_ABORT, b"\0\0"),
        (Code.SLOT_INFO, b""),
    ):
        _expect_nack(tally, (NackReason.BAD_LENGTH,), c.transact, code, data)
    return "kept"


def _commit_pieces(c, rng, tally, image, pieces) -> str:
    rng.shuffle(pieces)
    c.xfer_begin(SLOT, len(image), crc32(image))
    _send(c, image, pieces, tally)
    c.xfer_commit(SLOT)
    tally.messages += 2
    return "replaced"


def out_of_order(c, rng, tally, image):
    """A valid image in shuffled chunks: committed."""
    pieces = _chunks(len(image), rng.choice([512, 1000, 4096]))
    return _commit_pieces(c, rng, tally, image, pieces)


def overlapping(c, rng, tally, image):
    """A valid image in random overlapping windows covering it: committed."""
    pieces, pos = [], 0
    while pos < len(image):
        start = max(0, pos - rng.randrange(0, 600))
        n = rng.randrange(100, 3000)
        pieces.append((start, min(n, len(image) - start)))
        pos = max(pos, start + n)
    return _commit_pieces(c, rng, tally, image, pieces)


SCENARIOS = {
    f.__name__: f
    for f in (
        corrupted,
        corrupted_and_resigned,
        truncated,
        wrong_version_image,
        commit_incomplete,
        overlapping_conflicting,
        interrupted,
        out_of_range,
        raw_damage,
        out_of_order,
        overlapping,
    )
}
REPLACING = ("out_of_order", "overlapping", "overlapping_conflicting")
FAULTLESS = ("out_of_order", "overlapping")  #: the replacing scenarios that send no fault


def check_state(c: Client, state: Path, expected: bytes, tally: Tally, when: str) -> None:
    """SLOT_INFO and the state file must both hold ``expected``."""
    try:
        info = c.slot_info(SLOT)
        tally.messages += 1
        if not info.active or (info.length, info.crc32) != (len(expected), crc32(expected)):
            tally.fail("state_corruptions", f"{when}: SLOT_INFO {info.active} {info.length} 0x{info.crc32:08X}")
    except LinkError as exc:
        tally.fail("unanswered_pings", f"{when}: SLOT_INFO {exc}")
    try:
        on_disk = unpack_image((state / f"slot{SLOT}" / "active.img").read_bytes())
    except (OSError, ValueError) as exc:
        tally.fail("state_corruptions", f"{when}: active.img {exc}")
        return
    if on_disk != expected:
        tally.fail("state_corruptions", f"{when}: active.img holds another image")


def run(seed: int, scenarios: int, restarts: int = 1, images: int = 3) -> Tally:
    """``scenarios`` transfer faults (each kind once, then at random) on a device holding a
    catalog; ``restarts`` SIGKILLs mid-transfer spread over the run, each followed by a restart."""
    rng = random.Random(seed)
    goods = [catalog_image(seed * 10 + k) for k in range(images)]
    tally = Tally()
    names = list(SCENARIOS)
    kill_at = set(rng.sample(range(scenarios), min(restarts, scenarios)))
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp)
        device = DeviceProcess("--pty", "--state", str(state))
        try:
            with Client(device.path, timeout=5.0, retries=0) as c:
                c.upload(SLOT, goods[0], progress=False)
                tally.messages += 1
            active = goods[0]
            for k in range(scenarios):
                name = names[k] if k < len(names) else rng.choice(names)
                image = rng.choice([g for g in goods if g != active] if name in REPLACING else goods)
                with Client(device.path, timeout=5.0, retries=0) as c:
                    tally.faults += name not in FAULTLESS
                    try:
                        outcome = SCENARIOS[name](c, rng, tally, image)
                    except LinkError as exc:
                        tally.fail("bad_replies", f"{name}: {exc}")
                        outcome = "unknown"
                    if outcome == "replaced":
                        active = image
                    check_state(c, state, active, tally, name)
                    ping_check(c, tally, device)
                    if k in kill_at:  # power loss mid-transfer, then a restart
                        c.xfer_begin(SLOT, len(image), crc32(image))
                        _send(c, image, _chunks(len(image))[:2], tally)
                        tally.faults += 1
                if k in kill_at:
                    device.stop(signal.SIGKILL)
                    stderr_check(device, tally)
                    device = DeviceProcess("--pty", "--state", str(state))
                    with Client(device.path, timeout=5.0, retries=0) as c:
                        check_state(c, state, active, tally, f"restart after {name}")
                        ping_check(c, tally, device)
        finally:
            if device.stop() != 0:
                tally.fail("crashes", "device exit code at stop")
            stderr_check(device, tally)
    return tally
