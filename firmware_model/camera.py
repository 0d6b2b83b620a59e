"""Pinhole camera with Brown-Conrady radial and tangential distortion.

Conventions (docs/CONVENTIONS.md):

* Sensor frame: +z boresight (toward the sky), +x along increasing column, +y along
  increasing row. A sensor-frame direction ``v`` maps to ideal normalised coordinates
  ``(u, w) = (v_x / v_z, v_y / v_z)``.
* Pixel coordinates: ``x`` = column, ``y`` = row, zero-based, the centre of pixel
  ``(row r, col c)`` is at ``(x, y) = (c, r)``; the array spans ``[-0.5, W - 0.5)``.
* Distortion (Brown-Conrady, as in Heikkila & Silven 1997), applied to ideal normalised
  coordinates with ``r^2 = u^2 + w^2``::

      radial = 1 + k1 r^2 + k2 r^4 + k3 r^6
      u_d = u radial + 2 p1 u w + p2 (r^2 + 2 u^2)
      w_d = w radial + p1 (r^2 + 2 w^2) + 2 p2 u w
      x = cx + f u_d,  y = cy + f w_d

  ``f`` is the focal length in pixels (square pixels), ``(cx, cy)`` the principal point
  in pixels. ``pixel_to_vector`` inverts the distortion by Newton iteration to better
  than 1e-6 px over the array.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from functools import cached_property

import numpy as np
from numba import njit

#: Reference design of Enright & McVittie section 2: MT9P031-class 2592 x 1944 array, 2.2 um pixels.
REFERENCE_WIDTH = 2592
REFERENCE_HEIGHT = 1944
REFERENCE_PIXEL_UM = 2.2
REFERENCE_HALF_FOV_MINOR_DEG = 7.5

_NEWTON_MAX_ITER = 30
_NEWTON_TOL = 1e-12  # normalised units; f ~ 7e3 px => ~1e-8 px
_CONVERGED = 1e-10  # residual accepted as an inverse (normalised units, ~1e-6 px at f ~ 7e3)


@dataclass(frozen=True)
class CameraModel:
    """Camera intrinsics: array size (px), focal length ``f`` (px), principal point
    ``(cx, cy)`` (px), radial ``k1, k2, k3`` and tangential ``p1, p2`` coefficients
    (dimensionless, on normalised coordinates)."""

    width: int
    height: int
    f: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self):
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera array size must be positive, got {self.width} x {self.height}")
        if not math.isfinite(self.f) or self.f <= 0:
            raise ValueError(f"focal length must be a positive number of pixels, got {self.f}")
        for name in ("cx", "cy", "k1", "k2", "k3", "p1", "p2"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"camera parameter {name} must be finite")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # ---------------------------------------------------------------- constructors
    @classmethod
    def pinhole(cls, width: int, height: int, f: float, **distortion) -> CameraModel:
        """Camera of focal length ``f`` (px), principal point at the array centre, distortion-free
        unless ``distortion`` gives coefficients."""
        return cls(width, height, float(f), (width - 1) / 2.0, (height - 1) / 2.0, **distortion)

    @classmethod
    def from_fov(cls, width: int, height: int, half_fov_minor_deg: float, **distortion) -> CameraModel:
        """Distortion-free camera whose half field of view across the minor axis (from the
        array centre to the outer edge of the edge pixels) is ``half_fov_minor_deg``."""
        if not 0.0 < half_fov_minor_deg < 90.0:
            raise ValueError(f"half field of view must be in (0, 90) deg, got {half_fov_minor_deg}")
        half_extent = min(width, height) / 2.0
        return cls.pinhole(width, height, half_extent / np.tan(np.radians(half_fov_minor_deg)), **distortion)

    @classmethod
    def from_horizontal_fov(cls, width: int, height: int, fov_deg: float) -> CameraModel:
        """Distortion-free camera whose full field of view across the array width (outer pixel
        edges) is ``fov_deg``, principal point at the array centre: what a plate solver's
        field-of-view estimate gives."""
        if not 0.0 < fov_deg < 180.0:
            raise ValueError(f"field of view must be in (0, 180) deg, got {fov_deg}")
        return cls.pinhole(width, height, width / 2.0 / np.tan(np.radians(fov_deg) / 2.0))

    @classmethod
    def from_focal(cls, width: int, height: int, focal_mm: float, pixel_um: float, **distortion) -> CameraModel:
        """Camera from a focal length in mm and a pixel pitch in micrometres; principal
        point at the array centre."""
        if focal_mm <= 0 or pixel_um <= 0:
            raise ValueError("focal length and pixel pitch must be positive")
        return cls.pinhole(width, height, focal_mm * 1000.0 / pixel_um, **distortion)

    @classmethod
    def reference_design(cls) -> CameraModel:
        """Enright & McVittie reference design: 2592 x 1944, 7.5 deg half FOV on the minor axis
        (f = 972 / tan 7.5 deg = 7383.1 px, i.e. 16.24 mm at 2.2 um)."""
        return cls.from_fov(REFERENCE_WIDTH, REFERENCE_HEIGHT, REFERENCE_HALF_FOV_MINOR_DEG)

    def to_dict(self) -> dict:
        """Plain JSON-serialisable dict of the parameters."""
        return {k: (int(v) if k in ("width", "height") else float(v)) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> CameraModel:
        """Inverse of ``to_dict``; unknown keys are an error, missing distortion terms default to 0."""
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown camera model keys: {sorted(unknown)}")
        missing = {"width", "height", "f", "cx", "cy"} - set(d)
        if missing:
            raise ValueError(f"camera model dict lacks {sorted(missing)}")
        return cls(**d)

    # ---------------------------------------------------------------- geometry
    @property
    def has_distortion(self) -> bool:
        return any(getattr(self, k) != 0.0 for k in ("k1", "k2", "k3", "p1", "p2"))

    @cached_property
    def fov_half_angle_minor(self) -> float:
        """Half field of view (rad) from the principal point to the minor-axis array edge."""
        return self._edge_half_angle(minor=True)

    @cached_property
    def fov_half_angle_major(self) -> float:
        """Half field of view (rad) from the principal point to the major-axis array edge."""
        return self._edge_half_angle(minor=False)

    @cached_property
    def fov_half_angle_diagonal(self) -> float:
        """Largest angle (rad) between the boresight (+z) and any array corner."""
        xs = np.array([-0.5, self.width - 0.5, -0.5, self.width - 0.5])
        ys = np.array([-0.5, -0.5, self.height - 0.5, self.height - 0.5])
        v = self.pixel_to_vector(xs, ys)
        return float(np.max(np.arccos(np.clip(v[:, 2], -1.0, 1.0))))

    def _edge_half_angle(self, minor: bool) -> float:
        along_x = (self.width <= self.height) == minor
        if along_x:
            xs, ys = np.array([-0.5, self.width - 0.5]), np.array([self.cy, self.cy])
        else:
            xs, ys = np.array([self.cx, self.cx]), np.array([-0.5, self.height - 0.5])
        v = self.pixel_to_vector(xs, ys)
        return float(np.mean(np.arccos(np.clip(v[:, 2], -1.0, 1.0))))

    def in_frame(self, x, y, margin: float = 0.0) -> np.ndarray:
        """True where pixel coordinates lie inside the array, ``margin`` px from its edges."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        return (
            (x >= -0.5 + margin)
            & (x < self.width - 0.5 - margin)
            & (y >= -0.5 + margin)
            & (y < self.height - 0.5 - margin)
        )

    # ---------------------------------------------------------------- distortion
    def distort(self, u, w):
        """Ideal normalised coordinates -> distorted normalised coordinates."""
        u = np.asarray(u, dtype=float)
        w = np.asarray(w, dtype=float)
        r2 = u * u + w * w
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        ud = u * radial + 2.0 * self.p1 * u * w + self.p2 * (r2 + 2.0 * u * u)
        wd = w * radial + self.p1 * (r2 + 2.0 * w * w) + 2.0 * self.p2 * u * w
        return ud, wd

    def _distort_jacobian(self, u, w):
        r2 = u * u + w * w
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        drad_dr2 = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2)
        drad_du = drad_dr2 * 2.0 * u
        drad_dw = drad_dr2 * 2.0 * w
        j11 = radial + u * drad_du + 2.0 * self.p1 * w + 6.0 * self.p2 * u
        j12 = u * drad_dw + 2.0 * self.p1 * u + 2.0 * self.p2 * w
        j21 = w * drad_du + 2.0 * self.p1 * u + 2.0 * self.p2 * w
        j22 = radial + w * drad_dw + 6.0 * self.p1 * w + 2.0 * self.p2 * u
        return j11, j12, j21, j22

    def undistort(self, ud, wd):
        """Distorted normalised coordinates -> ideal normalised coordinates (Newton, per point,
        compiled: :func:`_undistort`). Points without a physical inverse (beyond the fold of a
        strongly distorting model: no convergence, or a solution with a negative radial factor or
        reversed orientation) come back as NaN rather than a wrong direction."""
        ud = np.asarray(ud, dtype=float)
        wd = np.asarray(wd, dtype=float)
        if not self.has_distortion:
            return ud.copy(), wd.copy()
        shape = np.broadcast_shapes(ud.shape, wd.shape)
        u, w = _undistort(
            np.broadcast_to(ud, shape).ravel(),
            np.broadcast_to(wd, shape).ravel(),
            self.k1,
            self.k2,
            self.k3,
            self.p1,
            self.p2,
        )
        return u.reshape(shape), w.reshape(shape)

    # ---------------------------------------------------------------- projection
    def pixel_to_vector(self, x, y) -> np.ndarray:
        """Sensor-frame unit vectors, shape (N, 3), for pixel coordinates (x = column, y = row);
        NaN rows where the distortion cannot be inverted."""
        x = np.atleast_1d(np.asarray(x, dtype=float)).ravel()
        y = np.atleast_1d(np.asarray(y, dtype=float)).ravel()
        if x.shape != y.shape:
            raise ValueError(f"x and y must have the same length, got {x.shape} and {y.shape}")
        return pixel_to_vector_kernel(x, y, self.f, self.cx, self.cy, self.k1, self.k2, self.k3, self.p1, self.p2)

    def vector_to_pixel(self, v):
        """Pixel coordinates ``(x, y)`` (arrays of length N) of sensor-frame directions
        ``v`` (shape (3,) or (N, 3), need not be unit). Directions with ``v_z <= 0`` (behind
        the camera) give NaN."""
        v = np.atleast_2d(np.asarray(v, dtype=float))
        if v.shape[-1] != 3:
            raise ValueError(f"vectors must have shape (N, 3), got {v.shape}")
        return vector_to_pixel_kernel(v, self.f, self.cx, self.cy, self.k1, self.k2, self.k3, self.p1, self.p2)


@njit(cache=True, nogil=True)
def distort_point(u, w, k1, k2, k3, p1, p2):  # pragma: no cover - compiled
    """:meth:`CameraModel.distort` and its Jacobian at one point: ``(u_d, w_d, radial, j11, j12,
    j22)`` (``j21 = j12``), compiled for the kernels that loop over stars."""
    r2 = u * u + w * w
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    ud = u * radial + 2.0 * p1 * u * w + p2 * (r2 + 2.0 * u * u)
    wd = w * radial + p1 * (r2 + 2.0 * w * w) + 2.0 * p2 * u * w
    j11 = radial + 2.0 * u * u * drad + 2.0 * p1 * w + 6.0 * p2 * u
    j12 = 2.0 * u * w * drad + 2.0 * p1 * u + 2.0 * p2 * w
    j22 = radial + 2.0 * w * w * drad + 6.0 * p1 * w + 2.0 * p2 * u
    return ud, wd, radial, j11, j12, j22


@njit(cache=True, nogil=True)
def _undistort(ud, wd, k1, k2, k3, p1, p2):  # pragma: no cover - compiled
    """Newton inversion of :meth:`CameraModel.distort`, point by point; NaN where no physical
    inverse converges."""
    n = len(ud)
    u_out, w_out = np.empty(n), np.empty(n)
    for i in range(n):
        u, w = ud[i], wd[i]
        ok = math.isfinite(u) and math.isfinite(w)
        for _ in range(_NEWTON_MAX_ITER):
            if not ok:
                break
            fu, fw, _radial, j11, j12, j22 = distort_point(u, w, k1, k2, k3, p1, p2)
            eu, ew = fu - ud[i], fw - wd[i]
            det = j11 * j22 - j12 * j12
            if det == 0.0 or not math.isfinite(det):
                ok = False
                break
            du = (j22 * eu - j12 * ew) / det
            dw = (-j12 * eu + j11 * ew) / det
            u -= du
            w -= dw
            if abs(du) + abs(dw) < _NEWTON_TOL:
                break
        if ok:
            fu, fw, radial, j11, j12, j22 = distort_point(u, w, k1, k2, k3, p1, p2)
            # a physical inverse: converged, a positive radial factor, the map's orientation kept
            ok = abs(fu - ud[i]) + abs(fw - wd[i]) < _CONVERGED and radial > 0.0 and j11 * j22 - j12 * j12 > 0.0
        u_out[i] = u if ok else np.nan
        w_out[i] = w if ok else np.nan
    return u_out, w_out


# --- the projections, compiled: the identification projects a frame's stars and its catalog
# stars a dozen times a solve; the same arithmetic as distort / undistort


@njit(cache=True, nogil=True)
def vector_to_pixel_kernel(v, f, cx, cy, k1, k2, k3, p1, p2):  # pragma: no cover - compiled
    """:meth:`CameraModel.vector_to_pixel`'s numbers."""
    n = v.shape[0]
    x, y = np.empty(n), np.empty(n)
    for i in range(n):
        vz = v[i, 2]
        if vz > 0:
            ud, wd, _radial, _j11, _j12, _j22 = distort_point(v[i, 0] / vz, v[i, 1] / vz, k1, k2, k3, p1, p2)
            x[i], y[i] = cx + f * ud, cy + f * wd
        else:
            x[i], y[i] = np.nan, np.nan
    return x, y


@njit(cache=True, nogil=True)
def pixel_to_vector_kernel(x, y, f, cx, cy, k1, k2, k3, p1, p2):  # pragma: no cover - compiled
    """:meth:`CameraModel.pixel_to_vector`'s numbers."""
    u, w = (x - cx) / f, (y - cy) / f
    if k1 != 0.0 or k2 != 0.0 or k3 != 0.0 or p1 != 0.0 or p2 != 0.0:
        u, w = _undistort(u, w, k1, k2, k3, p1, p2)
    out = np.empty((len(u), 3))
    for i in range(len(u)):
        norm = np.sqrt(u[i] * u[i] + w[i] * w[i] + 1.0)
        out[i, 0], out[i, 1], out[i, 2] = u[i] / norm, w[i] / norm, 1.0 / norm
    return out
