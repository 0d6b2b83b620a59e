"""A FITS WCS (TAN with SIP distortion) for a solved frame, from our camera model and attitude.

Conventions (docs/CONVENTIONS.md): pixel ``(x, y)`` = (column, row), zero-based, pixel centres
on integers; FITS counts from 1, so ``CRPIX = (cx + 1, cy + 1)``. The sensor frame has +x along
increasing column, +y along increasing row, +z the boresight; ``v_sensor = A(q) v_icrs``.

* ``CRVAL`` is the boresight (ICRS), the tangent point of the gnomonic projection;
* ``CD`` (deg/px) maps an undistorted pixel offset ``f (u, w)``, ``(u, w) = (v_x, v_y) / v_z``,
  to the standard coordinates (xi east, eta north, deg) at the tangent point;
* SIP ``A``/``B`` (pixel offset -> undistorted offset) and ``AP``/``BP`` (the inverse) are fitted
  to the Brown-Conrady model over a grid on the array, the order raised until astropy's
  pixel -> sky -> our pixel round trip is within :data:`SIP_TOLERANCE_PX` everywhere on it.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.reference_frames import quat_to_matrix, radec_to_vec, vec_to_radec
from ground.atomic_write import atomic_path

SIP_TOLERANCE_PX = 0.01  #: fitted SIP against the camera model, worst point of the grid (px)
SIP_MAX_ORDER = 9
GRID = 41  #: points per array axis where the SIP polynomials are fitted and checked


class WcsError(ValueError):
    """No WCS can describe this solve (no attitude, or a distortion SIP cannot follow)."""


def frame_wcs(camera: CameraModel, q_icrs_to_sensor) -> tuple[object, float]:
    """(astropy ``WCS``, worst round-trip error over the array in px) for a frame solved to
    ``q_icrs_to_sensor`` (scalar first) with ``camera``."""
    if q_icrs_to_sensor is None:
        raise WcsError("no attitude: the frame was not solved, so there is no WCS to write")
    from astropy.wcs import Sip

    a = quat_to_matrix(np.asarray(q_icrs_to_sensor, dtype=float))
    wcs = _tan_wcs(camera, a)
    if not camera.has_distortion:
        return wcs, _round_trip_px(wcs, camera, a)
    for order in range(2, SIP_MAX_ORDER + 1):
        wcs.sip = Sip(*_sip_polynomials(camera, order), wcs.wcs.crpix)
        wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
        err = _round_trip_px(wcs, camera, a)
        if err <= SIP_TOLERANCE_PX:
            return wcs, err
    raise WcsError(f"SIP up to order {SIP_MAX_ORDER} misses the camera model by {err:.3f} px")


def record_camera(record: dict, width: int, height: int, camera: CameraModel | None = None) -> CameraModel:
    """The camera a solve record was found with: focal length and k1 as the record reports them
    (fitted, or the nominal ones), the principal point and the other terms from ``camera`` when it
    has the frame's size, else the array centre and none."""
    optics = record.get("optics") or {}
    base = camera if camera is not None and (camera.width, camera.height) == (width, height) else None
    if base is None:
        base = CameraModel(width, height, 1.0, (width - 1) / 2.0, (height - 1) / 2.0)
    f, k1 = optics.get("focal_px"), optics.get("k1")
    return replace(base, f=float(f) if f else base.f, k1=float(k1) if k1 is not None else base.k1)


def record_wcs(record: dict, width: int, height: int, camera: CameraModel | None = None):
    """:func:`frame_wcs` of a solve record (``st16-ground solve --json``'s fields)."""
    if record.get("q_icrs_to_sensor") is None:
        raise WcsError(f"no attitude (status {record.get('status')}): the frame was not solved, so there is no WCS")
    return frame_wcs(record_camera(record, width, height, camera), record["q_icrs_to_sensor"])


def write_wcs(path: str | Path, wcs) -> Path:
    """A FITS file holding only the WCS header (as astrometry.net's ``.wcs``, with its IMAGEW and
    IMAGEH: the image size), written atomically.

    The header says ``NAXIS = 2`` with ``NAXIS1 = NAXIS2 = 0``: two axes, as the WCS has, and no data
    array (FITS 4.0 section 4.4.1.1: a zero axis length means no data follow). astropy then reads it
    without a warning: with ``NAXIS = 0`` (astropy's own ``to_fits``, and astrometry.net's "minimal
    header") it warns that the WCS has more axes than the image, and with the image's size as
    ``NAXIS1``/``NAXIS2`` the file would be a truncated image of that size (astropy warns that it may
    have been truncated; other readers fail)."""
    header = wcs.to_fits(relax=True)[0].header
    header["NAXIS"] = 2
    header.insert("NAXIS", ("NAXIS1", 0, "no data: the image width is IMAGEW"), after=True)
    header.insert("NAXIS1", ("NAXIS2", 0, "no data: the image height is IMAGEH"), after=True)
    if wcs.pixel_shape is not None:
        width, height = (int(n) for n in wcs.pixel_shape)
        header["IMAGEW"] = (width, "Image width,  in pixels.")
        header["IMAGEH"] = (height, "Image height, in pixels.")
    with atomic_path(path) as tmp:
        header.tofile(tmp, overwrite=True)  # the header alone, padded to 2880 bytes (a PrimaryHDU resets NAXIS)
    return Path(path)


def _tan_wcs(camera: CameraModel, a: np.ndarray):
    """TAN projection at the boresight with the CD matrix of the sensor axes (no distortion)."""
    from astropy.wcs import WCS

    ra, dec = (float(np.degrees(x)) for x in vec_to_radec(a[2]))
    east = np.array([-np.sin(np.radians(ra)), np.cos(np.radians(ra)), 0.0])
    north = np.cross(a[2] / np.linalg.norm(a[2]), east)
    m = np.array([[a[0] @ east, a[1] @ east], [a[0] @ north, a[1] @ north]])  # (u, w) -> (xi, eta), rad
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [ra % 360.0, dec]
    wcs.wcs.crpix = [camera.cx + 1.0, camera.cy + 1.0]
    wcs.wcs.cd = np.degrees(m) / camera.f
    wcs.wcs.radesys = "ICRS"
    wcs.pixel_shape = (camera.width, camera.height)
    return wcs


def _grid(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.meshgrid(np.linspace(-0.5, camera.width - 0.5, GRID), np.linspace(-0.5, camera.height - 0.5, GRID))
    return x.ravel(), y.ravel()


def _terms(order: int) -> list[tuple[int, int]]:
    return [(p, q) for n in range(2, order + 1) for p in range(n + 1) for q in [n - p]]


def _fit(dx, dy, target, order: int) -> np.ndarray:
    """SIP coefficient matrix ``c[p, q]`` of ``sum c dx^p dy^q`` (p + q in 2..order) fitting ``target``."""
    terms = _terms(order)
    scale = max(np.abs(dx).max(), np.abs(dy).max())
    design = np.column_stack([(dx / scale) ** p * (dy / scale) ** q for p, q in terms])
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    out = np.zeros((order + 1, order + 1))
    for (p, q), c in zip(terms, coef):
        out[p, q] = c / scale ** (p + q)
    return out


def _sip_polynomials(camera: CameraModel, order: int):
    """(A, B, AP, BP) of the given order for ``camera`` (pixel offsets from CRPIX)."""
    x, y = _grid(camera)
    v = camera.pixel_to_vector(x, y)
    big_u, big_w = camera.f * v[:, 0] / v[:, 2], camera.f * v[:, 1] / v[:, 2]  # undistorted offsets
    dx, dy = x - camera.cx, y - camera.cy
    a, b = _fit(dx, dy, big_u - dx, order), _fit(dx, dy, big_w - dy, order)
    ap, bp = _fit(big_u, big_w, dx - big_u, order), _fit(big_u, big_w, dy - big_w, order)
    return a, b, ap, bp


def _round_trip_px(wcs, camera: CameraModel, a: np.ndarray) -> float:
    """Worst distance (px) over the grid between a pixel and the pixel our camera model gives for
    astropy's sky position of it, and between a pixel and astropy's pixel of our sky position."""
    x, y = _grid(camera)
    ra, dec = wcs.all_pix2world(x, y, 0)
    v_icrs = radec_to_vec(np.radians(ra), np.radians(dec))
    xb, yb = camera.vector_to_pixel(v_icrs @ a.T)
    ours = camera.pixel_to_vector(x, y) @ a  # sensor -> ICRS
    r2, d2 = (np.degrees(t) for t in vec_to_radec(ours))
    xa, ya = wcs.all_world2pix(r2, d2, 0, tolerance=1e-6, maxiter=50)
    return float(max(np.hypot(xb - x, yb - y).max(), np.hypot(xa - x, ya - y).max()))
