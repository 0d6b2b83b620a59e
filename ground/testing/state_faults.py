"""Damaged state directories: the device must start, say what it ignored in one line per
damage (``state:`` or ``device:``), answer PING, and hold its catalog intact or no catalog,
never another one.

A base state (a catalog in slot 0, a transfer in progress in slot 0, parameters in slot 2) is
written, one or more :data:`DAMAGE` functions are applied, and the device is started on it, as
a process (``st16-device --state``) or in this process (fast, for tests).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import random
import shutil
import struct
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_model.device.slots import SlotStore, pack_image
from ground.link.client import Client, LinkError
from ground.testing.checks import ping_check
from ground.testing.device_proc import DeviceProcess, tracebacks
from ground.testing.tally import Tally
from ground.testing.upload_faults import catalog_image
from protocol import nsp
from protocol.commands import Code, XferState
from protocol.crc import crc32

if TYPE_CHECKING:
    from firmware_model.device.device import Device

PREFIXES = ("state: ", "device: ")


def base_state(root: Path, catalog: bytes) -> None:
    """A catalog committed in slot 0, the first half of another image pending in slot 0, and a
    parameter set in slot 2."""
    store = SlotStore(root)
    store.set_active(0, catalog)
    store.begin(0, len(catalog) + 100, crc32(catalog))
    store.write(0, 0, catalog[: len(catalog) // 2])
    store.set_active(2, json.dumps({"sigma_rg": 0.05}).encode())


def _flip(path: Path, rng: random.Random) -> None:
    data = bytearray(path.read_bytes())
    for _ in range(rng.randrange(1, 9)):
        data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
    path.write_bytes(bytes(data))


BAD_PARTIAL_JSON = [
    "[]",
    "{}",
    "null",
    '"x"',
    '{"length": "12", "crc32": 0, "ranges": []}',
    '{"length": 1e400, "crc32": 0, "ranges": []}',
    '{"length": -5, "crc32": 0, "ranges": []}',
    '{"length": 1099511627776, "crc32": 0, "ranges": []}',
    '{"length": 10, "crc32": -1, "ranges": []}',
    '{"length": 10, "crc32": 0, "ranges": [[0, 11]]}',
    '{"length": 10, "crc32": 0, "ranges": 5}',
    '{"length": 10, "crc32": 0, "ranges": [[3]]}',
    '{"length": 10, "crc32": 0, "ranges": {"ab": 1}}',
    "[" * 100_000 + "]" * 100_000,
]


def _img(root):
    return root / "slot0" / "active.img"


def _forge_log(root: Path, rng: random.Random) -> None:
    """Records appended to ``partial.log`` claiming the never-written second half of the transfer."""
    meta = json.loads((root / "slot0" / "partial.json").read_text())
    end = meta["length"]
    start = max(r[1] for r in meta["ranges"])
    cuts = sorted(rng.sample(range(start + 1, end), 2))
    records = [(start, cuts[0]), (cuts[0], cuts[1]), (cuts[1], end)][: rng.randrange(1, 4)]
    with open(root / "slot0" / "partial.log", "ab") as fh:
        for a, b in records:
            fh.write(struct.pack("<III", a, b, rng.getrandbits(32)))


def _forge_json(root: Path, rng: random.Random) -> None:
    """``partial.json``'s checkpoint claiming the never-written rest of the transfer."""
    path = root / "slot0" / "partial.json"
    meta = json.loads(path.read_text())
    start = max(r[1] for r in meta["ranges"])
    meta["ranges"].append([start, meta["length"], rng.getrandbits(32)])
    path.write_text(json.dumps(meta))


def _forge_old_json(root: Path, rng: random.Random) -> None:
    """The ``partial.json`` of an older state directory (ranges without CRC-32s) claiming the whole
    transfer, over a ``partial.bin`` whose second half was never written (a hole, as the device
    leaves it; a copy of the directory may have filled it in)."""
    sub = root / "slot0"
    meta = json.loads((sub / "partial.json").read_text())
    written = max(r[1] for r in meta["ranges"])
    head = (sub / "partial.bin").read_bytes()[:written]
    with open(sub / "partial.bin", "wb") as fh:
        fh.truncate(meta["length"])
        fh.write(head)
    (sub / "partial.log").unlink()
    (sub / "partial.json").write_text(
        json.dumps({"length": meta["length"], "crc32": meta["crc32"], "ranges": [[0, meta["length"]]]})
    )


#: name -> (fn(root, rng), touches slot 0's committed image, touches slot 0's transfer)
DAMAGE = {
    "img_truncated": (
        lambda r, g: _img(r).write_bytes(_img(r).read_bytes()[: g.randrange(_img(r).stat().st_size)]),
        True,
        False,
    ),
    "img_bit_flips": (lambda r, g: _flip(_img(r), g), True, False),
    "img_garbage": (lambda r, g: _img(r).write_bytes(g.randbytes(g.randrange(1, 5000))), True, False),
    "img_empty": (lambda r, g: _img(r).write_bytes(b""), True, False),
    "img_huge_length": (
        lambda r, g: _img(r).write_bytes(_img(r).read_bytes()[:8] + b"\xff" * 8 + _img(r).read_bytes()[16:]),
        True,
        False,
    ),
    "img_deleted": (lambda r, g: _img(r).unlink(), True, False),
    "img_is_a_directory": (lambda r, g: (_img(r).unlink(), _img(r).mkdir()), True, False),
    "img_symlink_loop": (lambda r, g: (_img(r).unlink(), _img(r).symlink_to(_img(r).name)), True, False),
    "img_not_a_catalog": (lambda r, g: _img(r).write_bytes(pack_image(g.randbytes(3000))), True, False),
    "partial_json_garbage": (lambda r, g: (r / "slot0" / "partial.json").write_bytes(g.randbytes(200)), False, True),
    "partial_json_wrong": (
        lambda r, g: (r / "slot0" / "partial.json").write_text(g.choice(BAD_PARTIAL_JSON)),
        False,
        True,
    ),
    "partial_log_forged": (_forge_log, False, True),
    "partial_json_forged": (_forge_json, False, True),
    "partial_json_old_forged": (_forge_old_json, False, True),
    "partial_log_missing": (lambda r, g: (r / "slot0" / "partial.log").unlink(), False, True),
    "partial_log_cut": (
        lambda r, g: (r / "slot0" / "partial.log").write_bytes((r / "slot0" / "partial.log").read_bytes() + b"\1" * 5),
        False,
        True,
    ),
    "partial_bin_truncated": (lambda r, g: (r / "slot0" / "partial.bin").write_bytes(b"\0" * 10), False, True),
    "partial_bin_missing": (lambda r, g: (r / "slot0" / "partial.bin").unlink(), False, True),
    "partial_json_missing": (lambda r, g: (r / "slot0" / "partial.json").unlink(), False, True),
    "unfinished_writes": (
        lambda r, g: [(r / "slot0" / n).write_bytes(g.randbytes(100)) for n in ("active.img.tmp", "partial.json.tmp")],
        False,
        False,
    ),
    "old_layout_damaged": (
        lambda r, g: ((r / "slot2" / "active.img").unlink(), (r / "slot2" / "active.json").write_text("{not json")),
        False,
        False,
    ),
    "params_not_json": (
        lambda r, g: (r / "slot2" / "active.img").write_bytes(pack_image(b"\xff not json")),
        False,
        False,
    ),
    "slot_dir_deleted": (lambda r, g: shutil.rmtree(r / "slot0"), True, True),
    "manifest_garbage": (
        lambda r, g: (r / "manifest.json").write_bytes(g.randbytes(g.randrange(0, 300))),
        False,
        False,
    ),
    "odd_entries": (
        lambda r, g: (
            (r / "slotX").mkdir(),
            (r / "slot4").write_text("x"),
            (r / "slot999").mkdir(),
            (r / "slot7").mkdir(),
            (r / "slot7" / "active.img").write_bytes(pack_image(b"7")),
        ),
        False,
        False,
    ),
}


#: damage applied after the others of a combination (it removes the files they damage)
LAST = ("slot_dir_deleted",)


@contextlib.contextmanager
def in_process_device(root: Path) -> Iterator[tuple[Device, str]]:
    """The device ``st16-device --state root`` would build, and what it wrote to stderr while
    built; its index-building process is ended on leaving (a campaign of hundreds of devices
    leaked one process each)."""
    from firmware_model.device.cli import build_device, build_parser

    err = io.StringIO()
    handler = logging.StreamHandler(err)  # what st16-device's logging set-up writes to stderr
    handler.setFormatter(logging.Formatter("%(message)s"))
    handler.setLevel(logging.WARNING)
    logging.getLogger().addHandler(handler)
    try:
        with contextlib.redirect_stderr(err):
            device = build_device(build_parser().parse_args(["--pty", "--state", str(root)]))
    finally:
        logging.getLogger().removeHandler(handler)
    try:
        yield device, err.getvalue()
    finally:
        close = getattr(device.solver, "close", None)
        if close is not None:
            close()


def _check_messages(text: str, damaged: bool, tally: Tally, names: list[str]) -> None:
    lines = [line for line in text.splitlines() if line.strip()]
    if tracebacks(text):
        tally.fail("tracebacks", f"{names}: {text[:400]!r}")
    elif any(not line.startswith(PREFIXES) for line in lines):
        tally.fail("tracebacks", f"{names}: a start-up line that is not a one-line message: {text[:400]!r}")
    if damaged and not lines:
        tally.fail("state_corruptions", f"{names}: damage ignored without a word")


def _check_slots(
    info_active: bool,
    info_crc: int,
    xfer_state: int,
    catalog: bytes,
    names: list[str],
    touches_img: bool,
    touches_partial: bool,
    tally: Tally,
) -> None:
    if info_active and info_crc != crc32(catalog):
        tally.fail("state_corruptions", f"{names}: slot 0 holds another image (0x{info_crc:08X})")
    if not touches_img and not info_active:
        tally.fail("state_corruptions", f"{names}: slot 0 lost an intact catalog")
    if not touches_partial and xfer_state != XferState.RECEIVING:
        tally.fail("state_corruptions", f"{names}: slot 0 lost an intact transfer")


def trial(root: Path, rng: random.Random, catalog: bytes, names: list[str], tally: Tally, process: bool) -> None:
    """Damage ``root`` (a base state) with ``names``, start a device on it and check it."""
    for name in sorted(names, key=lambda n: n in LAST):
        DAMAGE[name][0](root, rng)
    tally.faults += len(names)
    touches_img = any(DAMAGE[n][1] for n in names)
    touches_partial = any(DAMAGE[n][2] for n in names)
    if process:
        _process_trial(root, catalog, names, touches_img, touches_partial, tally)
        return
    try:
        with in_process_device(root) as (device, text):
            _check_in_process(device, text, catalog, names, touches_img, touches_partial, tally)
    except Exception as exc:  # noqa: BLE001 - this is what the trial looks for
        tally.fail("crashes", f"{names}: {type(exc).__name__}: {exc}")


def _check_in_process(device: Device, text: str, catalog, names, touches_img, touches_partial, tally: Tally) -> None:
    _check_messages(text, True, tally, names)
    from protocol.commands import SlotImage, SlotRequest, XferStatus

    def ask(code: int, data: bytes = b"") -> nsp.Message | None:
        tally.messages += 1
        replies = device.handle(nsp.command(device.address, nsp.HOST_ADDRESS, code, data))
        return replies[0] if replies and replies[0].ack else None

    if ask(Code.PING) is None:
        tally.fail("unanswered_pings", f"{names}: PING not answered")
        return
    info_reply = ask(Code.SLOT_INFO, SlotRequest(0).pack())
    status_reply = ask(Code.XFER_STATUS, SlotRequest(0).pack()) if info_reply is not None else None
    if info_reply is None or status_reply is None:  # as the process trial counts a LinkError here
        tally.fail("unanswered_pings", f"{names}: SLOT_INFO or XFER_STATUS not answered")
        return
    info = SlotImage.unpack(info_reply.data)
    status = XferStatus.unpack(status_reply.data)
    _check_slots(info.active, info.crc32, status.state, catalog, names, touches_img, touches_partial, tally)


def _process_trial(root, catalog, names, touches_img, touches_partial, tally) -> None:
    try:
        device = DeviceProcess("--pty", "--state", str(root))
    except RuntimeError as exc:
        tally.fail("crashes", f"{names}: {exc}")
        return
    try:
        with Client(device.path, timeout=2.0, retries=0) as c:
            if ping_check(c, tally, device):
                try:
                    info, status = c.slot_info(0), c.xfer_status(0)
                    tally.messages += 2
                    _check_slots(
                        info.active, info.crc32, status.state, catalog, names, touches_img, touches_partial, tally
                    )
                except LinkError as exc:
                    tally.fail("unanswered_pings", f"{names}: {exc}")
    finally:
        if device.stop() != 0:
            tally.fail("crashes", f"{names}: exit code at stop")
        _check_messages(device.stderr(), True, tally, names)


def _target(name: str) -> str:
    return name.split("_")[0] if name.startswith(("img_", "partial_")) else name


def _combination(rng: random.Random, kinds: list[str], most: int) -> list[str]:
    """Up to ``most`` kinds of damage, at most one per file they damage."""
    chosen: dict[str, str] = {}
    for name in rng.sample(kinds, len(kinds)):
        chosen.setdefault(_target(name), name)
    return rng.sample(sorted(chosen.values()), rng.randrange(1, most + 1))


def run(seed: int, trials: int, process: bool = True, max_damage: int = 3) -> Tally:
    """Each kind of damage alone once, then ``trials - len(DAMAGE)`` random combinations of up
    to ``max_damage`` kinds; devices started as processes or in this process."""
    rng = random.Random(seed)
    catalog = catalog_image(seed)
    tally = Tally()
    kinds = sorted(DAMAGE)
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base"
        base_state(base, catalog)
        for k in range(trials):
            names = [kinds[k]] if k < len(kinds) else _combination(rng, kinds, max_damage)
            root = Path(tmp) / f"t{k}"
            shutil.copytree(base, root, symlinks=True)
            trial(root, rng, catalog, names, tally, process)
            shutil.rmtree(root, ignore_errors=True)
    return tally
