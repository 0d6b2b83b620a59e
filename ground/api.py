"""Solve one image from Python: the device pipeline in-process, one call.

    from ground.api import solve_image
    s = solve_image("frame.tiff", fov_deg=11.4)          # or camera=CameraModel(...), catalog=...
    if s.solved:
        print(s.status, s.ra_deg, s.dec_deg, s.roll_deg, s.sigma_arcsec)
        s.wcs().to_header()                                # astropy WCS, TAN-SIP (docs/wcs.md)

``image`` is a path (every format the pipeline reads: DNG/raw, FITS, TIFF, PNG/JPEG, .npy, frame
blobs) or an array: (H, W) a mono frame, (H, W, 3) a demosaiced RGB image (saturation at the
integer type's maximum). ``camera`` is a
:class:`CameraModel`; without one, ``fov_deg`` (horizontal field of view, deg) gives a pinhole
camera at the array centre and the pipeline's optics search and fit absorb its error. ``catalog``
is an :class:`OnboardCatalog` or a catalog image path (``st16-ground catalog build``); without
one, a catalog for the field is built from the bundled Hipparcos (``CatalogDesign.for_field``)
with its pattern index, once per field: kept for the next call in the process and on disk in the
user's cache directory (:func:`catalog_for_field`). ``params`` are the pipeline's parameters (the
device's slot-2 settings).

The first solve in a process loads the compiled kernels (``replay.warm_up_kernels``); its record's
``timings_s`` count that as ``compile`` and the catalog's building or loading as ``catalog``, and
their ``total`` is the whole time the call took past reading the image.
"""

from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.onboard import OnboardCatalog
    from firmware_model.pipeline.raw_frame import Frame
    from firmware_model.pipeline.run import PipelineOutput, PipelineParams

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class IdentifiedStar:
    """One detection: position (px, docs/CONVENTIONS.md), flux (DN), colour ratios, and its
    catalog star number (HIP or HR) with the residual (arcsec) when it was matched."""

    x: float
    y: float
    flux: float
    rg: float
    bg: float
    catalog_id: int | None
    residual_arcsec: float | None


@dataclass(frozen=True)
class SolvedImage:
    """The answer for one image. ``status``: OK (high confidence), LOW_CONFIDENCE (an attitude to
    use with care), or why there is none (NO_MATCH, TOO_FEW_STARS, ...); ``q_icrs_to_sensor``
    scalar first, ``v_sensor = A(q) v_icrs``; ``sigma_arcsec`` 1-sigma about the sensor x, y, z
    axes; ``camera`` the camera the answer was found with, its fitted focal length and k1 applied;
    ``record`` the full result record (the fields ``st16-ground solve --json`` prints)."""

    status: str
    reason: str
    q_icrs_to_sensor: tuple[float, float, float, float] | None
    ra_deg: float | None
    dec_deg: float | None
    roll_deg: float | None
    sigma_arcsec: tuple[float, float, float] | None
    camera: CameraModel
    stars: tuple[IdentifiedStar, ...]
    record: dict[str, Any]

    @property
    def solved(self) -> bool:
        """An attitude was found (OK or LOW_CONFIDENCE)."""
        return self.q_icrs_to_sensor is not None

    def wcs(self):
        """astropy ``WCS`` (TAN-SIP) of the image; :class:`~ground.analysis.wcs.WcsError` when unsolved."""
        from ground.analysis.wcs import frame_wcs

        return frame_wcs(self.camera, self.q_icrs_to_sensor)[0]


def solve_image(
    image: str | Path | np.ndarray,
    camera: CameraModel | None = None,
    catalog: OnboardCatalog | str | Path | None = None,
    fov_deg: float | None = None,
    params: PipelineParams | None = None,
) -> SolvedImage:
    """Detect, identify and solve one image (module docstring); bad input raises ValueError."""
    frame = _frame(image)
    camera = _camera(frame, camera, fov_deg)
    t0 = time.perf_counter()
    from firmware_model.pipeline.run import PipelineParams, run_pipeline
    from ground.analysis.replay import warm_up_kernels

    loaded = warm_up_kernels() > 0  # the first call: the pipeline's modules and kernels loaded now
    compile_s = time.perf_counter() - t0 if loaded else 0.0
    t0, hits = time.perf_counter(), catalog_for_field.cache_info().hits
    cat = _catalog(catalog, camera)
    built = isinstance(catalog, (str, Path)) or (catalog is None and catalog_for_field.cache_info().hits == hits)
    catalog_s = time.perf_counter() - t0 if built else 0.0  # built or loaded now (not given, not kept)
    out = run_pipeline(frame, camera, cat, params or PipelineParams())
    return solved_image(out, camera, {"catalog": catalog_s, "compile": compile_s})


def solved_image(out: PipelineOutput, camera: CameraModel, setup_s: dict[str, float] | None = None) -> SolvedImage:
    """The :class:`SolvedImage` of a pipeline run made with ``camera``; ``setup_s``: set-up seconds
    (``catalog``, ``compile``) the call paid before the frame, added to the record's timings."""
    from ground.link.solve_report import add_setup_stages, record_from_output

    rec = add_setup_stages(record_from_output(out), **(setup_s or {}))
    used = out.optics.camera if out.optics is not None else (out.camera or camera)
    stars = tuple(
        IdentifiedStar(s["x"], s["y"], s["flux"], s["rg"], s["bg"], s["catalog_id"], s["residual_arcsec"])
        for s in rec["stars"]
    )
    q = rec["q_icrs_to_sensor"]
    return SolvedImage(
        status=rec["status"],
        reason=rec["reason"],
        q_icrs_to_sensor=tuple(q) if q is not None else None,
        ra_deg=rec["ra_deg"],
        dec_deg=rec["dec_deg"],
        roll_deg=rec["roll_deg"],
        sigma_arcsec=tuple(rec["sigma_arcsec"]) if rec["sigma_arcsec"] is not None else None,
        camera=used,
        stars=stars,
        record=rec,
    )


def _frame(image) -> Frame:
    from firmware_model.pipeline.frame_readers import FrameReadError, read_frame, remosaic_rggb
    from firmware_model.pipeline.raw_frame import Frame

    if isinstance(image, (str, Path)):
        try:
            return read_frame(image)
        except FrameReadError as exc:
            raise ValueError(str(exc)) from None
    arr = np.asarray(image)
    white = float(np.iinfo(arr.dtype).max) if np.issubdtype(arr.dtype, np.integer) else 65535.0  # as read_npy
    if arr.ndim == 2:
        return Frame(pixels=arr, pattern="MONO", white_level=white)
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        rgb = arr[:, :, :3]
        rgb = rgb[: rgb.shape[0] // 2 * 2, : rgb.shape[1] // 2 * 2]
        return Frame(pixels=remosaic_rggb(rgb), pattern="RGGB", white_level=white, metadata={"demosaiced": True})
    raise ValueError(f"an image array must be (H, W) or (H, W, 3), got shape {arr.shape}")


def _camera(frame: Frame, camera: CameraModel | None, fov_deg: float | None) -> CameraModel:
    from firmware_model.camera import CameraModel

    if camera is not None:
        if (camera.width, camera.height) != (frame.width, frame.height):
            raise ValueError(
                f"the camera is {camera.width} x {camera.height} px but the image is {frame.width} x {frame.height}"
            )
        return camera
    if fov_deg is None:
        raise ValueError("give camera=CameraModel(...) or fov_deg=<horizontal field of view, deg>")
    if not 0.0 < fov_deg < 180.0:
        raise ValueError(f"fov_deg must be in (0, 180) deg, got {fov_deg}")
    return CameraModel.from_horizontal_fov(frame.width, frame.height, float(fov_deg))


def _catalog(catalog, camera: CameraModel) -> OnboardCatalog:
    if catalog is None:
        return catalog_for_camera(camera)
    if isinstance(catalog, (str, Path)):
        from firmware_model.catalog.image_io import catalog_from_image

        try:
            return catalog_from_image(Path(catalog).read_bytes())
        except (OSError, ValueError) as exc:
            raise ValueError(f"catalog {catalog}: {exc}") from None
    return catalog


def catalog_for_camera(camera: CameraModel) -> OnboardCatalog:
    """:func:`catalog_for_field` of the camera's array and horizontal field of view (to 0.01 deg)."""
    hfov = float(np.degrees(2.0 * np.arctan(camera.width / 2.0 / camera.f)))
    return catalog_for_field(camera.width, camera.height, round(hfov, 2))


@lru_cache(maxsize=4)
def catalog_for_field(width: int, height: int, fov_deg: float) -> OnboardCatalog:
    """The catalog ``st16-ground catalog build --fov-deg`` makes for this field (bundled Hipparcos),
    with its pattern index for the field: built once (1-20 s; one warning line says so), then
    loaded from the user's cache directory (the catalog image in ``field-catalogs/``, named by a
    hash of the design and of the code that builds it; the index in ``pattern-index/``,
    ``scale_free.cached_pattern_index``)."""
    from firmware_model import user_cache_dir
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_from_image, catalog_to_image
    from firmware_model.pipeline import scale_free
    from ground.atomic_write import write_bytes
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    design = CatalogDesign.for_field(width, height, fov_deg)
    camera = CameraModel.from_horizontal_fov(width, height, fov_deg)
    folder = user_cache_dir() / "field-catalogs"
    path = folder / f"{_field_key(design)}.st16cat"
    try:
        cat = catalog_from_image(path.read_bytes())
    except (OSError, ValueError) as exc:  # not kept yet (or damaged): built now
        if not isinstance(exc, FileNotFoundError):
            _log.debug("field catalog %s not used: %s", path, exc)
        _log.warning(
            "building a star catalog and its pattern index for a %.2f deg field of %d x %d px: once per "
            "field (1-20 s), then kept in %s",
            fov_deg,
            width,
            height,
            user_cache_dir(),
        )
        image = catalog_to_image(build_catalog(design))
        cat = catalog_from_image(image)  # as it will load from the cache: the same answers every time
        try:
            folder.mkdir(parents=True, exist_ok=True)
            write_bytes(path, image)
        except OSError as exc:
            _log.warning("field catalog not kept in %s: %s", folder, exc)
    mrad = scale_free.pattern_field(camera)
    index = scale_free.cached_pattern_index(
        user_cache_dir() / "pattern-index", cat.vec, cat.mag, cat.n_pattern_stars, mrad
    )
    scale_free.set_catalog_patterns(cat, mrad, index)
    return cat


def _field_key(design) -> str:
    """A name for a field's cached catalog: a hash of its design, the package version and the
    code that builds the catalog and its image."""
    import protocol

    root = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256(f"{protocol.__version__} {design!r}".encode())
    sources = [
        *sorted((root / "ground" / "catalog").glob("*.py")),
        *sorted((root / "firmware_model" / "catalog").glob("*.py")),
        root / "protocol" / "catalog_image.py",
    ]  # the pattern index is kept apart, under its own hash (scale_free.cached_pattern_index)
    for source in sources:
        digest.update(source.read_bytes())
    return digest.hexdigest()[:20]
