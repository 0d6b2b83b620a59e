"""Frame readers: DNG / camera raw (rawpy), FITS (astropy), 16-bit TIFF (tifffile),
``.npy`` with a JSON sidecar, PNG / JPEG images (Pillow), and the link blob of
``frame.frame_to_bytes``.

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
DNG files written by ``ground.sim.frame_writer`` carry the same JSON object in ImageDescription.

PNG and JPEG (``read_image``) hold images that were already demosaiced (one R, G and B
value at every pixel). They are *re-mosaiced* into an RGGB frame: each pixel keeps only the
value of the plane of its Bayer site (R at even row / even column, G at the two G sites, B at
odd row / odd column). The reason is that the pipeline's colour fit models each CFA site as
``channel amplitude x PSF`` sampled at that site; a demosaiced plane sampled at its own site
satisfies that model, so the raw pipeline takes these frames unchanged. The cost is that
3/4 of the R samples and 3/4 of the B samples (and half of the G samples) are not used; they
were interpolated by the demosaicing anyway, mostly from the very sites that are kept.

* Odd width or height: the last column / row is cropped (the pixel grid origin is kept);
  ``metadata["cropped_px"] = [columns, rows]``. Greyscale images become ``MONO`` uncropped.
* RGBA / LA drop alpha; palette, bilevel and CMYK images are converted to RGB (or L).
* Greyscale ``L`` (8-bit) and ``I;16`` (16-bit PNG) become ``MONO``.
* Levels: black 0; white 255 for 8-bit, 65535 for 16-bit greyscale PNG. Pillow reads a
  16-bit *colour* PNG as 8-bit RGB (its high bytes); that is recorded as
  ``metadata["png_bit_depth"] = 16`` with white 255.
* Values are taken as stored: 8-bit images are usually gamma-encoded (sRGB), not linear in
  flux, and JPEG adds compression artefacts; nothing is linearised here.
* EXIF (Exif IFD): ``DateTimeOriginal`` (+ ``SubsecTimeOriginal``) becomes ``timestamp`` in
  UTC (``...Z``). EXIF times are local clock times; with ``OffsetTimeOriginal`` (or ``OffsetTime``) the
  offset is applied, otherwise the time is *assumed* UTC. ``metadata["timestamp_source"]``
  and ``metadata["timestamp_utc_assumed"]`` say which. ``ExposureTime`` becomes ``exposure_s``.
* ``metadata`` also holds ``demosaiced`` (true for colour sources), ``source_format``,
  ``source_mode`` and ``source_size`` ([width, height] before cropping), and, when present,
  ``exif_camera``, ``exif_orientation`` (not applied: pixels stay as stored) and
  ``exif_pixel_size`` (the camera's image size when it differs, i.e. the image was resampled).
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
import warnings
from datetime import UTC, datetime, timezone
from pathlib import Path

import numpy as np

from firmware_model import user_files
from firmware_model.pipeline.raw_frame import Frame, frame_from_bytes, normalise_pattern
from protocol import frame_blob

RAW_EXTENSIONS = {
    ".dng",
    ".cr2",
    ".cr3",
    ".nef",
    ".nrw",
    ".arw",
    ".srf",
    ".sr2",
    ".raf",
    ".orf",
    ".rw2",
    ".pef",
    ".srw",
    ".3fr",
    ".iiq",
    ".mos",
    ".erf",
    ".kdc",
    ".raw",
    ".rwl",
}
FITS_CAMERA_KEYS = ("f", "cx", "cy", "k1", "k2", "k3", "p1", "p2")
#: File suffixes taken for frames when a directory is listed (sidecars and truth files are not).
FRAME_SUFFIXES = RAW_EXTENSIONS | {".fits", ".fit", ".fts", ".tif", ".tiff", ".npy", ".png", ".jpg", ".jpeg"}
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Largest frame read (pixels, 134 Mpx: above a 102-Mpx medium-format sensor); every reader
#: refuses a header claiming more before it decodes or allocates anything (an image bomb: a small
#: file claiming a huge image; docs/bad_input.md).
MAX_FRAME_PIXELS = 1 << 27
#: A TIFF's strips are read this many bytes at a time: tifffile's default reads a whole file in
#: one buffer, whose allocation and release hold the GIL, stalling the device's link thread during
#: a GO (docs/bad_input.md, ``bench/bench_link_during_go.py``)
TIFF_READ_BYTES = 8 << 20
JPEG_SIGNATURE = b"\xff\xd8\xff"
#: Widest or tallest frame (px): the result's fields hold a frame's rows in 16 bits (``good_rows``),
#: so a wider frame is refused before its solve (it raised OverflowError after it).
MAX_FRAME_SIDE = 0xFFFF


class FrameReadError(ValueError):
    """A file could not be read as a frame; the message (``PATH: reason``) says why, and
    :attr:`brief` says it cause first with the file's name only (for the device's 96-byte
    ``ext.reason``, where the path cut the cause off)."""

    def __init__(self, message: str):
        super().__init__(message)
        path, sep, reason = message.partition(": ")
        self.reason = reason if sep else message
        self.name = Path(path).name if sep else ""

    @property
    def brief(self) -> str:
        """``reason (NAME)``: the cause first, then the file's name."""
        return f"{self.reason} ({self.name})" if self.name else self.reason


def read_frame(path) -> Frame:
    """Read any supported frame file (module docstring); raises FrameReadError."""
    path = Path(path)
    why = user_files.problem(path)  # a FIFO, a device or a symlink loop named for what it is
    if why is not None:
        raise FrameReadError(f"{path}: {'a directory, not a frame file' if path.is_dir() else why}")
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        raise FrameReadError(f"{path}: {user_files.os_reason(exc)}") from None
    if not head:
        raise FrameReadError(f"{path}: file is empty")
    return _checked_sides(path, _read_by_kind(path, head))


def _checked_sides(path: Path, frame: Frame) -> Frame:
    """``frame`` when each side is 2..:data:`MAX_FRAME_SIDE` px; else FrameReadError."""
    height, width = frame.pixels.shape[:2]
    if not (2 <= width <= MAX_FRAME_SIDE and 2 <= height <= MAX_FRAME_SIDE):
        raise FrameReadError(
            f"{path}: a {width} x {height} px image: a frame needs 2 to {MAX_FRAME_SIDE} px on each side"
        )
    return frame


def _read_by_kind(path: Path, head: bytes) -> Frame:
    try:
        if head.startswith(b"\x93NUMPY"):
            return read_npy(path)
        if head.startswith(b"SIMPLE  "):
            return read_fits(path)
        if head.startswith(frame_blob.MAGIC):
            return frame_from_bytes(path.read_bytes())
        if head.startswith(PNG_SIGNATURE) or head.startswith(JPEG_SIGNATURE):
            return read_image(path)
        if head[:4] in (b"II*\x00", b"MM\x00*"):
            return read_dng(path) if _tiff_is_raw(path) else read_tiff(path)
        if path.suffix.lower() in RAW_EXTENSIONS:
            return read_dng(path)
    except FrameReadError:
        raise
    except (ValueError, OSError, KeyError, TypeError) as exc:
        raise FrameReadError(f"{path}: {exc}") from exc
    except Exception as exc:  # a damaged file can make an imaging library fail in any way
        raise FrameReadError(f"{path}: damaged or unsupported file ({type(exc).__name__}: {exc})") from exc
    raise FrameReadError(f"{path}: not a recognised frame file (DNG/raw, FITS, TIFF, PNG, JPEG, .npy, frame blob)")


def frame_files(directory) -> list[Path]:
    """Frame files of a directory (by :data:`FRAME_SUFFIXES`), in name order."""
    d = Path(directory)
    if not d.is_dir():
        raise ValueError(f"{d} is not a directory")
    return sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES)


def _tiff_is_raw(path: Path) -> bool:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages.first
        return 50706 in page.tags or int(page.photometric) in (32803, 34892)


def read_dng(path) -> Frame:
    """DNG or camera raw through rawpy: raw_image_visible, CFA pattern from
    raw_colors_visible/color_desc, black_level_per_channel, white_level."""
    import rawpy

    path = Path(path)
    with _libraw_stderr() as said:
        try:
            raw = rawpy.imread(str(path))
        except Exception as exc:  # rawpy raises its own LibRaw* exception hierarchy
            raise FrameReadError(f"{path}: not a readable raw file ({exc}{said()})") from None
    with raw:
        with _libraw_stderr() as said:
            try:
                pixels = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            except Exception as exc:
                raise FrameReadError(f"{path}: raw data could not be unpacked ({exc}{said()})") from None
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
        timestamp = stamp.replace(tzinfo=stamp.tzinfo or UTC).isoformat()
    exposure = extras.get("exposure_s", shutter if shutter > 0 else None)
    return Frame(
        pixels=pixels,
        pattern=pattern,
        black_level=black,
        white_level=white,
        exposure_s=exposure,
        timestamp=timestamp,
        site=extras.get("site"),
        camera=extras.get("camera"),
        metadata=extras.get("metadata") or {},
    )


_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def _libraw_stderr():
    """LibRaw writes its own lines to the process' stderr (``data corrupted at 123456`` for a cut
    DNG) beside the one-line error: they are caught here (file descriptor 2, for the block) and
    ``said()`` gives them as ``; libraw: ...`` for that error's reason. Anything written to stderr
    meanwhile is written back once the block ends, unless the block raised (then it is LibRaw's)."""
    with _STDERR_LOCK:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError, AttributeError):  # no stderr to guard
            yield lambda: ""
            return
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            caught = [b""]

            def said() -> str:
                os.dup2(saved, 2)  # restored before the error is raised and printed
                tmp.seek(0)
                caught[0] = tmp.read(4096)
                text = " ".join(caught[0].decode("utf-8", "replace").split())
                return f"; libraw: {user_files.echo(text, 120)}" if text else ""

            ok = False
            try:
                yield said
                ok = True
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                if ok:
                    tmp.seek(0)
                    rest = tmp.read()
                    if rest:
                        os.write(2, rest)


def _tiff_description_json(path: Path) -> dict:
    """JSON object stored in ImageDescription by ground.sim.frame_writer, or {}."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            desc = tif.pages.first.description
    except Exception:  # not a TIFF container (e.g. CR3): no embedded description
        return {}
    try:
        obj = user_files.loads(desc)
    except (TypeError, ValueError):  # not JSON, or nested too deep: not ours
        return {}
    return obj if isinstance(obj, dict) and obj.get("format") == "st16-frame" else {}


def read_tiff(path) -> Frame:
    """Monochrome integer or float TIFF (e.g. 16-bit night-sky frames); MONO pattern,
    black level 0, white level 2**bits - 1, exposure from ExposureTime if present."""
    import tifffile

    path = Path(path)
    with tifffile.TiffFile(path) as tif:
        if not tif.pages:
            raise FrameReadError(f"{path}: TIFF file holds no image")
        page = tif.pages.first
        if page.dtype is None:  # tifffile has no numpy type for the sample format
            raise FrameReadError(f"{path}: TIFF sample format not supported ({page.bitspersample}-bit samples)")
        _check_size(path, page.shape, page.dtype.itemsize, compressed=page.compression != 1)
        data = page.asarray(buffersize=TIFF_READ_BYTES)
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
    if np.issubdtype(data.dtype, np.integer):
        white = float(np.iinfo(data.dtype).max)
    else:
        finite = data[np.isfinite(data)] if data.size else data
        if not finite.size:  # np.nanmax warned twice (All-NaN slice) and the frame failed later
            raise FrameReadError(f"{path}: TIFF image holds no finite pixel value (all NaN or infinite)")
        white = float(finite.max())
    return Frame(pixels=data, pattern="MONO", black_level=0.0, white_level=white, exposure_s=exposure)


def _check_size(path: Path, shape, itemsize: int, compressed: bool = False) -> None:
    """Refuse an image whose header claims more than :data:`MAX_FRAME_PIXELS` pixels, or (stored
    uncompressed) more bytes than the file holds, before anything is allocated."""
    n = int(np.prod(np.asarray(shape, dtype=np.float64))) if len(shape) else 0
    if n > MAX_FRAME_PIXELS:
        raise FrameReadError(
            f"{path}: header claims a {' x '.join(map(str, shape))} image "
            f"(over {MAX_FRAME_PIXELS} pixels): damaged file?"
        )
    if not compressed and n * itemsize > path.stat().st_size:
        raise FrameReadError(
            f"{path}: header claims {n * itemsize} bytes of pixels, the file holds "
            f"{path.stat().st_size}: truncated or damaged"
        )


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
            for h in hdul:
                shape = tuple(int(h.header.get(f"NAXIS{i}", 0)) for i in range(int(h.header.get("NAXIS", 0)), 0, -1))
                _check_size(path, shape, abs(int(h.header.get("BITPIX", 8))) // 8)
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
    black: float | list[float]
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
        site = {
            "lat_deg": float(hdr["SITELAT"]),
            "lon_deg": float(hdr["SITELONG"]),
            "height_m": float(hdr.get("SITEELEV", 0.0)),
        }
    return Frame(
        pixels=data,
        pattern=pattern,
        black_level=black,
        white_level=float(hdr.get("WHITELVL", default_white)),
        exposure_s=hdr.get("EXPTIME"),
        timestamp=hdr.get("DATE-OBS"),
        site=site,
        camera=camera,
    )


def read_npy(path) -> Frame:
    """``.npy`` array (no pickles) plus optional ``<stem>.json`` sidecar."""
    path = Path(path)
    try:
        with open(path, "rb") as f:  # the header first: nothing allocated for a bomb
            read_header = {
                (1, 0): np.lib.format.read_array_header_1_0,
                (2, 0): np.lib.format.read_array_header_2_0,
            }.get(np.lib.format.read_magic(f))
            if read_header is None:
                raise ValueError("unsupported .npy format version")
            shape, _, dtype = read_header(f)
            _check_size(path, shape, dtype.itemsize)
            f.seek(0)
            data = np.lib.format.read_array(f, allow_pickle=False)
    except FrameReadError:
        raise
    except Exception as exc:
        raise FrameReadError(f"{path}: not a readable .npy array ({exc})") from None
    side = path.with_suffix(".json")
    meta = {}
    if side.exists():
        try:
            meta = user_files.load_json_file(side)
        except user_files.UserFileError as exc:
            raise FrameReadError(f"{side}: sidecar {str(exc).removeprefix(f'{side}: ')}") from None
        if not isinstance(meta, dict):
            raise FrameReadError(f"{side}: sidecar must hold a JSON object")
    return Frame(
        pixels=data,
        pattern=meta.get("pattern", "MONO"),
        black_level=meta.get("black_level", 0.0),
        white_level=meta.get(
            "white_level", float(np.iinfo(data.dtype).max) if np.issubdtype(data.dtype, np.integer) else 65535.0
        ),
        exposure_s=meta.get("exposure_s"),
        timestamp=meta.get("timestamp"),
        site=meta.get("site"),
        camera=meta.get("camera"),
        metadata=meta.get("metadata") or {},
    )


# ---------------------------------------------------------------------------- PNG / JPEG
_EXIF_IFD = 0x8769
_TAG_MAKE, _TAG_MODEL, _TAG_ORIENTATION = 271, 272, 274
_TAG_EXPOSURE_TIME = 33434
_TAG_DATETIME_ORIGINAL, _TAG_SUBSEC_ORIGINAL = 36867, 37521
_TAG_OFFSET_TIME, _TAG_OFFSET_ORIGINAL = 36880, 36881
_GREY_16 = ("I;16", "I;16L", "I;16B", "I;16N")


def read_image(path) -> Frame:
    """Demosaiced PNG / JPEG through Pillow, re-mosaiced to RGGB (module docstring)."""
    from PIL import Image

    path = Path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. DecompressionBombWarning, PNG chunk warnings
            with Image.open(path) as im:
                _check_size(path, (im.size[1], im.size[0]), 1, compressed=True)  # before decoding
                im.load()  # decode now: truncated or corrupt data fails here
                fmt, mode, size = im.format or "image", im.mode, im.size
                exif = _exif_fields(im)
                pixels, pattern, white = _image_pixels(im)
    except FrameReadError as exc:
        raise (exc if str(exc).startswith(str(path)) else FrameReadError(f"{path}: {exc}")) from None
    except Exception as exc:  # Pillow raises OSError, SyntaxError, EOFError, struct.error, ...
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if isinstance(exc, Image.UnidentifiedImageError):
            reason = "Pillow cannot identify the image data"  # its message repeats the path
        raise FrameReadError(f"{path}: not a readable PNG/JPEG image ({reason})") from None
    metadata = {
        "demosaiced": pattern != "MONO",
        "source_format": fmt,
        "source_mode": mode,
        "source_size": [int(size[0]), int(size[1])],
    }
    if fmt == "PNG" and pattern != "MONO" and _png_bit_depth(path) == 16:
        metadata["png_bit_depth"] = 16  # Pillow keeps only the high bytes of 16-bit colour
    if pattern != "MONO":
        h, w = pixels.shape
        crop_c, crop_r = w % 2, h % 2
        if crop_c or crop_r:
            pixels = pixels[: h - crop_r, : w - crop_c]
            metadata["cropped_px"] = [crop_c, crop_r]
    if pixels.size == 0:
        raise FrameReadError(f"{path}: image of {size[0]} x {size[1]} px is too small for a frame")
    timestamp, exposure = exif.pop("timestamp", None), exif.pop("exposure_s", None)
    metadata.update(exif)
    return Frame(
        pixels=np.ascontiguousarray(pixels),
        pattern=pattern,
        black_level=0.0,
        white_level=white,
        exposure_s=exposure,
        timestamp=timestamp,
        metadata=metadata,
    )


def _image_pixels(im) -> tuple[np.ndarray, str, float]:
    """(2-D pixels, pattern, white level) of an opened Pillow image."""
    mode = im.mode
    if mode in _GREY_16:
        return np.asarray(im).astype(np.uint16), "MONO", 65535.0
    if mode == "I":  # 32-bit integer greyscale (older Pillow for 16-bit PNG)
        data = np.asarray(im)
        if data.min() < 0 or data.max() > 65535:
            raise FrameReadError("32-bit greyscale image with values outside 0..65535 is not supported")
        return data.astype(np.uint16), "MONO", 65535.0
    if mode in ("L", "LA", "1"):
        return np.asarray(im.convert("L"), dtype=np.uint8), "MONO", 255.0
    if mode == "P":
        im = im.convert("RGBA" if "transparency" in im.info else "RGB")
    elif mode == "PA":
        im = im.convert("RGBA")
    if im.mode not in ("RGB", "RGBA"):
        try:
            im = im.convert("RGB")  # CMYK, YCbCr, LAB, RGBX, ...
        except Exception as exc:
            raise FrameReadError(f"image mode {mode} cannot be converted to RGB ({exc})") from None
    rgb = np.asarray(im, dtype=np.uint8)[:, :, :3]  # RGBA drops alpha
    return remosaic_rggb(rgb), "RGGB", 255.0


def remosaic_rggb(rgb: np.ndarray) -> np.ndarray:
    """RGGB mosaic (H, W) of an (H, W, 3) demosaiced image: each pixel keeps its site's plane."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] < 3:
        raise ValueError(f"expected an (H, W, 3) image, got shape {rgb.shape}")
    out = np.empty(rgb.shape[:2], dtype=rgb.dtype)
    out[0::2, 0::2] = rgb[0::2, 0::2, 0]
    out[0::2, 1::2] = rgb[0::2, 1::2, 1]
    out[1::2, 0::2] = rgb[1::2, 0::2, 1]
    out[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return out


def _png_bit_depth(path: Path) -> int | None:
    """Bit depth from a PNG's IHDR (byte 24), or None."""
    with open(path, "rb") as fh:
        head = fh.read(25)
    return head[24] if len(head) == 25 and head[12:16] == b"IHDR" else None


def _exif_fields(im) -> dict:
    """timestamp / exposure_s / metadata entries from an image's EXIF (empty when none)."""
    out: dict = {}
    try:
        exif = im.getexif()
        sub = exif.get_ifd(_EXIF_IFD) if exif else {}
    except Exception:  # malformed EXIF is not a reason to reject the pixels
        return {"exif_unreadable": True}
    make, model = (str(exif.get(t, "")).strip("\x00 ") for t in (_TAG_MAKE, _TAG_MODEL))
    if make or model:
        out["exif_camera"] = model if make and model.startswith(make) else " ".join(x for x in (make, model) if x)
    dims = [sub.get(40962), sub.get(40963)]  # PixelXDimension / PixelYDimension of the camera image
    if all(isinstance(d, int) and d > 0 for d in dims) and tuple(dims) != tuple(im.size):
        out["exif_pixel_size"] = dims  # the image was resampled (e.g. downscaled) after capture
    orientation = exif.get(_TAG_ORIENTATION)
    if orientation not in (None, 1):
        out["exif_orientation"] = int(orientation)
    exposure = _exif_number(sub.get(_TAG_EXPOSURE_TIME))
    if exposure is not None and np.isfinite(exposure) and exposure >= 0:
        out["exposure_s"] = exposure
    stamp = sub.get(_TAG_DATETIME_ORIGINAL)
    if stamp:
        try:
            t = datetime.strptime(str(stamp).strip("\x00 "), "%Y:%m:%d %H:%M:%S")
        except ValueError:
            out["exif_datetime_unparsed"] = str(stamp)
            return out
        subsec = str(sub.get(_TAG_SUBSEC_ORIGINAL, "")).strip("\x00 ")
        if subsec.isdigit():
            t = t.replace(microsecond=int(subsec[:6].ljust(6, "0")))
        offset = str(sub.get(_TAG_OFFSET_ORIGINAL) or sub.get(_TAG_OFFSET_TIME) or "").strip("\x00 ")
        tz = _parse_offset(offset)
        out["timestamp_source"] = "EXIF DateTimeOriginal"
        if tz is None:
            out["timestamp"] = _utc_iso(t)
            out["timestamp_utc_assumed"] = True
        else:
            out["timestamp"] = _utc_iso(t.replace(tzinfo=tz).astimezone(UTC))
            out["timestamp_utc_assumed"] = False
            out["exif_time_offset"] = offset
    return out


def _utc_iso(t: datetime) -> str:
    """ISO-8601 UTC with a ``Z`` suffix (astropy ``Time`` parses ``Z`` but not ``+00:00``)."""
    return t.replace(tzinfo=None).isoformat() + "Z"


def _exif_number(value) -> float | None:
    if value is None:
        return None
    try:
        if isinstance(value, tuple) and len(value) == 2:
            return value[0] / value[1] if value[1] else None
        return float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None


def _parse_offset(text: str):
    """timezone of an EXIF offset string ``+HH:MM`` / ``-HH:MM``, or None."""
    from datetime import timedelta

    if len(text) == 6 and text[0] in "+-" and text[3] == ":" and text[1:3].isdigit() and text[4:6].isdigit():
        minutes = int(text[1:3]) * 60 + int(text[4:6])
        if minutes < 24 * 60:
            return timezone((1 if text[0] == "+" else -1) * timedelta(minutes=minutes))
    return None
