"""The frame-upload format (slot 1): a raw frame as one little-endian blob, declared once.

Layout (version 2): the 52-byte :data:`HEADER_DTYPE` record, ``json_length`` bytes of UTF-8 JSON
(timestamp, site, camera, metadata), then ``width * height`` uint16 pixels row-major. The
header's last field is the CRC-32 (zlib) of the header's other 48 bytes followed by everything
after the header. ``pattern`` codes index :data:`PATTERNS`; ``exposure`` is NaN when unknown.

Version 1 (still read) put that CRC-32 in a 4-byte trailer instead. Every such blob, whatever its
pixels, has the same whole-file CRC-32, :data:`~protocol.crc.CRC32_RESIDUE` (the residue of any message
followed by its own little-endian CRC-32), so a transfer's announced length and CRC-32 could not
tell two frames of one camera apart, and an upload resumed the wrong frame's bytes.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

MAGIC = b"STFR"
VERSION = 2
PATTERNS = ("MONO", "RGGB", "BGGR", "GRBG", "GBRG")
_V1_FIELDS = [
    ("magic", "S4"),
    ("version", "u1"),
    ("pattern", "u1"),
    ("reserved", "<u2"),
    ("width", "<u4"),
    ("height", "<u4"),
    ("black", "<f4", (4,)),
    ("white", "<f4"),
    ("exposure", "<f8"),
    ("json_length", "<u4"),
]
HEADER_DTYPE = np.dtype([*_V1_FIELDS, ("crc32", "<u4")])
HEADER_SIZE = HEADER_DTYPE.itemsize  #: 52 bytes
V1_HEADER_DTYPE = np.dtype(_V1_FIELDS)  #: version 1: 48 bytes, the CRC-32 in a trailer


@dataclass(frozen=True)
class FrameBlob:
    """A decoded blob: header values, the JSON block and the pixels (height, width) uint16."""

    pattern: str
    black: tuple[float, float, float, float]
    white: float
    exposure: float
    extras_json: bytes
    pixels: np.ndarray


def pack(blob: FrameBlob) -> bytes:
    """The blob bytes of ``blob`` (pixels must already be uint16-valued)."""
    h = np.zeros((), HEADER_DTYPE)
    h["magic"], h["version"], h["pattern"] = MAGIC, VERSION, PATTERNS.index(blob.pattern)
    h["height"], h["width"] = blob.pixels.shape
    h["black"], h["white"], h["exposure"] = blob.black, blob.white, blob.exposure
    h["json_length"] = len(blob.extras_json)
    rest = blob.extras_json + np.ascontiguousarray(blob.pixels, dtype="<u2").tobytes()
    h["crc32"] = _crc(h.tobytes()[:-4], rest)
    return h.tobytes() + rest


def _crc(head: bytes, rest: bytes) -> int:
    return zlib.crc32(rest, zlib.crc32(head)) & 0xFFFFFFFF


def unpack(data: bytes) -> FrameBlob:
    """Decode and check a blob (version 2, or 1); ValueError on any inconsistency (size, magic,
    version, pattern, CRC)."""
    data = bytes(data)
    if len(data) < V1_HEADER_DTYPE.itemsize + 4:
        raise ValueError(f"frame blob too short ({len(data)} bytes)")
    h = np.frombuffer(data, V1_HEADER_DTYPE, 1)[0]
    if bytes(h["magic"]) != MAGIC:
        raise ValueError(f"not a frame blob (magic {bytes(h['magic'])!r})")
    version = int(h["version"])
    if version not in (1, 2):
        raise ValueError(f"unsupported frame blob version {version}")
    if int(h["pattern"]) >= len(PATTERNS):
        raise ValueError(f"unknown CFA pattern code {int(h['pattern'])}")
    width, height, jlen = int(h["width"]), int(h["height"]), int(h["json_length"])
    start = (HEADER_SIZE if version == 2 else V1_HEADER_DTYPE.itemsize) + jlen
    expected = start + 2 * width * height + (4 if version == 1 else 0)
    if len(data) != expected:
        raise ValueError(f"frame blob is {len(data)} bytes, header implies {expected}")
    if version == 2:
        ok = _crc(data[: HEADER_SIZE - 4], data[HEADER_SIZE:]) == int.from_bytes(
            data[HEADER_SIZE - 4 : HEADER_SIZE], "little"
        )
    else:
        ok = zlib.crc32(data[:-4]) & 0xFFFFFFFF == int.from_bytes(data[-4:], "little")
    if not ok:
        raise ValueError("frame blob CRC-32 mismatch")
    pixels = np.frombuffer(data, dtype="<u2", count=width * height, offset=start).reshape(height, width)
    b = [float(x) for x in h["black"]]
    return FrameBlob(
        PATTERNS[int(h["pattern"])],
        (b[0], b[1], b[2], b[3]),
        float(h["white"]),
        float(h["exposure"]),
        data[start - jlen : start],
        pixels.astype(np.uint16),
    )
