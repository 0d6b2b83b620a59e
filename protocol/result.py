"""The result structure read with READ RESULT / COMBINATION (little-endian).

Bytes 0x000-0x947 follow the COSMOS overlay of the ST-16 operational result (natural C
alignment); 0x948-0xA37 are reserved (the research reports a 2616-byte result but no layout
for these 240 bytes). EDAC 0x004C reports :data:`STANDARD_LENGTH` (2616) when a result is ready.
Our extension region for colour stars and matching starts at :data:`EXT_OFFSET` (0x0A38); its
length is reported at EDAC 0x0050 as the total :data:`TOTAL_LENGTH`.

Our choices (docs/ICD.md): quaternions are scalar first ``[w, x, y, z]``, ICRS -> sensor
(docs/CONVENTIONS.md), unless the device parameter ``quaternion_order`` makes those of the
standard structure scalar last (:class:`QuaternionOrder`, flagged in ``hardware.status``);
``epoch`` is the exposure's mid-time on the device clock (seconds of the TIME count; the same
instant in POSIX UTC is ``ext.utc_epoch``); the hardware section begins with flash error counts; ``return_code`` keeps the COSMOS bits in bits 0-6, bit 7 set
when our status (:class:`Status`, bits 8-15) is not OK, and the status is mirrored into the low
byte of ``hardware.status`` for readers that keep only the return code's low byte (docs/ICD.md
section 10.2, COSMOS compatibility).
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import Enum, IntEnum
from typing import Any

import numpy as np


def _struct(fields: list[tuple[str, str | np.dtype[Any], int]], itemsize: int) -> np.dtype[np.void]:
    names, formats, offsets = zip(*fields)
    return np.dtype({"names": list(names), "formats": list(formats), "offsets": list(offsets), "itemsize": itemsize})


HARDWARE = _struct(
    [
        ("flash_errors", "<3u4", 0x00),
        ("detector_temp_raw", "<i2", 0x0C),
        ("processor_temp_raw", "<u2", 0x0E),
        ("status", "<u4", 0x10),
        ("vdd_core_setpoint", "u1", 0x14),
        ("mpu_setpoint", "u1", 0x15),
        ("reserved", "2u1", 0x16),
        ("dark_offsets", "<16u2", 0x18),
    ],
    56,
)

#: ``hardware.status`` (ours in bits 0-11; the COSMOS agent names bit 19 memory over-temperature and
#: bit 31 thermal shutdown, which the emulator never sets): bits 0-7 mirror the status
#: (return-code bits 8-15), bit 8 says the standard structure's quaternions are scalar last, bits
#: 9-11 name the bright bodies inside their exclusion angles (:class:`ExclusionBits`).
HW_STATUS_MIRROR = 0x00FF
HW_QUATERNION_SCALAR_LAST = 0x0100


class ExclusionBits(IntEnum):
    """``hardware.status`` bits 9-11: a bright body inside its exclusion angle (device parameters
    ``sun_exclusion_deg``, ``moon_exclusion_deg``, ``earth_exclusion_deg``), set whenever the
    check finds it, whatever the status (docs/ICD.md section 10)."""

    SUN_IN_FOV = 0x0200
    MOON_IN_FOV = 0x0400
    EARTH_IN_FOV = 0x0800


#: The bodies the exclusion check knows, in the order it names them when several are inside.
EXCLUDED_BODIES = ("sun", "earth", "moon")


def exclusion_bit(body: str) -> ExclusionBits:
    """The ``hardware.status`` bit of ``body`` (one of :data:`EXCLUDED_BODIES`)."""
    return ExclusionBits[f"{body.upper()}_IN_FOV"]


def bodies_in_fov(hardware_status: int) -> list[str]:
    """The bodies ``hardware.status`` flags inside their exclusion angles, in :data:`EXCLUDED_BODIES` order."""
    return [b for b in EXCLUDED_BODIES if int(hardware_status) & exclusion_bit(b)]


def detector_temp_c(raw: int) -> float:
    """``hardware.detector_temp_raw`` in degC, as COSMOS converts it: ``(raw >> 4) / 16``."""
    return (int(raw) >> 4) / 16.0


def processor_temp_c(raw: int) -> float:
    """``hardware.processor_temp_raw`` in degC, as COSMOS converts it: ``25 + (raw - 0x32) * 1.5``."""
    return 25.0 + (int(raw) - 0x32) * 1.5


STATISTICS = _struct(
    [
        ("good_rows", "<2u2", 0),
        ("mean_1", "<8f4", 4),
        ("mean_2", "<8f4", 36),
        ("variation_1", "<8f4", 68),
        ("variation_2", "<8f4", 100),
        ("temporal_variation", "<8f4", 132),
        ("spare", "<2u4", 164),
    ],
    172,
)

IMAGE = _struct(
    [
        ("initialized", "<u4", 0),
        ("return_code", "<i4", 4),
        ("lit_pixels", "<i4", 8),
        ("peak_count", "<u4", 12),
        ("exposure_error", "<f8", 16),
        ("capture_time", "<f8", 24),
        ("peaks", "<(30,3)i4", 32),
    ],
    392,
)

ERS = _struct(
    [
        ("initialized", "<u4", 0),
        ("return_code", "<i4", 4),
        ("star_mapping", "<10i4", 8),
        ("fit_residual", "<f8", 48),
        ("spare", "48u1", 56),
    ],
    104,
)

CENTROID = _struct(
    [
        ("initialized", "<u4", 0),
        ("return_code", "<i4", 4),
        ("good_stars", "<i4", 8),
        ("centroids", "<(10,2)f8", 16),
        ("unit_vectors", "<(10,3)f8", 176),
    ],
    416,
)

MATCHING = _struct(
    [
        ("initialized", "<u4", 0),
        ("return_code", "<i4", 4),
        ("triangle_tests", "<i4", 8),
        ("matching_error", "<f8", 16),
        ("confidence", "<f8", 24),
        ("star_tests", "<i4", 32),
        ("set_tests", "<i4", 36),
        ("consensus_size", "<i4", 40),
        ("consensus_rms", "<f8", 48),
        ("matched_stars", "<10i4", 56),
        ("quaternion", "<4f8", 96),
        ("attitude_covariance", "<6f8", 128),
    ],
    176,
)

EXT_MAX_STARS = 29

#: Solar-system bodies a star's flags can name (bits 8-11: 1 + index here; 0 none).
BODIES = ("mercury", "venus", "mars", "jupiter", "saturn", "uranus", "neptune", "moon")

#: One detected star in the extension region (ours): pixel centroid (x = column, y = row), flux in
#: DN, colour ratios rg = S_r/S_g and bg = S_b/S_g with 1-sigma, matched catalog id (-1: none),
#: residual to the matched catalog direction (rad), flags (bit 0 matched, bit 1 saturated,
#: bit 2 on a predicted planet or the moon, bits 8-11 which: 1 + index into :data:`BODIES`).
EXT_STAR = _struct(
    [
        ("x", "<f4", 0),
        ("y", "<f4", 4),
        ("flux", "<f4", 8),
        ("rg", "<f4", 12),
        ("bg", "<f4", 16),
        ("rg_sigma", "<f4", 20),
        ("bg_sigma", "<f4", 24),
        ("catalog_id", "<i4", 28),
        ("residual", "<f4", 32),
        ("flags", "<u4", 36),
    ],
    40,
)

EXT_MAGIC = 0x31545343  # b"CST1"
#: 2: optics block added, EXT_MAX_STARS 32 -> 31 (same total length); 3: search block; 4: time and
#: rate block (the rate covariance moved here from ``ers`` and ``matching``), EXT_MAX_STARS 31 -> 29
EXT_VERSION = 4
EXT_REASON_BYTES = 96  #: UTF-8 reason text (NUL padded) when the status is not OK

#: Optics flags (``ext.optics_flags``).
OPTICS_FITTED = 0x01  #: focal length (and k1 when ``k1_sigma`` is finite) fitted to this solve's stars
OPTICS_SEARCHED = 0x02  #: found by the focal-length search (``focal_scale`` is the step that found it)
PSF_MEASURED = 0x04  #: ``psf_sigma`` was measured on this frame (else: the setting or the start value)

#: Search flags (``ext.search_flags``): what stopped a search of this frame early.
SEARCH_BUDGET_REACHED = 0x01  #: a counted search budget ran out (the same on every machine)
DEADLINE_MISSED = 0x02  #: flight timing only: the deadline stopped a search (the answer is what it had by then)

#: Extension header (ours), 248 bytes, then EXT_MAX_STARS stars. ``quaternion`` is the solved
#: attitude (scalar first, ICRS -> sensor); ``sigma`` its 1-sigma errors about sensor x, y, z (rad);
#: ``solve_time`` seconds spent in the solver; CRC-32s identify the catalog and frame used;
#: ``colour_rms`` RMS of (rg, bg) minus the catalog's over the matched stars, after the device's
#: colour correction (the stars' ``rg``, ``bg`` are the raw measurements);
#: ``stage_times`` seconds for detect, fit, vectors, identify, attitude, total
#: (``firmware_model.pipeline.solve_types.STAGES``); ``method`` a :class:`MethodCode`: 0 none, 1 colour, 2 geometric (4-star), 3 geometric
#: consensus, 4 scale-free pattern (uncalibrated optics), 5 tracking; ``reason``
#: why the status is what it is (UTF-8, truncated to EXT_REASON_BYTES). Optics block: ``psf_sigma``
#: PSF Gaussian sigma used (px); ``focal_px`` / ``focal_sigma`` fitted focal length and 1-sigma (px),
#: ``k1`` / ``k1_sigma`` radial distortion (NaN sigma: held), ``optics_rms`` residual of that fit
#: (px) over ``optics_stars`` stars, ``optics_flags`` (OPTICS_*, PSF_MEASURED), ``n_planets``
#: detections labelled as planets or the moon, ``focal_scale`` the search step that solved. Search
#: block: ``search_flags`` (SEARCH_BUDGET_REACHED, DEADLINE_MISSED), the counted work of the frame:
#: ``seeds`` pattern seeds refined and ``verifications`` hypotheses verified. Time and rate block:
#: ``omega_covariance`` the covariance of the result's ``omega`` (xx, yy, zz, xy, xz, yz,
#: (rad/s)^2; a tracked answer's, else 0) and ``utc_epoch``, the exposure's mid-time in POSIX UTC
#: seconds (the standard ``epoch`` is the same instant on the device clock).
EXTENSION = _struct(
    [
        ("magic", "<u4", 0),
        ("version", "<u2", 4),
        ("n_detected", "<u2", 6),
        ("n_matched", "<u2", 8),
        ("n_reported", "<u2", 10),
        ("solve_time", "<f4", 12),
        ("quaternion", "<4f8", 16),
        ("sigma", "<3f8", 48),
        ("catalog_crc32", "<u4", 72),
        ("frame_crc32", "<u4", 76),
        ("colour_rms", "<f4", 80),
        ("residual_rms", "<f4", 84),
        ("stage_times", "<6f4", 88),
        ("method", "u1", 112),
        ("search_flags", "u1", 113),
        ("seeds", "<u2", 114),
        ("verifications", "<u4", 116),
        ("spare", "8u1", 120),
        ("psf_sigma", "<f4", 128),
        ("focal_px", "<f4", 132),
        ("focal_sigma", "<f4", 136),
        ("k1", "<f4", 140),
        ("k1_sigma", "<f4", 144),
        ("optics_rms", "<f4", 148),
        ("optics_stars", "<u2", 152),
        ("optics_flags", "u1", 154),
        ("n_planets", "u1", 155),
        ("focal_scale", "<f4", 156),
        ("spare2", "8u1", 160),
        ("omega_covariance", "<6f8", 168),
        ("utc_epoch", "<f8", 216),
        ("spare3", "24u1", 224),
        ("stars", np.dtype((EXT_STAR, (EXT_MAX_STARS,))), 248),
        ("reason", f"S{EXT_REASON_BYTES}", 248 + 40 * EXT_MAX_STARS),
    ],
    248 + 40 * EXT_MAX_STARS + EXT_REASON_BYTES,
)

STANDARD_LENGTH = 2616  #: 0x0A38, the length COSMOS waits for at EDAC 0x004C
EXT_OFFSET = STANDARD_LENGTH
TOTAL_LENGTH = EXT_OFFSET + EXTENSION.itemsize  #: 4120 bytes

RESULT = _struct(
    [
        ("sequence", "<u4", 0x000),
        ("return_code", "<u4", 0x004),
        ("quaternion", "<4f8", 0x008),
        ("omega", "<3f8", 0x028),
        ("epoch", "<f8", 0x040),
        ("hardware", HARDWARE, 0x048),
        ("statistics", STATISTICS, 0x080),
        ("spare_12c", "<u4", 0x12C),
        ("image", np.dtype((IMAGE, (2,))), 0x130),
        ("ers", ERS, 0x440),
        ("centroid", np.dtype((CENTROID, (2,))), 0x4A8),
        ("matching", np.dtype((MATCHING, (2,))), 0x7E8),
        ("reserved_948", "240u1", 0x948),
        ("ext", EXTENSION, EXT_OFFSET),
    ],
    TOTAL_LENGTH,
)


class MethodCode(IntEnum):
    """How the answer was identified (``ext.method``); ``firmware_model.ident.solver.Method`` names
    each code."""

    NONE = 0
    COLOUR = 1  #: colour consensus
    GEOMETRIC = 2  #: 4-star voting with the triangle fallback
    GEOMETRIC_CONSENSUS = 3  #: the consensus matcher on geometry alone (mono fallback)
    PATTERN = 4  #: scale-free pattern search (uncalibrated optics)
    TRACKING = 5  #: tracking: predicted from the last attitude and rate


class ReturnBits(IntEnum):
    """Return-code bits 0-7: the COSMOS driver's 0-6 (what each means here: docs/ICD.md section
    10.2) and ours in bit 7, which the COSMOS agent's comment calls reserved."""

    IMAGE1_QUALITY = 0x01
    IMAGE2_QUALITY = 0x02
    IMAGE1_SUCCESS = 0x04
    IMAGE2_SUCCESS = 0x08
    FULL_PROCESSING = 0x10
    DETECTOR_IMAGE = 0x20
    CONSISTENT_SOLUTION = 0x40
    STATUS_NOT_OK = 0x80  #: ours: the status (bits 8-15) is not OK, for readers of the low byte alone


class QuaternionOrder(Enum):
    """Element order of the quaternions in the standard structure (``quaternion``,
    ``matching[i].quaternion``); the extension's is always scalar first. The value is the device
    parameter's spelling."""

    SCALAR_FIRST = "scalar_first"  #: [w, x, y, z]: docs/CONVENTIONS.md, the COSMOS agent's reading
    SCALAR_LAST = "scalar_last"  #: [x, y, z, w]: the COSMOS result struct's ``quaternion`` type

    def to_wire(self, q_wxyz: Any) -> np.ndarray:
        """The scalar-first quaternion ``q_wxyz`` in this order."""
        q = np.asarray(q_wxyz, dtype=float)
        return np.roll(q, -1) if self is QuaternionOrder.SCALAR_LAST else q

    def from_wire(self, q: Any) -> np.ndarray:
        """Scalar-first ``[w, x, y, z]`` of a quaternion written in this order."""
        q = np.asarray(q, dtype=float)
        return np.roll(q, 1) if self is QuaternionOrder.SCALAR_LAST else q

    @classmethod
    def of_hardware_status(cls, status: int) -> QuaternionOrder:
        """The order ``hardware.status`` flags (bit 8)."""
        return cls.SCALAR_LAST if status & HW_QUATERNION_SCALAR_LAST else cls.SCALAR_FIRST


class Status(IntEnum):
    """Our status in return-code bits 8-15: why a sequence produced (or did not produce) an attitude."""

    OK = 0
    NO_CATALOG = 1
    NO_FRAME = 2
    NO_SOLVER = 3
    TOO_FEW_STARS = 4
    NO_MATCH = 5
    SOLVER_ERROR = 6
    NO_RESULT = 7  #: no sequence has completed since the device started
    BAD_FRAME = 8  #: the frame is unreadable or does not fit the device's camera
    LOW_CONFIDENCE = 9  #: an attitude, but from a consensus below the eta threshold
    SUN_IN_FOV = 10  #: the Sun inside its exclusion angle: no attitude
    MOON_IN_FOV = 11  #: the Moon inside its exclusion angle: no attitude
    EARTH_IN_FOV = 12  #: the Earth's bright limb inside its exclusion angle: no attitude
    BLINDED = 13  #: the image is blinded (saturated or near full scale) and no attitude says by what
    TERMINATED = 14  #: the sequence was terminated by a GO without COMMAND: no attitude


def make_return_code(status: Status | int, bits: int = 0) -> int:
    """``status`` in bits 8-15, the COSMOS ``bits`` 0-6, and bit 7 set exactly when the status is not OK."""
    not_ok = ReturnBits.STATUS_NOT_OK if int(status) & 0xFF else 0
    return (int(status) & 0xFF) << 8 | not_ok | (bits & 0x7F)


def status_of(return_code: int) -> Status | int:
    value = (return_code >> 8) & 0xFF
    try:
        return Status(value)
    except ValueError:
        return value


#: COMBINATION section mask -> (result address, length). 0x0800 (self-test) is not emulated;
#: 0x1000 (ours) returns the extension region.
SECTIONS: dict[int, tuple[int, int]] = {
    0x0001: (0x000, 4),
    0x0002: (0x004, 4),
    0x0004: (0x008, 32),
    0x0008: (0x028, 24),
    0x0010: (0x040, 8),
    0x0020: (0x048, 56),
    0x0040: (0x080, 172),
    0x0080: (0x130, 784),
    0x0100: (0x440, 104),
    0x0200: (0x4A8, 832),
    0x0400: (0x7E8, 352),
    0x1000: (EXT_OFFSET, EXTENSION.itemsize),
}
SELF_TEST_SECTION = 0x0800


def empty() -> np.ndarray:
    """A zeroed result record (0-d structured array)."""
    return np.zeros((), dtype=RESULT)


def _target(rec: np.ndarray, path: str) -> tuple[Any, str]:
    parts = path.split(".")
    obj = rec
    for part in parts[:-1]:
        obj = obj[int(part)] if part.isdigit() else obj[part]
    return obj, parts[-1]


def build(fields: Mapping[str, Any], sequence: int = 0) -> bytes:
    """Result bytes (TOTAL_LENGTH) from ``fields``: keys are dotted paths into :data:`RESULT`
    (``"return_code"``, ``"quaternion"``, ``"centroid.0.good_stars"``, ``"ext.stars"``), values
    anything numpy can assign. Unknown paths raise KeyError/ValueError. The extension magic and
    version are filled in; ``sequence`` is written unless ``fields`` sets it."""
    rec = empty()
    rec["sequence"] = sequence
    rec["ext"]["magic"] = EXT_MAGIC
    rec["ext"]["version"] = EXT_VERSION
    for path, value in fields.items():
        obj, last = _target(rec, path)
        if last.isdigit():
            obj[int(last)] = value
        else:
            if last not in (obj.dtype.names or ()):
                raise KeyError(f"result has no field {path!r}")
            obj[last] = value
    return rec.tobytes()


def parse(data: bytes) -> np.ndarray:
    """Result record from bytes; ``data`` may be the standard 2616 bytes (extension zeroed) or
    the full TOTAL_LENGTH."""
    if len(data) not in (STANDARD_LENGTH, TOTAL_LENGTH):
        raise ValueError(f"result of {len(data)} bytes; expected {STANDARD_LENGTH} or {TOTAL_LENGTH}")
    buf = bytes(data) + bytes(TOTAL_LENGTH - len(data))
    rec: np.ndarray = np.frombuffer(buf, dtype=RESULT)[0].copy()
    return rec
