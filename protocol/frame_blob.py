"""The frame-upload format (slot 1): a raw frame as one little-endian blob, declared once.

Layout: the 48-byte :data:`HEADER_DTYPE` record, ``json_length`` bytes of UTF-8 JSON (timestamp,
site, camera, metadata), ``width * height`` uint16 pixels row-major, then the CRC-32 (zlib) of
every preceding byte. ``pattern`` codes index :data:`PATTERNS`; ``exposure`` is NaN when unknown.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

MAGIC = b"STFR"
VERSION = 1
PATTERNS = ("MONO", "RGGB", "BGGR", "GRBG", "GBRG")
HEADER_DTYPE = np.dtype(
    [
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
)
HEADER_SIZE = HEADER_DTYPE.itemsize  #: 48 bytes


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
    body = h.tobytes() + blob.extras_json + np.ascontiguousarray(blob.pixels, dtype="<u2").tobytes()
    return body + (zlib.crc32(body) & 0xFFFFFFFF).to_bytes(4, "little")


def unpack(data: bytes) -> FrameBlob:
    """Decode and check a blob; ValueError on any inconsistency (size, magic, version, pattern, CRC)."""
    data = bytes(data)
    if len(data) < HEADER_SIZE + 4:
        raise ValueError(f"frame blob too short ({len(data)} bytes)")
    h = np.frombuffer(data, HEADER_DTYPE, 1)[0]
    if bytes(h["magic"]) != MAGIC:
        raise ValueError(f"not a frame blob (magic {bytes(h['magic'])!r})")
    if int(h["version"]) != VERSION:
        raise ValueError(f"unsupported frame blob version {int(h['version'])}")
    if int(h["pattern"]) >= len(PATTERNS):
        raise ValueError(f"unknown CFA pattern code {int(h['pattern'])}")
    width, height, jlen = int(h["width"]), int(h["height"]), int(h["json_length"])
    expected = HEADER_SIZE + jlen + 2 * width * height + 4
    if len(data) != expected:
        raise ValueError(f"frame blob is {len(data)} bytes, header implies {expected}")
    if zlib.crc32(data[:-4]) & 0xFFFFFFFF != int.from_bytes(data[-4:], "little"):
        raise ValueError("frame blob CRC-32 mismatch")
    start = HEADER_SIZE + jlen
    pixels = np.frombuffer(data, dtype="<u2", count=width * height, offset=start).reshape(height, width)
    b = [float(x) for x in h["black"]]
    return FrameBlob(
        PATTERNS[int(h["pattern"])],
        (b[0], b[1], b[2], b[3]),
        float(h["white"]),
        float(h["exposure"]),
        data[HEADER_SIZE:start],
        pixels.astype(np.uint16),
    )
