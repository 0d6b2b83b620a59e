"""Raw sensor frame: pixels in DN, colour-filter-array pattern, levels and metadata.

* ``pixels[row, col]``; the centre of pixel ``(r, c)`` is at ``(x, y) = (c, r)``.
* CFA pattern named by the 2x2 block at the top-left pixel, row-major (``RGGB`` means
  ``(0,0)=R, (0,1)=G, (1,0)=G, (1,1)=B``), or ``MONO``.
* ``black_level`` holds four values, one per position of the 2x2 block in row-major order
  (``black_level[2 * (r % 2) + (c % 2)]``); a mono frame has four equal values.
* Signal above black is ``pixels - black``; ``white_level`` is the largest valid raw DN.

Serialisation for upload over the link (``frame_to_bytes`` / ``frame_from_bytes``): the blob
format of :mod:`protocol.frame_blob` (declared there once).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from protocol import frame_blob

PATTERNS = frame_blob.PATTERNS
#: Channel codes used by detection and fitting.
RED, GREEN, BLUE = 0, 1, 2
_LETTER_CODE = {"R": RED, "G": GREEN, "B": BLUE}


def normalise_pattern(pattern: str) -> str:
    """Upper-case CFA pattern name, validated against ``PATTERNS``."""
    if not isinstance(pattern, str):
        raise ValueError(f"CFA pattern must be a string, got {type(pattern).__name__}")
    p = pattern.strip().upper()
    if p in ("MONO", "MONOCHROME", "NONE", ""):
        return "MONO"
    if p not in PATTERNS:
        raise ValueError(f"unknown CFA pattern {pattern!r}; expected one of {', '.join(PATTERNS)}")
    return p


def pattern_codes(pattern: str) -> np.ndarray:
    """2x2 int array of channel codes (RED/GREEN/BLUE) of a CFA pattern; MONO gives all GREEN."""
    p = normalise_pattern(pattern)
    if p == "MONO":
        return np.full((2, 2), GREEN, dtype=np.int8)
    return np.array([_LETTER_CODE[ch] for ch in p], dtype=np.int8).reshape(2, 2)


@dataclass
class Frame:
    """One raw frame (see module docstring for the conventions).

    ``exposure_s`` in seconds; ``timestamp`` UTC ISO-8601 string; ``site`` an optional dict
    (``lat_deg``, ``lon_deg``, ``height_m``); ``camera`` an optional ``CameraModel.to_dict()``;
    ``metadata`` free-form JSON-serialisable extras.
    """

    pixels: np.ndarray
    pattern: str = "MONO"
    black_level: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    white_level: float = 4095.0
    exposure_s: float | None = None
    timestamp: str | None = None
    site: dict | None = None
    camera: dict | None = None
    metadata: dict = field(default_factory=dict)

    if TYPE_CHECKING:
        # What the generated __init__ accepts: one black level or four (__post_init__ stores four
        # floats); declared for the type checker only, the dataclass writes the real one.
        def __init__(
            self,
            pixels: np.ndarray,
            pattern: str = ...,
            black_level: float | Sequence[float] = ...,
            white_level: float = ...,
            exposure_s: float | None = ...,
            timestamp: str | None = ...,
            site: dict | None = ...,
            camera: dict | None = ...,
            metadata: dict = ...,
        ) -> None: ...

    def __post_init__(self):
        self.pattern = normalise_pattern(self.pattern)
        px = np.asarray(self.pixels)
        if px.ndim != 2:
            raise ValueError(f"frame pixels must be a 2-D array, got shape {px.shape}")
        if px.size == 0:
            raise ValueError("frame has no pixels")
        if not (np.issubdtype(px.dtype, np.integer) or np.issubdtype(px.dtype, np.floating)):
            raise ValueError(f"frame pixels must be numeric, got dtype {px.dtype}")
        if np.issubdtype(px.dtype, np.floating):
            bad = int(np.count_nonzero(~np.isfinite(px)))
            if bad:
                raise ValueError(f"frame contains {bad} non-finite (NaN/inf) pixels")
        if self.pattern != "MONO" and (px.shape[0] % 2 or px.shape[1] % 2):
            raise ValueError(f"a {self.pattern} frame needs even dimensions, got {px.shape[1]} x {px.shape[0]} (W x H)")
        self.pixels = px
        bl = np.atleast_1d(np.asarray(self.black_level, dtype=float))
        if bl.size == 1:
            bl = np.repeat(bl, 4)
        if bl.size != 4 or not np.all(np.isfinite(bl)):
            raise ValueError(f"black_level must be 1 or 4 finite values, got {self.black_level!r}")
        b0, b1, b2, b3 = (float(b) for b in bl)
        self.black_level = (b0, b1, b2, b3)
        self.white_level = float(self.white_level)
        if not np.isfinite(self.white_level) or self.white_level <= max(self.black_level):
            raise ValueError(f"white level {self.white_level} must exceed the black levels {self.black_level}")
        if self.exposure_s is not None:
            self.exposure_s = float(self.exposure_s)
            if not np.isfinite(self.exposure_s) or self.exposure_s < 0:
                raise ValueError(f"exposure must be a non-negative number of seconds, got {self.exposure_s}")

    # ------------------------------------------------------------------ geometry
    @property
    def height(self) -> int:
        return int(self.pixels.shape[0])

    @property
    def width(self) -> int:
        return int(self.pixels.shape[1])

    @property
    def is_mono(self) -> bool:
        return self.pattern == "MONO"

    def channel_map(self) -> np.ndarray:
        """Per-pixel channel code array (RED/GREEN/BLUE; all GREEN for MONO), int8, (H, W)."""
        codes = pattern_codes(self.pattern)
        return np.tile(codes, (self.height // 2 + 1, self.width // 2 + 1))[: self.height, : self.width]

    def black_map(self) -> np.ndarray:
        """Per-pixel black level (DN), float, (H, W)."""
        bl = np.asarray(self.black_level, dtype=float).reshape(2, 2)
        return np.tile(bl, (self.height // 2 + 1, self.width // 2 + 1))[: self.height, : self.width]

    def signal(self) -> np.ndarray:
        """Pixels minus black level, float64 DN."""
        return self.pixels.astype(np.float64) - self.black_map()

    def saturated_mask(self) -> np.ndarray:
        """True where the raw value is at or above the white level."""
        return self.pixels >= self.white_level


def frame_to_bytes(frame: Frame) -> bytes:
    """Serialise a frame with integer pixels in [0, 65535] (the :mod:`protocol.frame_blob` layout)."""
    px = frame.pixels
    if not np.issubdtype(px.dtype, np.integer):
        if not np.all(px == np.round(px)):
            raise ValueError("only integer-valued frames can be serialised")
    if px.min() < 0 or px.max() > 65535:
        raise ValueError("pixel values must lie in [0, 65535] to serialise as uint16")
    extras = {"timestamp": frame.timestamp, "site": frame.site, "camera": frame.camera, "metadata": frame.metadata}
    exposure = float("nan") if frame.exposure_s is None else frame.exposure_s
    b0, b1, b2, b3 = (float(v) for v in frame.black_level)
    black = (b0, b1, b2, b3)
    return frame_blob.pack(
        frame_blob.FrameBlob(
            frame.pattern,
            black,
            frame.white_level,
            exposure,
            json.dumps(extras, separators=(",", ":")).encode("utf-8"),
            px,
        )
    )


def frame_from_bytes(data: bytes) -> Frame:
    """Inverse of ``frame_to_bytes``; raises ValueError on any inconsistency."""
    blob = frame_blob.unpack(data)
    try:
        extras = json.loads(blob.extras_json.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"frame blob metadata is not valid JSON: {exc}") from None
    exposure = blob.exposure
    return Frame(
        pixels=blob.pixels,
        pattern=blob.pattern,
        black_level=blob.black,
        white_level=blob.white,
        exposure_s=None if np.isnan(exposure) else exposure,
        timestamp=extras.get("timestamp"),
        site=extras.get("site"),
        camera=extras.get("camera"),
        metadata=extras.get("metadata") or {},
    )
