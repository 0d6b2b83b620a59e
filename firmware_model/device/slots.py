"""Persistent slot storage (the emulated flash) and resumable partial transfers.

With a ``root`` directory, every slot lives in ``root/slot<N>/``: ``active.img`` for the committed
image (one file: a 16-byte header of magic, length and CRC-32, then the data, so that a commit is a
single rename and a power loss leaves the old image or the new one, never a mismatched pair;
the ``active.bin`` + ``active.json`` pair of older state directories is still read), and
``partial.bin`` + ``partial.json`` (length, CRC-32, received byte ranges) for a transfer in
progress. Slots named ``volatile`` (the frame slot: image
buffers are RAM on the real device) are kept in memory even with a ``root``. Metadata files are replaced atomically
(write to a temporary file, fsync, rename, fsync the directory); ``partial.bin`` is written in place before its range
list is updated, so after a crash or restart the range list never claims bytes that were not
written. Committed images are fsynced. Without ``root`` everything is kept in memory.
"""

from __future__ import annotations

import json
import logging
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

from protocol.commands import MAX_SLOT_BYTES
from protocol.crc import crc32

log = logging.getLogger(__name__)


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(fd)  # the rename itself is durable
    finally:
        os.close(fd)


#: Header of a committed slot image file: magic, then length (u64) and CRC-32 (u32), little-endian.
IMAGE_MAGIC = b"ST16IMG1"
_IMAGE_HEADER = struct.Struct("<8sQI")


def pack_image(data: bytes) -> bytes:
    """A committed image with its header (magic, length, CRC-32)."""
    return _IMAGE_HEADER.pack(IMAGE_MAGIC, len(data), crc32(data)) + data


def unpack_image(blob: bytes) -> bytes:
    """The data of a committed image file; ValueError if its header, length or CRC-32 is wrong."""
    if len(blob) < _IMAGE_HEADER.size:
        raise ValueError(f"image file of {len(blob)} bytes is shorter than its header")
    magic, length, crc = _IMAGE_HEADER.unpack_from(blob)
    data = blob[_IMAGE_HEADER.size :]
    if magic != IMAGE_MAGIC:
        raise ValueError(f"image file has magic {magic!r}, expected {IMAGE_MAGIC!r}")
    if len(data) != length or crc32(data) != crc:
        raise ValueError(f"image file fails its length/CRC-32 check ({len(data)} of {length} bytes)")
    return data


def _merge(ranges: list[list[int]], start: int, end: int) -> list[list[int]]:
    """Insert the half-open range [start, end) into sorted disjoint ``ranges``, merging neighbours."""
    out: list[list[int]] = []
    placed = False
    for a, b in ranges:
        if b < start:
            out.append([a, b])
        elif end < a:
            if not placed:
                out.append([start, end])
                placed = True
            out.append([a, b])
        else:
            start, end = min(a, start), max(b, end)
    if not placed:
        out.append([start, end])
    return out


def _warn(text: str) -> None:
    log.warning("state: %s", " ".join(text.split()))  # one line, whatever the text held


def _remove(path: Path) -> None:
    try:
        path.unlink()
    except OSError as exc:
        _warn(f"could not remove {path}: {exc}")


def _slot_number(name: str) -> int | None:
    digits = name[4:]
    if not digits.isdigit() or len(digits) > 3 or int(digits) > 255:
        return None
    return int(digits)


def _transfer_from_meta(slot: int, meta) -> Transfer:
    """A Transfer from ``partial.json``'s content; ValueError for anything but
    ``{"length": 1..MAX_SLOT_BYTES, "crc32": u32, "ranges": [[a, b], ...] within the length}``."""
    if not isinstance(meta, dict):
        raise ValueError("partial.json is not a JSON object")
    length, crc, ranges = meta.get("length"), meta.get("crc32"), meta.get("ranges")
    if type(length) is not int or not 1 <= length <= MAX_SLOT_BYTES:
        raise ValueError(f"transfer length {length!r} outside 1..{MAX_SLOT_BYTES}")
    if type(crc) is not int or not 0 <= crc <= 0xFFFFFFFF:
        raise ValueError(f"transfer CRC-32 {crc!r} is not a u32")
    if not isinstance(ranges, list) or len(ranges) > length:
        raise ValueError("received ranges are not a list of [start, end] pairs")
    merged: list[list[int]] = []
    for pair in ranges:
        if (
            not isinstance(pair, list)
            or len(pair) != 2
            or any(type(v) is not int for v in pair)
            or not 0 <= pair[0] < pair[1] <= length
        ):
            raise ValueError(f"received range {pair!r} is not [start, end] within 0..{length}")
        merged = _merge(merged, pair[0], pair[1])
    return Transfer(slot, length, crc, merged)


@dataclass
class Transfer:
    """A transfer in progress: total ``length``, expected ``crc32``, received ``ranges`` [a, b)."""

    slot: int
    length: int
    crc32: int
    ranges: list[list[int]] = field(default_factory=list)

    @property
    def contiguous(self) -> int:
        return self.ranges[0][1] if self.ranges and self.ranges[0][0] == 0 else 0

    @property
    def received(self) -> int:
        return sum(b - a for a, b in self.ranges)

    @property
    def complete(self) -> bool:
        return self.ranges == [[0, self.length]]

    def missing(self) -> list[tuple[int, int]]:
        """Missing ranges as (offset, length)."""
        out, pos = [], 0
        for a, b in self.ranges:
            if a > pos:
                out.append((pos, a - pos))
            pos = b
        if pos < self.length:
            out.append((pos, self.length - pos))
        return out


class SlotStore:
    """Committed slot images and partial transfers, on disk under ``root`` or in memory."""

    def __init__(self, root: str | os.PathLike | None = None, volatile=()):
        self.root = Path(root) if root is not None else None
        self.volatile = frozenset(volatile)
        self._active: dict[int, bytes] = {}
        self._transfers: dict[int, Transfer] = {}
        self._buffers: dict[int, bytearray] = {}
        if self.root is not None:
            self.root.mkdir(parents=True, exist_ok=True)
            self._load()

    def _persistent(self, slot: int) -> bool:
        return self.root is not None and slot not in self.volatile

    def _dir(self, slot: int) -> Path:
        assert self.root is not None
        path = self.root / f"slot{slot}"
        path.mkdir(exist_ok=True)
        return path

    def _load(self) -> None:
        """Read every slot directory; damage is reported as one ``state:`` line on stderr and the
        damaged part ignored (never an exception: a device with bad state still starts)."""
        assert self.root is not None
        for sub in sorted(self.root.iterdir()):
            if not sub.name.startswith("slot"):
                continue
            slot = _slot_number(sub.name)
            if slot is None or not sub.is_dir():
                _warn(f"ignoring {sub}: not a slot directory (slot<N>/, N = 0..255)")
                continue
            if slot in self.volatile:
                continue
            for name in ("active.img.tmp", "partial.json.tmp"):  # a write cut by a crash: never committed
                if (sub / name).exists():
                    _warn(f"slot {slot}: removing {name}, a write that did not finish")
                    _remove(sub / name)
            for part in (self._load_active, self._load_partial):
                try:
                    part(slot, sub)
                except Exception as exc:  # noqa: BLE001 - any damage: report it, keep starting
                    _warn(f"slot {slot}: {part.__doc__} unreadable ({type(exc).__name__}: {exc}); ignored")

    def _load_active(self, slot: int, sub: Path) -> None:
        """committed image"""
        meta_path, bin_path, img = sub / "active.json", sub / "active.bin", sub / "active.img"
        if img.exists() or img.is_symlink():
            try:
                self._active[slot] = unpack_image(img.read_bytes())
            except ValueError as exc:
                _warn(f"slot {slot}: active.img: {exc}; ignored, the slot has no image")
        elif meta_path.exists() or bin_path.exists():  # a state directory from before active.img
            if not (meta_path.exists() and bin_path.exists()):
                _warn(
                    f"slot {slot}: {meta_path.name if meta_path.exists() else bin_path.name} without its pair; ignored"
                )
                return
            meta = json.loads(meta_path.read_text())
            data = bin_path.read_bytes()
            if len(data) == meta["length"] and crc32(data) == meta["crc32"]:
                self._active[slot] = data
            else:
                _warn(f"slot {slot}: active.bin fails its length/CRC-32 check; ignored")

    def _load_partial(self, slot: int, sub: Path) -> None:
        """partial transfer"""
        pmeta, pbin = sub / "partial.json", sub / "partial.bin"
        if not (pmeta.exists() or pbin.exists()):
            return
        if not (pmeta.exists() and pbin.exists()):
            _warn(f"slot {slot}: {pmeta.name if pmeta.exists() else pbin.name} without its pair; transfer dropped")
            return
        tr = _transfer_from_meta(slot, json.loads(pmeta.read_text()))
        size = pbin.stat().st_size
        if size != tr.length:
            _warn(f"slot {slot}: partial.bin holds {size} bytes, its transfer {tr.length}; transfer dropped")
            return
        self._transfers[slot] = tr

    # ------------------------------------------------------------------ committed images

    def active(self, slot: int) -> bytes | None:
        return self._active.get(slot)

    def active_slots(self) -> list[int]:
        return sorted(self._active)

    def set_active(self, slot: int, data: bytes) -> None:
        """Persist ``data`` as the committed image of ``slot`` (atomic replace)."""
        data = bytes(data)
        if self._persistent(slot):
            d = self._dir(slot)
            _atomic_write(d / "active.img", pack_image(data))  # the commit: one rename
            for old in ("active.json", "active.bin"):  # an older directory's pair, superseded
                (d / old).unlink(missing_ok=True)
        self._active[slot] = data

    # ------------------------------------------------------------------ transfers

    def transfer(self, slot: int) -> Transfer | None:
        return self._transfers.get(slot)

    def begin(self, slot: int, length: int, crc: int) -> Transfer:
        """Start a transfer, or keep the pending one if it has the same length and CRC-32."""
        current = self._transfers.get(slot)
        if current is not None and current.length == length and current.crc32 == crc:
            return current
        self.drop_transfer(slot)
        tr = Transfer(slot, length, crc)
        self._transfers[slot] = tr
        if not self._persistent(slot):
            self._buffers[slot] = bytearray(length)
        else:
            d = self._dir(slot)
            with open(d / "partial.bin", "wb") as fh:
                fh.truncate(length)
            self._save_meta(tr)
        return tr

    def write(self, slot: int, offset: int, data: bytes) -> Transfer:
        """Store ``data`` at ``offset`` of the pending transfer (caller checked the bounds)."""
        tr = self._transfers[slot]
        if not self._persistent(slot):
            self._buffers[slot][offset : offset + len(data)] = data
        else:
            with open(self._dir(slot) / "partial.bin", "r+b") as fh:
                fh.seek(offset)
                fh.write(data)
        tr.ranges = _merge(tr.ranges, offset, offset + len(data))
        if self._persistent(slot):
            self._save_meta(tr)
        return tr

    def transfer_bytes(self, slot: int) -> bytes:
        if not self._persistent(slot):
            return bytes(self._buffers[slot])
        return (self._dir(slot) / "partial.bin").read_bytes()

    def drop_transfer(self, slot: int) -> None:
        self._transfers.pop(slot, None)
        self._buffers.pop(slot, None)
        if self.root is not None and slot not in self.volatile:  # _persistent(slot), narrowed
            d = self.root / f"slot{slot}"
            for name in ("partial.json", "partial.bin"):
                if (d / name).exists():
                    _remove(d / name)

    def _save_meta(self, tr: Transfer) -> None:
        meta = {"length": tr.length, "crc32": tr.crc32, "ranges": tr.ranges}
        tmp = self._dir(tr.slot) / "partial.json.tmp"
        tmp.write_text(json.dumps(meta))
        os.replace(tmp, self._dir(tr.slot) / "partial.json")
