"""Frame readers: DNG / camera raw (rawpy), FITS (astropy), 16-bit TIFF (tifffile),
``.npy`` with a JSON sidecar, and the link blob of ``frame.frame_to_bytes``.

``read_frame(path)`` sniffs the file's first bytes (extension only for camera-raw formats
without a distinctive signature) and raises ``FrameReadError`` (a ValueError) with the
reason for anything that is not a readable frame.

FITS keywords (primary HDU or first image extension, 2-D integer or float data):

=========== =====================================================================
BAYERPAT    CFA pattern (RGGB, BGGR, GRBG, GBRG, MONO); absent means MONO
XBAYROFF    optional column offset of the pattern (odd value swaps columns)
YBAYROFF    optional row offset of the pattern (odd value swaps rows)
BLACKLVL    black level (DN) for all positions, or BLACK0..BLACK3 per 2x2 position
WHITELVL    white (saturation) level in DN; default 2**BITPIX-1 or 65535 for floats
EXPTIME     exposure in seconds
DATE-OBS    UTC ISO-8601 timestamp
SITELAT     site latitude (deg), SITELONG longitude (deg, east positive), SITEELEV (m)
CAM_F ...   camera model: CAM_F, CAM_CX, CAM_CY, CAM_K1, CAM_K2, CAM_K3, CAM_P1, CAM_P2
=========== =====================================================================

The ``.npy`` sidecar is ``<stem>.json`` beside the array: ``{"pattern", "black_level",
"white_level", "exposure_s", "timestamp", "site", "camera", "metadata"}`` (all optional).
DNG files written by ``ground.frame_writer`` carry the same JSON object in ImageDescription.
"""

from __future__ import annotations

import json
import warnings
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from firmware_model.frame import Frame, frame_from_bytes, normalise_pattern

RAW_EXTENSIONS = {
    ".dng", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf",
    ".rw2", ".pef", ".srw", ".3fr", ".iiq", ".mos", ".erf", ".kdc", ".raw", ".rwl",
}
FITS_CAMERA_KEYS = ("f", "cx", "cy", "k1", "k2", "k3", "p1", "p2")
#: File suffixes taken for frames when a directory is listed (sidecars and truth files are not).
FRAME_SUFFIXES = RAW_EXTENSIONS | {".fits", ".fit", ".fts", ".tif", ".tiff", ".npy"}


class FrameReadError(ValueError):
    """A file could not be read as a frame; the message says why."""


def read_frame(path) -> Frame:
    """Read any supported frame file (module docstring); raises FrameReadError."""
    path = Path(path)
    if not path.is_file():
        raise FrameReadError(f"{path}: no such file")
    with open(path, "rb") as fh:
        head = fh.read(16)
    if not head:
        raise FrameReadError(f"{path}: file is empty")
    try:
        if head.startswith(b"\x93NUMPY"):
            return read_npy(path)
        if head.startswith(b"SIMPLE  "):
            return read_fits(path)
        if head.startswith(b"STFR"):
            return frame_from_bytes(path.read_bytes())
        if head[:4] in (b"II*\x00", b"MM\x00*"):
            return read_dng(path) if _tiff_is_raw(path) else read_tiff(path)
        if path.suffix.lower() in RAW_EXTENSIONS:
            return read_dng(path)
    except FrameReadError:
        raise
    except (ValueError, OSError, KeyError, TypeError) as exc:
        raise FrameReadError(f"{path}: {exc}") from exc
    raise FrameReadError(f"{path}: not a recognised frame file (DNG/raw, FITS, TIFF, .npy, frame blob)")


def frame_files(directory) -> list[Path]:
    """Frame files of a directory (by :data:`FRAME_SUFFIXES`), in name order."""
    d = Path(directory)
    if not d.is_dir():
        raise ValueError(f"{d} is not a directory")
    return sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES)


def _tiff_is_raw(path: Path) -> bool:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        return 50706 in page.tags or int(page.photometric) in (32803, 34892)


def read_dng(path) -> Frame:
    """DNG or camera raw through rawpy: raw_image_visible, CFA pattern from
    raw_colors_visible/color_desc, black_level_per_channel, white_level."""
    import rawpy

    path = Path(path)
    try:
        raw = rawpy.imread(str(path))
    except Exception as exc:  # rawpy raises its own LibRaw* exception hierarchy
        raise FrameReadError(f"{path}: not a readable raw file ({exc})") from None
    with raw:
        try:
            pixels = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
        except Exception as exc:
            raise FrameReadError(f"{path}: raw data could not be unpacked ({exc})") from None
        desc = raw.color_desc.decode("ascii", "replace")
        colors = np.asarray(raw.raw_colors_visible[:2, :2])
        blpc = list(raw.black_level_per_channel)
        if raw.num_colors == 1:
            pattern = "MONO"
            black = [float(blpc[0])] * 4
        else:
            letters = "".join(desc[c] for c in colors.ravel())
            if set(letters) - set("RGB"):
                raise FrameReadError(f"{path}: unsupported CFA colours {letters!r} (only RGB Bayer)")
            pattern = normalise_pattern(letters)
            black = [float(blpc[c]) for c in colors.ravel()]
        white = float(raw.white_level)
        shutter = float(raw.other.shutter_speed)
        stamp = raw.other.timestamp
    extras = _tiff_description_json(path)
    timestamp = extras.get("timestamp")
    if timestamp is None and isinstance(stamp, datetime) and stamp.year > 1970:
        timestamp = stamp.replace(tzinfo=stamp.tzinfo or timezone.utc).isoformat()
    exposure = extras.get("exposure_s", shutter if shutter > 0 else None)
    return Frame(
        pixels=pixels, pattern=pattern, black_level=black, white_level=white, exposure_s=exposure,
        timestamp=timestamp, site=extras.get("site"), camera=extras.get("camera"),
        metadata=extras.get("metadata") or {},
    )


def _tiff_description_json(path: Path) -> dict:
    """JSON object stored in ImageDescription by ground.frame_writer, or {}."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            desc = tif.pages[0].description
    except Exception:  # not a TIFF container (e.g. CR3): no embedded description
        return {}
    try:
        obj = json.loads(desc)
    except (TypeError, json.JSONDecodeError):
        return {}
    return obj if isinstance(obj, dict) and obj.get("format") == "st16-frame" else {}


def read_tiff(path) -> Frame:
    """Monochrome integer or float TIFF (e.g. 16-bit night-sky frames); MONO pattern,
    black level 0, white level 2**bits - 1, exposure from ExposureTime if present."""
    import tifffile

    path = Path(path)
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        data = page.asarray()
        exp_tag = page.tags.get(33434)
        exif = page.tags.get(34665)
        if exp_tag is None and exif is not None and isinstance(exif.value, dict):
            exposure = exif.value.get("ExposureTime")
        else:
            exposure = exp_tag.value if exp_tag is not None else None
    if data.ndim != 2:
        raise FrameReadError(f"{path}: TIFF image has shape {data.shape}; a raw mono frame must be 2-D")
    if isinstance(exposure, tuple):
        exposure = exposure[0] / exposure[1] if exposure[1] else None
    white = float(np.iinfo(data.dtype).max) if np.issubdtype(data.dtype, np.integer) else float(np.nanmax(data))
    return Frame(pixels=data, pattern="MONO", black_level=0.0, white_level=white, exposure_s=exposure)


def read_fits(path) -> Frame:
    """FITS through astropy with the keywords in the module docstring."""
    from astropy.io import fits

    path = Path(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            hdul = fits.open(path, memmap=False)
        except Exception as exc:
            raise FrameReadError(f"{path}: not a readable FITS file ({exc})") from None
        with hdul:
            hdu = next((h for h in hdul if h.data is not None and getattr(h.data, "ndim", 0) == 2), None)
            if hdu is None:
                raise FrameReadError(f"{path}: FITS file has no 2-D image")
            try:
                data = np.array(hdu.data)
            except Exception as exc:
                raise FrameReadError(f"{path}: FITS image data unreadable ({exc})") from None
            hdr = hdu.header
    pattern = normalise_pattern(str(hdr.get("BAYERPAT", "MONO")))
    if pattern != "MONO":
        letters = np.array(list(pattern)).reshape(2, 2)
        letters = np.roll(letters, (-int(hdr.get("YBAYROFF", 0)) % 2, -int(hdr.get("XBAYROFF", 0)) % 2), axis=(0, 1))
        pattern = "".join(letters.ravel())
    if all(f"BLACK{i}" in hdr for i in range(4)):
        black = [float(hdr[f"BLACK{i}"]) for i in range(4)]
    else:
        black = float(hdr.get("BLACKLVL", 0.0))
    if np.issubdtype(data.dtype, np.integer):
        default_white = float(np.iinfo(data.dtype).max)
    else:
        default_white = 65535.0
    camera = None
    if "CAM_F" in hdr:
        camera = {"width": data.shape[1], "height": data.shape[0]}
        camera.update({k: float(hdr[f"CAM_{k.upper()}"]) for k in FITS_CAMERA_KEYS if f"CAM_{k.upper()}" in hdr})
    site = None
    if "SITELAT" in hdr and "SITELONG" in hdr:
        site = {"lat_deg": float(hdr["SITELAT"]), "lon_deg": float(hdr["SITELONG"]),
                "height_m": float(hdr.get("SITEELEV", 0.0))}
    return Frame(
        pixels=data, pattern=pattern, black_level=black, white_level=float(hdr.get("WHITELVL", default_white)),
        exposure_s=hdr.get("EXPTIME"), timestamp=hdr.get("DATE-OBS"), site=site, camera=camera,
    )


def read_npy(path) -> Frame:
    """``.npy`` array (no pickles) plus optional ``<stem>.json`` sidecar."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise FrameReadError(f"{path}: not a readable .npy array ({exc})") from None
    side = path.with_suffix(".json")
    meta = {}
    if side.is_file():
        try:
            meta = json.loads(side.read_text())
        except json.JSONDecodeError as exc:
            raise FrameReadError(f"{side}: sidecar is not valid JSON ({exc})") from None
        if not isinstance(meta, dict):
            raise FrameReadError(f"{side}: sidecar must hold a JSON object")
    return Frame(
        pixels=data,
        pattern=meta.get("pattern", "MONO"),
        black_level=meta.get("black_level", 0.0),
        white_level=meta.get("white_level", float(np.iinfo(data.dtype).max) if np.issubdtype(data.dtype, np.integer) else 65535.0),
        exposure_s=meta.get("exposure_s"),
        timestamp=meta.get("timestamp"),
        site=meta.get("site"),
        camera=meta.get("camera"),
        metadata=meta.get("metadata") or {},
    )
