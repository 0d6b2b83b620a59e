"""Solve one image from Python: the device pipeline in-process, one call.

    from ground.api import solve_image
    s = solve_image("frame.tiff", fov_deg=11.4)          # or camera=CameraModel(...), catalog=...
    if s.solved:
        print(s.status, s.ra_deg, s.dec_deg, s.roll_deg, s.sigma_arcsec)
        s.wcs().to_header()                                # astropy WCS, TAN-SIP (docs/wcs.md)

``image`` is a path (every format the pipeline reads: DNG/raw, FITS, TIFF, PNG/JPEG, .npy, frame
blobs) or an array: (H, W) a mono frame, (H, W, 3) a demosaiced RGB image (saturation at the
integer type's maximum).

Without a ``camera``, the field of view is searched with the attitude against the whole-sky
pattern database (``ground.catalog.sky_database``, ``database`` a file or the user cache's, built
once): ``fov_deg`` (horizontal, deg) is a hint (the field within ``fov_deg / 1.4`` to
``1.4 fov_deg``), ``fov_range=(lo, hi)`` bounds it, neither solves blind over 5-60 deg; the
record's ``sky`` block gives the search's field of view, hypotheses checked and false-alarm
probability (docs/identification.md, "Blind and wide"). A ``camera`` (:class:`CameraModel`) is
taken as calibrated but for the optics fit; with a ``catalog`` too, the solve is the device's
twin (that catalog's own pattern index, no database). ``catalog`` is an :class:`OnboardCatalog`
or a catalog image path (``st16-ground catalog build``); without one, each field's catalog is
built from the bundled Hipparcos once and kept (``ground.catalog.field_catalogs``). ``params`` are the
pipeline's parameters (the device's slot-2 settings).

The first solve in a process loads the compiled kernels (``ground.kernels.warm_up_kernels``); its record's
``timings_s`` count that as ``compile``, the database's loading as ``database`` and the catalog's
building or loading as ``catalog``, and their ``total`` is the whole time the call took past
reading the image.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.onboard import OnboardCatalog
    from firmware_model.pipeline.raw_frame import Frame
    from firmware_model.pipeline.solve_types import PipelineParams
    from ground.solver import Solve

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
    fov_range: tuple[float, float] | None = None,
    database: str | Path | None = None,
) -> SolvedImage:
    """Detect, identify and solve one image (module docstring) with ``ground.solver``'s one
    in-process solver; bad input raises ValueError."""
    frame = _frame(image)
    if camera is not None:
        _check_size(frame, camera)
    from ground.solver import in_process_solver

    solver = in_process_solver(
        camera=camera, catalog=catalog, fov_deg=fov_deg, fov_range=fov_range, database=database, params=params
    )
    solver.every_star = True
    return solved_image(solver.solve(frame), frame)


def solved_image(solve: Solve, frame: Frame) -> SolvedImage:
    """The :class:`SolvedImage` of one in-process :class:`~ground.solver.Solve` of ``frame``."""
    from firmware_model.camera import CameraModel

    rec, out = solve.record, solve.output
    assert out is not None
    if out.optics is not None:
        used = out.optics.camera
    else:  # the pipeline's camera, else the given one, else (no camera found) a stand-in
        used = out.camera or solve.camera or CameraModel.from_horizontal_fov(frame.width, frame.height, 10.0)
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


def _check_size(frame: Frame, camera: CameraModel) -> None:
    if (camera.width, camera.height) != (frame.width, frame.height):
        raise ValueError(
            f"the camera is {camera.width} x {camera.height} px but the image is {frame.width} x {frame.height}"
        )
