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
import os
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path

from protocol.crc import crc32


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
    data = blob[_IMAGE_HEADER.size:]
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
        for sub in sorted(self.root.glob("slot*")):
            try:
                slot = int(sub.name[4:])
            except ValueError:
                continue
            if slot in self.volatile:
                continue
            try:
                self._load_slot(slot, sub)
            except (OSError, ValueError, KeyError, TypeError) as exc:
                print(f"state: ignoring unreadable {sub}: {exc}", file=sys.stderr)

    def _load_slot(self, slot: int, sub: Path) -> None:
        meta_path, bin_path = sub / "active.json", sub / "active.bin"
        if (sub / "active.img").exists():
            try:
                self._active[slot] = unpack_image((sub / "active.img").read_bytes())
            except ValueError as exc:
                print(f"state: slot {slot}: {exc}; ignored", file=sys.stderr)
        elif meta_path.exists() and bin_path.exists():  # a state directory from before active.img
            meta = json.loads(meta_path.read_text())
            data = bin_path.read_bytes()
            if len(data) == meta["length"] and crc32(data) == meta["crc32"]:
                self._active[slot] = data
            else:
                print(f"state: slot {slot} image fails its length/CRC-32 check; ignored", file=sys.stderr)
        pmeta, pbin = sub / "partial.json", sub / "partial.bin"
        if pmeta.exists() and pbin.exists():
            meta = json.loads(pmeta.read_text())
            length = int(meta["length"])
            ranges = [[int(a), int(b)] for a, b in meta["ranges"]]
            if pbin.stat().st_size == length and all(0 <= a < b <= length for a, b in ranges):
                self._transfers[slot] = Transfer(slot, length, int(meta["crc32"]), ranges)

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
            self._buffers[slot][offset:offset + len(data)] = data
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
        if self._persistent(slot):
            d = self.root / f"slot{slot}"
            for name in ("partial.json", "partial.bin"):
                (d / name).unlink(missing_ok=True)

    def _save_meta(self, tr: Transfer) -> None:
        meta = {"length": tr.length, "crc32": tr.crc32, "ranges": tr.ranges}
        tmp = self._dir(tr.slot) / "partial.json.tmp"
        tmp.write_text(json.dumps(meta))
        os.replace(tmp, self._dir(tr.slot) / "partial.json")
