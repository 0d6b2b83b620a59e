"""The on-board catalog image: a versioned, little-endian binary file (docs/catalog_image.md).

Layout: a fixed header (magic, version, sizes, counts, build parameters, epoch, a table of four
sections with offset, size and CRC-32 each, the CRC-32 of everything after the header, and the
header's own CRC-32), then the 8-byte aligned sections STARS, PAIRS, HASH and KVECTOR.

:func:`parse_image` validates everything and returns numpy views into the caller's buffer (no
copies of the tables). Any inconsistency raises :class:`CatalogImageError` with one of the
:class:`Reason` codes (0x0201-0x0212, inside the link's validator range 0x0100-0xFFFF).
This module works on named arrays and header fields only; the conversion from and to the
firmware's ``OnboardCatalog`` lives in ``firmware_model/catalog/image_io.py``.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

MAGIC = b"ST16CAT\x00"
VERSION = 1
ALIGN = 8
UNIT_NORM_TOL = 1e-9  # |norm - 1| allowed for star vectors
ANGLE_TOL = 1e-9  # rad, stored pair angle vs. angle from the star vectors
FLAG_COLOUR = 0x1  # header flag: the star table holds colour ratios

STAR_DTYPE = np.dtype(
    [
        ("star_id", "<u4"),
        ("flags", "<u4"),
        ("vec", "<f8", (3,)),
        ("mag", "<f4"),
        ("rg", "<f4"),
        ("bg", "<f4"),
        ("reserved", "<u4"),
    ]
)
PAIR_DTYPE = np.dtype([("i", "<u4"), ("j", "<u4"), ("phi", "<f8")])
INDEX_DTYPE = np.dtype("<u4")
SECTIONS = ("stars", "pairs", "hash", "kvector")
#: per-star flags, low byte: colour source (0 none, 1 Pickles MK, 2 B-V lookup, 3 blackbody, 4 V-I lookup)
STAR_COLOUR_SOURCE_MASK = 0xFF
MAX_COLOUR_SOURCE = 4
STAR_FLAG_VARIABLE = 0x100

#: The header, declared once: packing fills a record of it, parsing reads one (192 bytes).
#: ``sections``: (offset, size, CRC-32) of each of :data:`SECTIONS`, in order.
HEADER_DTYPE = np.dtype(
    [
        ("magic", "S8"),
        ("version", "<u2"),
        ("header_size", "<u2"),
        ("flags", "<u4"),
        ("total_size", "<u4"),
        ("n_stars", "<u4"),
        ("n_pairs", "<u4"),
        ("n_h", "<u4"),
        ("source_id", "<u4"),
        ("epoch", "<f8"),
        ("phi_min", "<f8"),
        ("phi_max", "<f8"),
        ("dphi_star", "<f8"),
        ("kv_m", "<f8"),
        ("kv_q", "<f8"),
        ("theta_fov", "<f8"),
        ("m_thresh", "<f8"),
        ("sigma_phi", "<f8"),
        ("sigma_rg", "<f8"),
        ("sigma_bg", "<f8"),
        ("created_unix", "<i8"),
        ("sections", "<u4", (4, 3)),
        ("n_pattern_stars", "<u4"),
        ("data_crc32", "<u4"),
        ("header_crc32", "<u4"),
    ]
)
HEADER_SIZE = HEADER_DTYPE.itemsize
assert HEADER_SIZE % ALIGN == 0
#: ImageParams fields stored as floats and as integers in the header (same names).
_FLOAT_PARAMS = (
    "epoch",
    "phi_min",
    "phi_max",
    "dphi_star",
    "kv_m",
    "kv_q",
    "theta_fov",
    "m_thresh",
    "sigma_phi",
    "sigma_rg",
    "sigma_bg",
)
_INT_PARAMS = ("n_h", "source_id", "flags", "created_unix", "n_pattern_stars")


class Reason(IntEnum):
    """Why an image was refused (the NACK reason code the device sends)."""

    TRUNCATED = 0x0201  # shorter than the header or than the declared total size
    BAD_MAGIC = 0x0202
    BAD_VERSION = 0x0203
    HEADER_CRC = 0x0204
    SIZE_MISMATCH = 0x0205  # longer than the declared total size, or header_size wrong
    SECTION_BOUNDS = 0x0206  # misaligned, overlapping or outside the file
    SECTION_SIZE = 0x0207  # section size disagrees with the counts
    SECTION_CRC = 0x0208
    DATA_CRC = 0x0209
    BAD_PARAMETERS = 0x020A  # non-finite or impossible build parameters
    STAR_VECTOR = 0x020B  # non-finite or not unit norm
    STAR_VALUES = 0x020C  # non-finite magnitude, negative colour ratio, unknown colour source
    PAIR_INDEX = 0x020D  # star index out of range or i >= j
    PAIR_ORDER = 0x020E  # angles not ascending or outside (phi_min, phi_max]
    PAIR_ANGLE = 0x020F  # stored angle disagrees with the star vectors
    HASH_INDEX = 0x0210
    KVECTOR = 0x0211
    COUNTS = 0x0212  # impossible counts (no stars, more pairs than n(n-1)/2, more pattern stars than stars)


class CatalogImageError(ValueError):
    """An image refused by :func:`parse_image`: ``code`` (a :class:`Reason`) and a precise message."""

    def __init__(self, code: Reason, message: str):
        super().__init__(f"{Reason(code).name} (0x{int(code):04X}): {message}")
        self.code = Reason(code)
        self.message = message


@dataclass
class ImageParams:
    """Build parameters stored in the header (angles in radians, epoch in Julian years)."""

    epoch: float
    phi_min: float
    phi_max: float
    dphi_star: float
    kv_m: float
    kv_q: float
    n_h: int
    theta_fov: float = float("nan")
    m_thresh: float = float("nan")
    sigma_phi: float = float("nan")
    sigma_rg: float = float("nan")
    sigma_bg: float = float("nan")
    source_id: int = 0  # 0 unknown, 1 Hipparcos, 2 Yale BSC5
    flags: int = 0
    created_unix: int = 0
    #: stars ``[0, n)`` form the pairs; the rest are verification-only (fainter); 0: every star
    n_pattern_stars: int = 0


@dataclass
class SectionEntry:
    offset: int
    size: int
    crc32: int


@dataclass
class CatalogImage:
    """A validated image: header values and read-only numpy views into the buffer."""

    version: int
    n_stars: int
    n_pairs: int
    params: ImageParams
    sections: dict[str, SectionEntry]
    total_size: int
    data_crc32: int
    header_crc32: int
    stars: np.ndarray  # STAR_DTYPE
    pairs: np.ndarray  # PAIR_DTYPE
    hash_index: np.ndarray  # n_h + 1 entries
    kvector: np.ndarray  # n_pairs entries (empty if fewer than two pairs)


def crc32(data: bytes | bytearray | memoryview) -> int:
    """CRC-32 (zlib / ISO-HDLC) of bytes-like ``data``."""
    return zlib.crc32(data) & 0xFFFFFFFF


def hash_bounds(n_h: int, phi_max: float, dphi_star: float) -> np.ndarray:
    """Lower angle bound of every hash bucket h = 0..n_h: ``h * (phi_max / n_h) - dphi_star``."""
    return np.arange(n_h + 1, dtype=float) * (phi_max / n_h) - dphi_star


def _align(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


def pack_image(
    params: ImageParams, stars: np.ndarray, pairs: np.ndarray, hash_index: np.ndarray, kvector: np.ndarray
) -> bytes:
    """Serialise an image. ``stars``/``pairs`` are STAR_DTYPE/PAIR_DTYPE arrays (or castable)."""
    blobs = {
        "stars": np.ascontiguousarray(stars, dtype=STAR_DTYPE).tobytes(),
        "pairs": np.ascontiguousarray(pairs, dtype=PAIR_DTYPE).tobytes(),
        "hash": np.ascontiguousarray(hash_index, dtype=INDEX_DTYPE).tobytes(),
        "kvector": np.ascontiguousarray(kvector, dtype=INDEX_DTYPE).tobytes(),
    }
    body, entries, offset = bytearray(), [], HEADER_SIZE
    for name in SECTIONS:
        blob = blobs[name]
        entries += [offset, len(blob), crc32(blob)]
        padded = blob + bytes(_align(len(blob)) - len(blob))
        body += padded
        offset += len(padded)
    header = _pack_header(params, len(stars), len(pairs), HEADER_SIZE + len(body), entries, crc32(body))
    return header + bytes(body)


def _pack_header(p: ImageParams, n_stars: int, n_pairs: int, total: int, entries: list[int], data_crc: int) -> bytes:
    h = np.zeros((), HEADER_DTYPE)
    h["magic"], h["version"], h["header_size"] = MAGIC, VERSION, HEADER_SIZE
    h["total_size"], h["n_stars"], h["n_pairs"], h["data_crc32"] = total, n_stars, n_pairs, data_crc
    for name in _FLOAT_PARAMS + _INT_PARAMS:
        h[name] = getattr(p, name)
    h["sections"] = np.reshape(entries, (len(SECTIONS), 3))
    raw = h.tobytes()
    return raw[:-4] + struct.pack("<I", crc32(raw[:-4]))


def with_star_colours(data: bytes | bytearray | memoryview, rg: np.ndarray, bg: np.ndarray) -> bytes:
    """A copy of the valid image ``data`` whose STARS rows carry the colour ratios ``rg``/``bg``
    (one per star, stored as f32), re-signed: the STARS CRC-32, the data CRC-32 and the header
    CRC-32 are recomputed and the result validated (:class:`CatalogImageError` if it is not)."""
    img = parse_image(data)
    rg32, bg32 = np.asarray(rg, dtype="<f4"), np.asarray(bg, dtype="<f4")
    if rg32.shape != (img.n_stars,) or bg32.shape != (img.n_stars,):
        raise ValueError(f"need {img.n_stars} colour ratios of each kind, got {rg32.shape} and {bg32.shape}")
    buf = bytearray(data)
    e = img.sections["stars"]
    stars = np.frombuffer(buf, STAR_DTYPE, img.n_stars, e.offset)
    stars["rg"], stars["bg"] = rg32, bg32
    head = np.frombuffer(buf, HEADER_DTYPE, 1)
    head["sections"][0, 0, 2] = crc32(buf[e.offset : e.offset + e.size])
    head["data_crc32"] = crc32(buf[HEADER_SIZE : img.total_size])
    head["header_crc32"] = crc32(buf[: HEADER_SIZE - 4])
    out = bytes(buf)
    parse_image(out)
    return out


def parse_image(data: bytes | bytearray | memoryview) -> CatalogImage:
    """Validate ``data`` (bytes-like) and return views into it; raise :class:`CatalogImageError`."""
    buf = memoryview(data).cast("B")
    n = len(buf)
    if n < HEADER_SIZE:
        raise CatalogImageError(Reason.TRUNCATED, f"{n} bytes, the header alone is {HEADER_SIZE}")
    if bytes(buf[:8]) != MAGIC:
        raise CatalogImageError(Reason.BAD_MAGIC, f"magic {bytes(buf[:8])!r}, expected {MAGIC!r}")
    h = np.frombuffer(buf, HEADER_DTYPE, 1)[0]
    version, header_size, total = int(h["version"]), int(h["header_size"]), int(h["total_size"])
    n_stars, n_pairs, n_h, header_crc = int(h["n_stars"]), int(h["n_pairs"]), int(h["n_h"]), int(h["header_crc32"])
    if version != VERSION:
        raise CatalogImageError(Reason.BAD_VERSION, f"version {version}, this device reads version {VERSION}")
    if crc32(buf[: HEADER_SIZE - 4]) != header_crc:
        raise CatalogImageError(
            Reason.HEADER_CRC, f"header CRC-32 0x{header_crc:08X} != computed 0x{crc32(buf[: HEADER_SIZE - 4]):08X}"
        )
    if header_size != HEADER_SIZE:
        raise CatalogImageError(Reason.SIZE_MISMATCH, f"header_size {header_size}, expected {HEADER_SIZE}")
    if n < total:
        raise CatalogImageError(Reason.TRUNCATED, f"{n} bytes, header declares {total}")
    if n > total:
        raise CatalogImageError(Reason.SIZE_MISMATCH, f"{n} bytes, header declares {total} ({n - total} trailing)")
    values: dict[str, Any] = {f: float(h[f]) for f in _FLOAT_PARAMS} | {f: int(h[f]) for f in _INT_PARAMS}
    params = ImageParams(**values)
    sec = {name: SectionEntry(*(int(x) for x in h["sections"][k])) for k, name in enumerate(SECTIONS)}
    data_crc = int(h["data_crc32"])
    _check_sections(sec, total, n_stars, n_pairs, n_h)
    if params.n_pattern_stars > n_stars:
        raise CatalogImageError(Reason.COUNTS, f"{params.n_pattern_stars} pattern stars of {n_stars} stars")
    for name, e in sec.items():
        got = crc32(buf[e.offset : e.offset + e.size])
        if got != e.crc32:
            raise CatalogImageError(
                Reason.SECTION_CRC, f"section {name}: CRC-32 0x{e.crc32:08X} != computed 0x{got:08X}"
            )
    got = crc32(buf[HEADER_SIZE:total])
    if got != data_crc:
        raise CatalogImageError(
            Reason.DATA_CRC, f"data CRC-32 0x{data_crc:08X} != computed 0x{got:08X} (padding altered?)"
        )
    img = CatalogImage(
        version=version,
        n_stars=n_stars,
        n_pairs=n_pairs,
        params=params,
        sections=sec,
        total_size=total,
        data_crc32=data_crc,
        header_crc32=header_crc,
        stars=np.frombuffer(buf, STAR_DTYPE, n_stars, sec["stars"].offset),
        pairs=np.frombuffer(buf, PAIR_DTYPE, n_pairs, sec["pairs"].offset),
        hash_index=np.frombuffer(buf, INDEX_DTYPE, n_h + 1, sec["hash"].offset),
        kvector=np.frombuffer(buf, INDEX_DTYPE, sec["kvector"].size // 4, sec["kvector"].offset),
    )
    _check_params(params)
    _check_stars(img)
    _check_pairs(img)
    _check_hash(img)
    _check_kvector(img)
    return img


def _check_sections(sec: dict[str, SectionEntry], total: int, n_stars: int, n_pairs: int, n_h: int) -> None:
    if n_stars < 1 or n_pairs > n_stars * (n_stars - 1) // 2:
        raise CatalogImageError(Reason.COUNTS, f"{n_stars} stars cannot form {n_pairs} pairs")
    if n_h < 1:
        raise CatalogImageError(Reason.BAD_PARAMETERS, f"n_h = {n_h}, must be >= 1")
    expected = {
        "stars": n_stars * STAR_DTYPE.itemsize,
        "pairs": n_pairs * PAIR_DTYPE.itemsize,
        "hash": (n_h + 1) * INDEX_DTYPE.itemsize,
        "kvector": (n_pairs if n_pairs >= 2 else 0) * INDEX_DTYPE.itemsize,
    }
    end = HEADER_SIZE
    for name in SECTIONS:
        e = sec[name]
        if e.offset % ALIGN or e.offset < end or e.offset + e.size > total:
            raise CatalogImageError(
                Reason.SECTION_BOUNDS,
                f"section {name} at {e.offset}+{e.size}: must be {ALIGN}-byte aligned, after byte {end} and inside {total} bytes",
            )
        if e.size != expected[name]:
            raise CatalogImageError(
                Reason.SECTION_SIZE, f"section {name}: {e.size} bytes, the counts need {expected[name]}"
            )
        end = e.offset + e.size


def _check_params(p: ImageParams) -> None:
    for name in ("epoch", "phi_min", "phi_max", "dphi_star", "kv_m", "kv_q"):
        if not np.isfinite(getattr(p, name)):
            raise CatalogImageError(Reason.BAD_PARAMETERS, f"{name} = {getattr(p, name)} is not finite")
    if not 0.0 <= p.phi_min < p.phi_max <= np.pi:
        raise CatalogImageError(
            Reason.BAD_PARAMETERS, f"need 0 <= phi_min < phi_max <= pi, got {p.phi_min}, {p.phi_max}"
        )
    if not 0.0 <= p.dphi_star < p.phi_max:
        raise CatalogImageError(Reason.BAD_PARAMETERS, f"dphi_star = {p.dphi_star} outside [0, phi_max)")


def _check_stars(img: CatalogImage) -> None:
    s = img.stars
    norm = np.linalg.norm(s["vec"], axis=1)
    bad = np.flatnonzero(~np.isfinite(norm) | (np.abs(norm - 1.0) > UNIT_NORM_TOL))
    if len(bad):
        raise CatalogImageError(
            Reason.STAR_VECTOR, f"star row {bad[0]} (id {s['star_id'][bad[0]]}): |vec| = {norm[bad[0]]!r}"
        )
    bad = np.flatnonzero(~np.isfinite(s["mag"]))
    if len(bad):
        raise CatalogImageError(Reason.STAR_VALUES, f"star row {bad[0]}: magnitude {s['mag'][bad[0]]}")
    for name in ("rg", "bg"):  # NaN = unknown colour; otherwise finite and positive
        x = s[name]
        bad = np.flatnonzero(~np.isnan(x) & ~((x > 0) & np.isfinite(x)))
        if len(bad):
            raise CatalogImageError(Reason.STAR_VALUES, f"star row {bad[0]}: {name} = {x[bad[0]]}")
    bad = np.flatnonzero((s["flags"] & STAR_COLOUR_SOURCE_MASK) > MAX_COLOUR_SOURCE)
    if len(bad):
        raise CatalogImageError(
            Reason.STAR_VALUES, f"star row {bad[0]}: unknown colour source {s['flags'][bad[0]] & 0xFF}"
        )


def _check_pairs(img: CatalogImage) -> None:
    pr, p = img.pairs, img.params
    n = img.params.n_pattern_stars or img.n_stars
    bad = np.flatnonzero((pr["i"] >= pr["j"]) | (pr["j"] >= n))
    if len(bad):
        k = bad[0]
        raise CatalogImageError(
            Reason.PAIR_INDEX, f"pair {k}: ({pr['i'][k]}, {pr['j'][k]}) with {n} pattern stars (need i < j < n)"
        )
    phi = pr["phi"]
    bad = np.flatnonzero(~(phi > p.phi_min) | ~(phi <= p.phi_max))
    if len(bad):
        raise CatalogImageError(
            Reason.PAIR_ORDER, f"pair {bad[0]}: angle {phi[bad[0]]!r} outside ({p.phi_min}, {p.phi_max}]"
        )
    bad = np.flatnonzero(np.diff(phi) < 0)
    if len(bad):
        raise CatalogImageError(
            Reason.PAIR_ORDER, f"pairs {bad[0]}, {bad[0] + 1}: angles {phi[bad[0]]!r} > {phi[bad[0] + 1]!r}"
        )
    vec = img.stars["vec"]
    d = np.linalg.norm(vec[pr["i"]] - vec[pr["j"]], axis=1)
    err = np.abs(2.0 * np.arcsin(np.clip(d / 2.0, 0.0, 1.0)) - phi)
    bad = np.flatnonzero(err > ANGLE_TOL)
    if len(bad):
        raise CatalogImageError(
            Reason.PAIR_ANGLE, f"pair {bad[0]}: stored angle differs from the star vectors by {err[bad[0]]:.3g} rad"
        )


def _check_hash(img: CatalogImage) -> None:
    """``P_h`` = first pair with phi >= h phi_max / n_h - dphi_star; ``P_{n_h}`` = n_pairs."""
    p = img.params
    want = np.searchsorted(img.pairs["phi"], hash_bounds(p.n_h, p.phi_max, p.dphi_star), side="left")
    want[-1] = img.n_pairs
    bad = np.flatnonzero(img.hash_index != want)
    if len(bad):
        h = bad[0]
        raise CatalogImageError(Reason.HASH_INDEX, f"P_{h} = {img.hash_index[h]}, the pair table gives {want[h]}")


def _check_kvector(img: CatalogImage) -> None:
    """K-vector over ascending cos(phi): ``k[i]`` = count of cosines <= m (i + 1) + q, line bracketing the data."""
    n, p = img.n_pairs, img.params
    if n < 2:
        return
    y = np.cos(img.pairs["phi"][::-1])
    if not (p.kv_m > 0 and p.kv_m + p.kv_q <= y[0] and p.kv_m * n + p.kv_q >= y[-1]):
        raise CatalogImageError(
            Reason.KVECTOR, f"line m = {p.kv_m!r}, q = {p.kv_q!r} does not bracket the cosines [{y[0]!r}, {y[-1]!r}]"
        )
    want = np.searchsorted(y, p.kv_m * np.arange(1, n + 1) + p.kv_q, side="right")
    bad = np.flatnonzero(img.kvector != want)
    if len(bad):
        raise CatalogImageError(
            Reason.KVECTOR, f"k[{bad[0]}] = {img.kvector[bad[0]]}, the pair table gives {want[bad[0]]}"
        )
