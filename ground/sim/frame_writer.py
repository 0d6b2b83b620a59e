"""Frame writers: DNG (tifffile; rawpy reads it back bit-exactly), FITS (astropy) and
``.npy`` + JSON sidecar, the formats ``firmware_model.pipeline.frame_readers.read_frame`` reads.

DNG layout: one uncompressed 16-bit IFD0 (NewSubfileType 0) holding the raw data; a CFA
frame uses PhotometricInterpretation CFA (32803) with CFARepeatPatternDim 2x2 and
CFAPattern, a mono frame LinearRaw (34892). Black levels go in BlackLevel (2x2 repeat),
the white level in WhiteLevel (e.g. 4095 for 12-bit data in the 16-bit container),
exposure in ExposureTime, and the frame's timestamp/site/camera/metadata as a JSON object
in ImageDescription.
"""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import numpy as np

from firmware_model.pipeline.frame_readers import FITS_CAMERA_KEYS
from firmware_model.pipeline.raw_frame import Frame
from ground.atomic_write import atomic_path

_CFA_CODES = {"R": 0, "G": 1, "B": 2}


def _uint16_pixels(frame: Frame) -> np.ndarray:
    px = frame.pixels
    if np.issubdtype(px.dtype, np.floating) and not np.all(px == np.round(px)):
        raise ValueError("DNG needs integer raw values")
    if px.min() < 0 or px.max() > 65535:
        raise ValueError("raw values must lie in [0, 65535] for a 16-bit container")
    return np.ascontiguousarray(px, dtype=np.uint16)


def _description(frame: Frame) -> str:
    return json.dumps(
        {
            "format": "st16-frame",
            "exposure_s": frame.exposure_s,
            "timestamp": frame.timestamp,
            "site": frame.site,
            "camera": frame.camera,
            "metadata": frame.metadata,
        }
    )


def write_dng(frame: Frame, path) -> Path:
    """Write ``frame`` as a DNG; returns the path."""
    import tifffile

    path = Path(path)
    data = _uint16_pixels(frame)
    mono = frame.is_mono
    tags = [
        (271, "s", 0, "ST16", True),  # Make: LibRaw needs it to accept a minimal DNG
        (272, "s", 0, "colour-st16 emulator", True),  # Model
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, "colour-st16 emulator", True),  # UniqueCameraModel
        (50717, "I", 1, int(round(frame.white_level)), True),  # WhiteLevel
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1 = D65
    ]
    black = [int(round(b)) for b in frame.black_level]
    if mono:
        tags += [(50714, "I", 1, (black[0],), True), (50721, "2i", 3, (1, 1) * 3, True)]
    else:
        tags += [
            (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
            (33422, "B", 4, tuple(_CFA_CODES[c] for c in frame.pattern), True),  # CFAPattern
            (50710, "B", 3, (0, 1, 2), True),  # CFAPlaneColor
            (50711, "H", 1, 1, True),  # CFALayout rectangular
            (50713, "H", 2, (2, 2), True),  # BlackLevelRepeatDim
            (50714, "I", 4, tuple(black), True),  # BlackLevel
            (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),  # identity ColorMatrix1
        ]
    if frame.exposure_s is not None:
        fr = Fraction(frame.exposure_s).limit_denominator(1_000_000)
        tags.append((33434, "2I", 1, (fr.numerator, fr.denominator), True))
    with atomic_path(path) as tmp:
        tifffile.imwrite(
            tmp,
            data,
            photometric="minisblack" if mono else 32803,
            extratags=tags,
            description=_description(frame),
            metadata=None,
            subfiletype=0,
        )
        if mono:  # tifffile refuses LinearRaw with one sample; patch the tag in place
            with tifffile.TiffFile(tmp, mode="r+") as tif:  # binary: tifffile appends the "b"
                tif.pages.first.tags["PhotometricInterpretation"].overwrite(34892)
    return path


def write_fits(frame: Frame, path) -> Path:
    """Write ``frame`` as FITS with the keywords documented in firmware_model.pipeline.frame_readers."""
    from astropy.io import fits

    path = Path(path)
    hdu = fits.PrimaryHDU(_uint16_pixels(frame))
    h = hdu.header
    h["BAYERPAT"] = (frame.pattern, "CFA pattern of the top-left 2x2 block")
    for i, b in enumerate(frame.black_level):
        h[f"BLACK{i}"] = (b, f"black level DN, 2x2 position {i}")
    h["WHITELVL"] = (frame.white_level, "white level DN")
    if frame.exposure_s is not None:
        h["EXPTIME"] = (frame.exposure_s, "exposure [s]")
    if frame.timestamp:
        h["DATE-OBS"] = (frame.timestamp, "UTC")
    if frame.site:
        h["SITELAT"] = frame.site.get("lat_deg", 0.0)
        h["SITELONG"] = frame.site.get("lon_deg", 0.0)
        h["SITEELEV"] = frame.site.get("height_m", 0.0)
    if frame.camera:
        for k in FITS_CAMERA_KEYS:
            if k in frame.camera:
                h[f"CAM_{k.upper()}"] = float(frame.camera[k])
    with atomic_path(path) as tmp:
        hdu.writeto(tmp, overwrite=True)
    return path


def write_npy(frame: Frame, path) -> Path:
    """Write ``frame`` as ``path`` (.npy) plus the ``<stem>.json`` sidecar."""
    path = Path(path)
    side = {
        "pattern": frame.pattern,
        "black_level": list(frame.black_level),
        "white_level": frame.white_level,
        "exposure_s": frame.exposure_s,
        "timestamp": frame.timestamp,
        "site": frame.site,
        "camera": frame.camera,
        "metadata": frame.metadata,
    }
    with atomic_path(path.with_suffix(".json")) as side_tmp:  # replaced after the pixels, not without them
        side_tmp.write_text(json.dumps(side, indent=1))
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.save(f, frame.pixels, allow_pickle=False)
    return path


def truth_path_for(frame_path) -> Path:
    """Where the truth of a rendered frame lives: ``NAME.truth.json`` beside ``NAME.ext``."""
    p = Path(frame_path)
    return p.with_name(p.stem + ".truth.json")


def write_rendered(rendered, path) -> Path:
    """Write a ``sensor_sim.RenderResult``: the frame (by extension) and its truth beside it; the
    truth replaces the previous one only once the frame has."""
    with atomic_path(truth_path_for(path)) as tmp:
        tmp.write_text(json.dumps(rendered.truth, indent=1))
        return write_frame(rendered.frame, path)


def write_frame(frame: Frame, path) -> Path:
    """Write by extension: .dng, .fits/.fit/.fts, .npy."""
    suffix = Path(path).suffix.lower()
    if suffix == ".dng":
        return write_dng(frame, path)
    if suffix in (".fits", ".fit", ".fts"):
        return write_fits(frame, path)
    if suffix == ".npy":
        return write_npy(frame, path)
    raise ValueError(f"cannot write frames as {suffix!r}; use .dng, .fits or .npy")
