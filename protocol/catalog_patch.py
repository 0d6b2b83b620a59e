"""A catalog patch: the bytes that differ between two catalog images of one length
(docs/catalog_image.md, "Patches"), sent to the device's slot 3 and applied there all at once.

Layout (little-endian): ``char[8] magic "ST16PAT1"``, ``u32 base_length``, ``u32 base_crc32``
(CRC-32 of the whole image the patch applies to), ``u32 result_crc32`` (of the whole image after
it), ``u32 n_ranges``, then per range ``u32 offset, u32 length, bytes[length]``; ranges ascending
and disjoint, inside ``base_length``. A patch never changes the image's length.

:func:`apply_patch` builds the new image in a copy and checks the base and the result CRC-32 before
returning it; the caller validates the result as any catalog image (its section, data and
header CRCs) before it replaces anything. Refusals raise :class:`PatchError` with a
:class:`PatchReason` (0x0500-0x0504, inside the link's validator range).
"""

from __future__ import annotations

import struct
from enum import IntEnum

import numpy as np

from protocol.crc import crc32

MAGIC = b"ST16PAT1"
_HEAD = struct.Struct("<8sIIII")
_RANGE = struct.Struct("<II")
MERGE_GAP = 16  #: differing runs closer than this many bytes travel as one range


class PatchReason(IntEnum):
    """Why a patch was refused (the NACK reason code the device sends)."""

    NOT_A_PATCH = 0x0500  # wrong magic, cut short, trailing bytes, ranges out of order
    NO_BASE = 0x0501  # the device holds no catalog to patch
    BASE_MISMATCH = 0x0502  # the active catalog is not the one the patch was made for
    RANGE = 0x0503  # a range outside the image
    RESULT_CRC = 0x0504  # the patched image's CRC-32 is not the announced one


class PatchError(ValueError):
    """A patch refused by :func:`apply_patch`: ``code`` and a one-line message."""

    def __init__(self, code: PatchReason, message: str):
        super().__init__(f"{PatchReason(code).name} (0x{int(code):04X}): {message}")
        self.code = PatchReason(code)
        self.message = message


def diff_ranges(old: bytes, new: bytes, gap: int = MERGE_GAP) -> list[tuple[int, int]]:
    """(offset, length) of the runs where ``new`` differs from ``old`` (same length), runs closer
    than ``gap`` bytes merged."""
    if len(old) != len(new):
        raise ValueError(f"a patch keeps the length: {len(old)} != {len(new)} bytes")
    d = np.flatnonzero(np.frombuffer(old, np.uint8) != np.frombuffer(new, np.uint8))
    if not len(d):
        return []
    cut = np.flatnonzero(np.diff(d) > gap)
    starts = d[np.concatenate([[0], cut + 1])]
    ends = d[np.concatenate([cut, [len(d) - 1]])] + 1
    return [(int(a), int(b - a)) for a, b in zip(starts, ends)]


def make_patch(old: bytes, new: bytes, gap: int = MERGE_GAP) -> bytes:
    """The patch that turns ``old`` into ``new`` (same length)."""
    ranges = diff_ranges(old, new, gap)
    out = bytearray(_HEAD.pack(MAGIC, len(old), crc32(old), crc32(new), len(ranges)))
    for off, length in ranges:
        out += _RANGE.pack(off, length) + new[off : off + length]
    return bytes(out)


def parse_patch(patch: bytes) -> tuple[int, int, int, list[tuple[int, bytes]]]:
    """``(base_length, base_crc32, result_crc32, [(offset, bytes), ...])``; :class:`PatchError`."""
    if len(patch) < _HEAD.size or patch[:8] != MAGIC:
        raise PatchError(PatchReason.NOT_A_PATCH, f"not a catalog patch (magic {bytes(patch[:8])!r})")
    _, base_len, base_crc, result_crc, n = _HEAD.unpack_from(patch)
    pos, end_prev, ranges = _HEAD.size, 0, []
    for k in range(n):
        if pos + _RANGE.size > len(patch):
            raise PatchError(PatchReason.NOT_A_PATCH, f"cut short in range {k} of {n}")
        off, length = _RANGE.unpack_from(patch, pos)
        pos += _RANGE.size
        if pos + length > len(patch):
            raise PatchError(PatchReason.NOT_A_PATCH, f"range {k}: {length} bytes, {len(patch) - pos} left")
        if off < end_prev or length == 0:
            raise PatchError(
                PatchReason.NOT_A_PATCH, f"range {k} at {off}+{length}: empty, overlapping or out of order"
            )
        if off + length > base_len:
            raise PatchError(PatchReason.RANGE, f"range {k} at {off}+{length} beyond the image's {base_len} bytes")
        ranges.append((off, bytes(patch[pos : pos + length])))
        pos += length
        end_prev = off + length
    if pos != len(patch):
        raise PatchError(PatchReason.NOT_A_PATCH, f"{len(patch) - pos} trailing bytes")
    return base_len, base_crc, result_crc, ranges


def apply_patch(base: bytes, patch: bytes) -> bytes:
    """The image ``patch`` makes of ``base``, its base and result CRC-32s checked (a copy: ``base``
    is never touched); :class:`PatchError` otherwise."""
    base_len, base_crc, result_crc, ranges = parse_patch(patch)
    if len(base) != base_len or crc32(base) != base_crc:
        raise PatchError(
            PatchReason.BASE_MISMATCH,
            f"made for an image of {base_len} bytes, CRC-32 0x{base_crc:08X}; the active one is {len(base)} bytes, "
            f"0x{crc32(base):08X}",
        )
    buf = bytearray(base)
    for off, data in ranges:
        buf[off : off + len(data)] = data
    out = bytes(buf)
    if crc32(out) != result_crc:
        raise PatchError(
            PatchReason.RESULT_CRC, f"patched image CRC-32 0x{crc32(out):08X} != announced 0x{result_crc:08X}"
        )
    return out
