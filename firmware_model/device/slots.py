"""Persistent slot storage (the emulated flash) and resumable partial transfers.

With a ``root`` directory, every slot lives in ``root/slot<N>/``: ``active.img`` for the committed
image (one file: a 16-byte header of magic, length and CRC-32, then the data, so that a commit is a
single rename and a power loss leaves the old image or the new one, never a mismatched pair;
the ``active.bin`` + ``active.json`` pair of older state directories is still read), and for a
transfer in progress ``partial.bin`` (the image's bytes, written in place), ``partial.json`` (a
checkpoint: length, CRC-32, and the received byte ranges with the CRC-32 of each) and
``partial.log`` (the ranges received since the checkpoint: one fixed-size record
``[start, end)`` + CRC-32 of those bytes appended per XFER DATA, *after* the bytes are written to
``partial.bin``). The log is replayed at start and folded into a new checkpoint when it has grown
as large as the checkpoint (so a DATA costs one write of its bytes and one of 12 bytes, and the
checkpoints of one transfer cost O(its length) in all). At start every range is checked against
the CRC-32 it carries: a range whose bytes were never written (a crash, a forged or damaged list)
is dropped with a ``state:`` line and its bytes are asked for again. The ``partial.json`` of older
state directories (ranges without CRC-32s) is read, its ranges checked only for never-written
holes of ``partial.bin``, and rewritten in the new form.

``root/manifest.json`` lists the slots holding a committed image (length, CRC-32), replaced
atomically after each commit; a slot it lists whose image has gone (``active.img`` or the slot's
directory deleted) is a ``state:`` line at start. Received bytes are write-once: a DATA that
overlaps received bytes with other bytes raises :class:`Conflict` and changes nothing.

Slots named ``volatile`` (the frame slot: image buffers are RAM on the real device) are kept in
memory even with a ``root``. Metadata files are replaced atomically (write to a temporary file,
fsync, rename, fsync the directory). Committed images are fsynced. Without ``root`` everything is
kept in memory.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import zlib
from bisect import bisect_left, bisect_right
from dataclasses import dataclass, field
from pathlib import Path

from protocol.commands import MAX_SLOT_BYTES
from protocol.crc import CRC32_RESIDUE, crc32

log = logging.getLogger(__name__)


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` crash-safe: a temporary file, fsync, rename, fsync the folder
    (the device's persisted state: the slots and the NAND)."""
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


def pack_image(data: bytes, crc: int | None = None) -> bytes:
    """A committed image with its header (magic, length, CRC-32: ``crc`` if the caller has it)."""
    return _IMAGE_HEADER.pack(IMAGE_MAGIC, len(data), crc32(data) if crc is None else crc) + data


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


#: ``partial.log``: a header (magic, transfer length, transfer CRC-32), then one record per DATA:
#: start, end (the half-open range received) and the CRC-32 of those bytes, all u32 little-endian.
LOG_MAGIC = b"ST16LOG1"
_LOG_HEADER = struct.Struct("<8sII")
_LOG_RECORD = struct.Struct("<III")
PARTIAL_FORMAT = 2  #: ``partial.json`` with ``"format": 2``: checkpoint ranges ``[start, end, crc32]``
MANIFEST = "manifest.json"  #: at the state root: the slots holding a committed image
#: the log is folded into a new checkpoint at the latest when it holds this many records (and
#: four times the checkpoint's ranges): a flood of tiny DATAs never makes it unbounded
COMPACT_RECORDS = 65536


class Conflict(ValueError):
    """A DATA whose bytes differ from bytes already received at ``offset`` (received bytes are
    write-once); nothing was written."""

    def __init__(self, offset: int):
        super().__init__(f"byte {offset} differs from the byte already received there")
        self.offset = offset


def _first_difference(a: bytes, b: bytes) -> int:
    return next(i for i, (x, y) in enumerate(zip(a, b)) if x != y)


def _holes(path: Path, ranges: list[list[int]]) -> list[list[int]]:
    """The ranges of ``ranges`` that hold a hole of the sparse file ``path`` (bytes never written:
    ``partial.bin`` is created by truncation); none where the file system does not report holes."""
    out = []
    with open(path, "rb") as fh:
        fd = fh.fileno()
        for a, b in ranges:
            try:
                hole = os.lseek(fd, a, os.SEEK_HOLE)
            except OSError:  # ENXIO: a past the end; EINVAL: no hole support
                continue
            if hole < b:
                out.append([a, b])
    return out


def _ranges_from_meta(meta) -> tuple[int, int, list[list[int]], bool]:
    """``(length, crc32, ranges, new_form)`` from ``partial.json``'s content: ranges ``[a, b, crc]``
    (``"format": 2``) or ``[a, b]`` (older state directories); ValueError for any other shape."""
    if not isinstance(meta, dict):
        raise ValueError("partial.json is not a JSON object")
    length, crc, ranges = meta.get("length"), meta.get("crc32"), meta.get("ranges")
    new_form = meta.get("format") == PARTIAL_FORMAT
    if type(length) is not int or not 1 <= length <= MAX_SLOT_BYTES:
        raise ValueError(f"transfer length {length!r} outside 1..{MAX_SLOT_BYTES}")
    if type(crc) is not int or not 0 <= crc <= 0xFFFFFFFF:
        raise ValueError(f"transfer CRC-32 {crc!r} is not a u32")
    if not isinstance(ranges, list) or len(ranges) > length:
        raise ValueError("received ranges are not a list of [start, end] pairs")
    width = 3 if new_form else 2
    for pair in ranges:
        if (
            not isinstance(pair, list)
            or len(pair) != width
            or any(type(v) is not int for v in pair)
            or not 0 <= pair[0] < pair[1] <= length
            or (new_form and not 0 <= pair[2] <= 0xFFFFFFFF)
        ):
            raise ValueError(f"received range {pair!r} is not [start, end{', crc32' * new_form}] within 0..{length}")
    return length, crc, ranges, new_form


def _transfer_from_meta(slot: int, meta) -> Transfer:
    """A Transfer from ``partial.json``'s content (its ranges unchecked against the data)."""
    length, crc, ranges, _ = _ranges_from_meta(meta)
    tr = Transfer(slot, length, crc)
    for r in ranges:
        tr.add(r[0], r[1])
    return tr


def _start(r: list[int]) -> int:
    return r[0]


def _end(r: list[int]) -> int:
    return r[1]


@dataclass
class Transfer:
    """A transfer in progress: total ``length``, expected ``crc32``, received ``ranges`` [a, b)
    (sorted, disjoint, not touching)."""

    slot: int
    length: int
    crc32: int
    ranges: list[list[int]] = field(default_factory=list)

    def add(self, start: int, end: int) -> None:
        """Mark [start, end) received, merging the ranges it overlaps or touches (a bisection:
        O(log n) plus a list splice, O(1) for the usual append after the last range)."""
        r = self.ranges
        lo = bisect_left(r, start, key=_end)  # first range ending at or after start
        hi = bisect_right(r, end, key=_start)  # past the last range starting at or before end
        if lo < hi:
            start, end = min(start, r[lo][0]), max(end, r[hi - 1][1])
        r[lo:hi] = [[start, end]]

    def overlaps(self, start: int, end: int) -> list[tuple[int, int]]:
        """The already-received parts of [start, end), as (a, b)."""
        r, out = self.ranges, []
        for k in range(bisect_right(r, start, key=_end), len(r)):
            a, b = r[k]
            if a >= end:
                break
            out.append((max(a, start), min(b, end)))
        return out

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


@dataclass
class _Journal:
    """A persisted transfer's open files and how much its checkpoint and its log cover."""

    checkpoint_bytes: int = 0
    checkpoint_ranges: int = 0
    log_bytes: int = 0
    log_records: int = 0
    bin_fd: int | None = None
    log_fd: int | None = None

    def due(self) -> bool:
        """Fold the log into a new checkpoint? Once it covers as much as the checkpoint does
        (geometric: O(length) of checkpoint work per transfer), or holds too many records."""
        return (self.log_bytes >= self.checkpoint_bytes and self.log_records >= self.checkpoint_ranges) or (
            self.log_records >= max(COMPACT_RECORDS, 4 * self.checkpoint_ranges)
        )

    def close(self) -> None:
        for fd in (self.bin_fd, self.log_fd):
            if fd is not None:
                os.close(fd)
        self.bin_fd = self.log_fd = None


def _pwrite_all(fd: int, data: bytes, offset: int) -> None:
    view = memoryview(data)
    while view:
        n = os.pwrite(fd, view, offset)
        view, offset = view[n:], offset + n


class SlotStore:
    """Committed slot images and partial transfers, on disk under ``root`` or in memory."""

    def __init__(self, root: str | os.PathLike | None = None, volatile=()):
        self.root = Path(root) if root is not None else None
        self.volatile = frozenset(volatile)
        self._active: dict[int, bytes] = {}
        self._transfers: dict[int, Transfer] = {}
        self._buffers: dict[int, bytearray] = {}
        self._journals: dict[int, _Journal] = {}
        self._manifest: dict[int, tuple[int, int]] = {}  # slot -> (length, CRC-32) of its committed image
        if self.root is not None:
            self.root.mkdir(parents=True, exist_ok=True)
            self._load()

    def close(self) -> None:
        """Close the files of the transfers in progress (they stay on disk)."""
        for journal in self._journals.values():
            journal.close()

    def __del__(self) -> None:
        self.close()

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
            for name in ("active.img.tmp", "partial.json.tmp", "partial.log.tmp"):  # cut by a crash: never committed
                if (sub / name).exists():
                    _warn(f"slot {slot}: removing {name}, a write that did not finish")
                    _remove(sub / name)
            for part in (self._load_active, self._load_partial):
                try:
                    part(slot, sub)
                except Exception as exc:  # noqa: BLE001 - any damage: report it, keep starting
                    _warn(f"slot {slot}: {part.__doc__} unreadable ({type(exc).__name__}: {exc}); ignored")
        self._check_manifest()

    def _check_manifest(self) -> None:
        """Compare the slots found with ``manifest.json``: a listed image that has gone is a line;
        the manifest is then rewritten to what the device holds."""
        assert self.root is not None
        path = self.root / MANIFEST
        if (self.root / (MANIFEST + ".tmp")).exists():
            _warn(f"removing {MANIFEST}.tmp, a write that did not finish")
            _remove(self.root / (MANIFEST + ".tmp"))
        listed: dict[int, tuple[int, int]] = {}
        damaged = False
        if path.exists() or path.is_symlink():
            try:
                listed = _parse_manifest(json.loads(path.read_text()))
            except Exception as exc:  # noqa: BLE001 - any damage: report it, keep starting
                _warn(f"{MANIFEST} unreadable ({type(exc).__name__}: {exc}); rebuilt from the slots found")
                damaged = True
        for slot, (length, crc) in sorted(listed.items()):
            if slot in self.volatile or slot in self._active:
                continue
            sub = self.root / f"slot{slot}"
            if any((sub / n).exists() or (sub / n).is_symlink() for n in ("active.img", "active.bin", "active.json")):
                continue  # damaged, not gone: _load_active said so
            gone = f"slot{slot}/active.img" if sub.is_dir() else f"slot{slot}/"
            _warn(
                f"slot {slot}: {gone} is missing, but {MANIFEST} lists a committed image of {length} bytes, "
                f"CRC-32 0x{crc:08X}; the slot has no image"
            )
        if damaged or self._manifest != listed:
            try:
                self._write_manifest()
            except OSError as exc:
                _warn(f"could not rewrite {MANIFEST}: {exc}")

    def _write_manifest(self) -> None:
        assert self.root is not None
        slots = {str(s): {"length": n, "crc32": c} for s, (n, c) in sorted(self._manifest.items())}
        atomic_write(self.root / MANIFEST, json.dumps({"slots": slots}).encode())

    def _load_active(self, slot: int, sub: Path) -> None:
        """committed image"""
        meta_path, bin_path, img = sub / "active.json", sub / "active.bin", sub / "active.img"
        if img.exists() or img.is_symlink():
            try:
                blob = img.read_bytes()
                self._install(slot, unpack_image(blob), _IMAGE_HEADER.unpack_from(blob)[2])
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
                self._install(slot, data)
            else:
                _warn(f"slot {slot}: active.bin fails its length/CRC-32 check; ignored")

    def _install(self, slot: int, data: bytes, crc: int | None = None) -> None:
        """``data`` is the committed image of persisted ``slot`` (its CRC-32 ``crc`` if known)."""
        self._active[slot] = data
        self._manifest[slot] = (len(data), crc32(data) if crc is None else crc)

    def _load_partial(self, slot: int, sub: Path) -> None:
        """partial transfer"""
        pmeta, pbin, plog = sub / "partial.json", sub / "partial.bin", sub / "partial.log"
        if not (pmeta.exists() or pbin.exists()):
            if plog.exists():
                _warn(f"slot {slot}: partial.log without its transfer; removed")
                _remove(plog)
            return
        if not (pmeta.exists() and pbin.exists()):
            _warn(f"slot {slot}: {pmeta.name if pmeta.exists() else pbin.name} without its pair; transfer dropped")
            return
        length, crc, ranges, new_form = _ranges_from_meta(json.loads(pmeta.read_text()))
        size = pbin.stat().st_size
        if size != length:
            _warn(f"slot {slot}: partial.bin holds {size} bytes, its transfer {length}; transfer dropped")
            return
        data = pbin.read_bytes()
        tr = Transfer(slot, length, crc)
        if new_form:
            kept = self._verified(slot, "partial.json", data, ranges)
            records, clean = self._read_log(slot, plog, length, crc)
            kept += self._verified(slot, "partial.log", data, records)
            rewrite = not clean or len(kept) < len(ranges) + len(records)
        else:  # an older state directory: ranges without CRC-32s, checked for never-written holes only
            holes = _holes(pbin, ranges)
            if holes:
                _warn(
                    f"slot {slot}: partial.json: {len(holes)} of {len(ranges)} received ranges claim bytes never "
                    f"written (first [{holes[0][0]}, {holes[0][1]})); dropped, those bytes will be asked for again"
                )
            kept = [r for r in ranges if r not in holes]
            rewrite = True  # into the new form, with the CRC-32 of each range
        for r in kept:
            tr.add(r[0], r[1])
        self._transfers[slot] = tr
        self._journals[slot] = _Journal()
        if rewrite:
            try:
                self._checkpoint(tr, data, fresh_log=True)
            except OSError as exc:
                _warn(f"slot {slot}: could not rewrite partial.json: {exc}")
        else:  # the checkpoint covers what partial.json lists, the log the rest
            j = self._journals[slot]
            j.checkpoint_bytes, j.checkpoint_ranges = sum(b - a for a, b, _ in ranges), len(ranges)
            j.log_bytes, j.log_records = sum(b - a for a, b, _ in records), len(records)

    @staticmethod
    def _verified(slot: int, name: str, data: bytes, ranges: list[list[int]]) -> list[list[int]]:
        """The ranges whose bytes in ``data`` have their CRC-32; a line for those that have not."""
        view = memoryview(data)
        bad = [r for r in ranges if zlib.crc32(view[r[0] : r[1]]) != r[2]]
        if bad:
            _warn(
                f"slot {slot}: {name}: {len(bad)} of {len(ranges)} received ranges claim bytes that fail their "
                f"CRC-32 (first [{bad[0][0]}, {bad[0][1]})); dropped, those bytes will be asked for again"
            )
        return [r for r in ranges if r not in bad] if bad else list(ranges)

    @staticmethod
    def _read_log(slot: int, path: Path, length: int, crc: int) -> tuple[list[list[int]], bool]:
        """The records of ``partial.log`` ([start, end, crc32], within the length) and whether the
        log was whole; a line for a log missing or not this transfer's, a record cut short at its
        end or records outside the length (those are left out)."""
        if not path.exists():
            _warn(f"slot {slot}: partial.log missing; only the ranges of partial.json kept")
            return [], False
        blob = path.read_bytes()
        head = blob[: _LOG_HEADER.size]
        if len(head) < _LOG_HEADER.size or _LOG_HEADER.unpack(head) != (LOG_MAGIC, length, crc):
            _warn(f"slot {slot}: partial.log is not the log of this transfer; only the ranges of partial.json kept")
            return [], False
        body = blob[_LOG_HEADER.size :]
        cut = len(body) % _LOG_RECORD.size
        if cut:
            _warn(f"slot {slot}: partial.log ends in a record cut short ({cut} bytes); the record ignored")
            body = body[: len(body) - cut]
        out, bad = [], 0
        for a, b, c in _LOG_RECORD.iter_unpack(body):
            if 0 <= a < b <= length:
                out.append([a, b, c])
            else:
                bad += 1
        if bad:
            _warn(f"slot {slot}: partial.log: {bad} records outside the transfer's {length} bytes; ignored")
        return out, not (cut or bad)

    # ------------------------------------------------------------------ committed images

    def active(self, slot: int) -> bytes | None:
        return self._active.get(slot)

    def active_slots(self) -> list[int]:
        return sorted(self._active)

    def set_active(self, slot: int, data: bytes) -> None:
        """Persist ``data`` as the committed image of ``slot`` (atomic replace), then the manifest."""
        data = bytes(data)
        if not self._persistent(slot):
            self._active[slot] = data
            return
        d = self._dir(slot)
        crc = crc32(data)
        atomic_write(d / "active.img", pack_image(data, crc))  # the commit: one rename
        for old in ("active.json", "active.bin"):  # an older directory's pair, superseded
            (d / old).unlink(missing_ok=True)
        self._install(slot, data, crc)
        try:
            self._write_manifest()
        except OSError as exc:  # the image is committed; the manifest is rewritten at the next start
            _warn(f"could not write {MANIFEST}: {exc}")

    # ------------------------------------------------------------------ transfers

    def transfer(self, slot: int) -> Transfer | None:
        return self._transfers.get(slot)

    def begin(self, slot: int, length: int, crc: int) -> Transfer:
        """Start a transfer, or keep the pending one if it has the same length and CRC-32 (never
        for the CRC-32 :data:`~protocol.crc.CRC32_RESIDUE`: every image that ends with its own
        CRC-32 has it, so it cannot tell two such images apart)."""
        current = self._transfers.get(slot)
        if current is not None and current.length == length and current.crc32 == crc != CRC32_RESIDUE:
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
            self._journals[slot] = _Journal()
            self._checkpoint(tr, b"", fresh_log=True)
        return tr

    def _journal(self, slot: int) -> _Journal:
        """The slot's journal with its files open."""
        j = self._journals[slot]
        if j.bin_fd is None or j.log_fd is None:
            d = self._dir(slot)
            j.close()
            j.bin_fd = os.open(d / "partial.bin", os.O_RDWR)
            j.log_fd = os.open(d / "partial.log", os.O_WRONLY | os.O_APPEND)
        return j

    def _read(self, slot: int, offset: int, n: int) -> bytes:
        if not self._persistent(slot):
            return bytes(self._buffers[slot][offset : offset + n])
        fd = self._journal(slot).bin_fd
        assert fd is not None  # _journal opened it
        return os.pread(fd, n, offset)

    def write(self, slot: int, offset: int, data: bytes) -> Transfer:
        """Store ``data`` at ``offset`` of the pending transfer (caller checked the bounds).
        Received bytes are write-once: :class:`Conflict` if ``data`` differs from bytes already
        received (nothing is written); a DATA inside received bytes, the same, changes nothing."""
        tr = self._transfers[slot]
        end = offset + len(data)
        overlap = tr.overlaps(offset, end)
        for a, b in overlap:  # only the overlapping bytes are read back
            have, want = self._read(slot, a, b - a), data[a - offset : b - offset]
            if have != want:
                raise Conflict(a + _first_difference(have, want))
        if sum(b - a for a, b in overlap) == len(data):
            return tr  # a repeat: nothing new
        if not self._persistent(slot):
            self._buffers[slot][offset:end] = data
            tr.add(offset, end)
            return tr
        j = self._journal(slot)
        assert j.bin_fd is not None and j.log_fd is not None
        _pwrite_all(j.bin_fd, data, offset)  # the bytes first, then the record that claims them
        os.write(j.log_fd, _LOG_RECORD.pack(offset, end, crc32(data)))
        tr.add(offset, end)
        j.log_bytes += len(data)
        j.log_records += 1
        if j.due():
            self._checkpoint(tr, None, fresh_log=False)
        return tr

    def _checkpoint(self, tr: Transfer, data: bytes | None, fresh_log: bool) -> None:
        """Write ``partial.json`` with every received range and its CRC-32 (read from ``data`` or
        ``partial.bin``), then empty ``partial.log`` (a crash in between leaves records the
        checkpoint already holds: replaying them changes nothing)."""
        d = self._dir(tr.slot)
        j = self._journals[tr.slot]
        if data is None:
            data = (d / "partial.bin").read_bytes()
        if j.bin_fd is not None:  # the bytes it vouches for are on disk before the checkpoint is
            os.fdatasync(j.bin_fd)
        else:
            with open(d / "partial.bin", "rb+") as fh:
                os.fdatasync(fh.fileno())
        view = memoryview(data)
        ranges = [[a, b, zlib.crc32(view[a:b])] for a, b in tr.ranges]  # protocol.crc's, without a copy
        meta = {"format": PARTIAL_FORMAT, "length": tr.length, "crc32": tr.crc32, "ranges": ranges}
        atomic_write(d / "partial.json", json.dumps(meta, separators=(",", ":")).encode())
        if fresh_log:
            j.close()
            atomic_write(d / "partial.log", _LOG_HEADER.pack(LOG_MAGIC, tr.length, tr.crc32))
        else:
            assert j.log_fd is not None
            os.ftruncate(j.log_fd, _LOG_HEADER.size)
        j.checkpoint_bytes, j.checkpoint_ranges, j.log_bytes, j.log_records = tr.received, len(tr.ranges), 0, 0

    def transfer_bytes(self, slot: int) -> bytes:
        if not self._persistent(slot):
            return bytes(self._buffers[slot])
        return (self._dir(slot) / "partial.bin").read_bytes()

    def drop_transfer(self, slot: int) -> None:
        self._transfers.pop(slot, None)
        self._buffers.pop(slot, None)
        journal = self._journals.pop(slot, None)
        if journal is not None:
            journal.close()
        if self.root is not None and slot not in self.volatile:  # _persistent(slot), narrowed
            d = self.root / f"slot{slot}"
            for name in ("partial.json", "partial.bin", "partial.log"):  # the checkpoint first
                if (d / name).exists():
                    _remove(d / name)


def _parse_manifest(meta) -> dict[int, tuple[int, int]]:
    """``{"slots": {"N": {"length": n, "crc32": c}}}`` -> {N: (n, c)}; ValueError for any other shape."""
    slots = meta.get("slots") if isinstance(meta, dict) else None
    if not isinstance(slots, dict):
        raise ValueError('not {"slots": {...}}')
    out = {}
    for key, entry in slots.items():
        n, c = (entry.get("length"), entry.get("crc32")) if isinstance(entry, dict) else (None, None)
        if not (key.isdigit() and int(key) <= 255 and type(n) is int and type(c) is int):
            raise ValueError(f"entry {key!r}: {entry!r:.60} is not a slot with a length and a CRC-32")
        out[int(key)] = (n, c)
    return out
