"""Open-loop rendering models: optics, detector and sky effects the solver does not assume.

Used by ``bench/bench_openloop.py`` (docs/openloop.md) with ``ground.sim.sensor_sim.render_frame``:

* PSFs (``render_frame(psf=...)``), each integrated over pixels by sub-pixel sampling or exact
  error functions: :class:`MoffatPSF` (beta 2.5-4 wings), :class:`DonutPSF` (defocused
  annulus with a central obstruction), :class:`ComaPSF` (third-order coma growing linearly
  with field radius);
* geometry: :func:`true_camera` (focal-length scale, principal-point offset) and
  :class:`RadialMappedCamera` (division model or equisolid blend, outside Brown-Conrady);
* detector and sky (``render_frame(extra_e=...)``): :func:`sky_gradient_e`,
  :func:`hot_clusters_e`, :func:`apply_bad_columns` (after rendering, on DN);
* scene: :func:`stars_in_cone`, :func:`drop_stars`, :func:`scintillate`,
  :func:`blackbody_sky_stars` (:func:`blackbody_colours`), :func:`planet`, :func:`false_star`, :func:`streak`.

Units: pixels (x = column, y = row, pixel centres at integers, docs/CONVENTIONS.md),
photo-electrons (e-) over the exposure unless a name says ``_per_s``, radians.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.special import erf

from firmware_model.camera import CameraModel
from firmware_model.pipeline.raw_frame import Frame
from ground.sim.sensor_sim import FalseObject, Stars

# ------------------------------------------------------------------------------------------ PSFs

_SUB = 8  #: sub-samples per pixel axis for numerically integrated PSFs


def _subgrid(cols: np.ndarray, rows: np.ndarray, n: int = _SUB):
    sub = (np.arange(n) + 0.5) / n - 0.5
    return (cols[:, None] + sub[None, :]).ravel(), (rows[:, None] + sub[None, :]).ravel()


def _bin(fine: np.ndarray, nr: int, nc: int, n: int = _SUB) -> np.ndarray:
    return fine.reshape(nr, n, nc, n).sum(axis=(1, 3))


@dataclass(frozen=True)
class MoffatPSF:
    """Moffat PSF ``I(r) = (beta - 1) / (pi alpha^2) (1 + r^2 / alpha^2)^-beta`` (unit integral
    over the plane) of full width at half maximum ``fwhm_px`` (px), ``alpha = fwhm / (2 sqrt(2^(1/beta) - 1))``.
    The stamp reaches the radius holding all but ``1e-3`` of the flux (capped at 60 px); it is
    not renormalised, so it integrates to the enclosed fraction."""

    fwhm_px: float
    beta: float

    def __post_init__(self):
        if not (self.fwhm_px > 0 and self.beta > 1):
            raise ValueError("Moffat needs fwhm > 0 and beta > 1")

    @property
    def alpha(self) -> float:
        return self.fwhm_px / (2.0 * np.sqrt(2.0 ** (1.0 / self.beta) - 1.0))

    @property
    def max_half_width(self) -> int:
        r = self.alpha * np.sqrt(1e-3 ** (1.0 / (1.0 - self.beta)) - 1.0)
        return int(min(np.ceil(r) + 2, 60))

    def half_width(self, x0, y0) -> int:
        return self.max_half_width

    def stamp(self, x0, y0, cols, rows) -> np.ndarray:
        xs, ys = _subgrid(cols, rows)
        r2 = (xs[None, :] - x0) ** 2 + (ys[:, None] - y0) ** 2
        a2 = self.alpha**2
        fine = (self.beta - 1.0) / (np.pi * a2) * (1.0 + r2 / a2) ** (-self.beta) / _SUB**2
        return _bin(fine, len(rows), len(cols))

    def to_dict(self) -> dict:
        return {"model": "moffat", "fwhm_px": float(self.fwhm_px), "beta": float(self.beta)}


@dataclass(frozen=True)
class DonutPSF:
    """Defocused pupil image: a uniform annulus of outer radius ``r_out_px`` and inner radius
    ``r_in_px`` (central obstruction), convolved with a Gaussian of ``blur_sigma_px`` (px);
    normalised to unit sum over the stamp."""

    r_out_px: float
    r_in_px: float
    blur_sigma_px: float = 0.5

    def __post_init__(self):
        if not (0 <= self.r_in_px < self.r_out_px and self.blur_sigma_px >= 0):
            raise ValueError("donut needs 0 <= r_in < r_out and blur >= 0")

    @property
    def max_half_width(self) -> int:
        return int(np.ceil(self.r_out_px + 5.0 * self.blur_sigma_px + 2))

    def half_width(self, x0, y0) -> int:
        return self.max_half_width

    def stamp(self, x0, y0, cols, rows) -> np.ndarray:
        xs, ys = _subgrid(cols, rows)
        r2 = (xs[None, :] - x0) ** 2 + (ys[:, None] - y0) ** 2
        fine = ((r2 <= self.r_out_px**2) & (r2 >= self.r_in_px**2)).astype(float)
        if self.blur_sigma_px > 0:
            fine = gaussian_filter(fine, self.blur_sigma_px * _SUB, mode="constant")
        total = fine.sum()
        out = _bin(fine, len(rows), len(cols))
        return out / total if total > 0 else out

    def to_dict(self) -> dict:
        return {
            "model": "donut",
            "r_out_px": float(self.r_out_px),
            "r_in_px": float(self.r_in_px),
            "blur_sigma_px": float(self.blur_sigma_px),
        }


@dataclass(frozen=True)
class ComaPSF:
    """Third-order coma on a Gaussian core. A pupil zone of normalised radius ``rho`` and
    azimuth ``theta`` lands at ``C rho^2 (2 + cos 2 theta)`` along the outward radial direction
    (from the optical axis ``(cx, cy)``) and ``C rho^2 sin 2 theta`` across it, with
    ``C = coma_px_at_corner * r / r_corner`` growing linearly with field radius ``r`` (px):
    a comet flaring outward, ``3 C`` long and ``2 C`` wide, its centroid ``C`` outward of the
    chief ray. Each of 12 x 24 equal-area pupil rays carries a pixel-integrated Gaussian of
    ``sigma_px`` (exact, error functions); unit sum over the plane."""

    sigma_px: float
    coma_px_at_corner: float
    cx: float
    cy: float
    r_corner_px: float

    @property
    def max_half_width(self) -> int:
        return int(np.ceil(3.0 * abs(self.coma_px_at_corner) + 5.0 * self.sigma_px + 2))

    def half_width(self, x0, y0) -> int:
        return self.max_half_width

    def coma_c(self, x0, y0) -> float:
        """Coma coefficient C (px) at pixel (x0, y0)."""
        return self.coma_px_at_corner * np.hypot(x0 - self.cx, y0 - self.cy) / self.r_corner_px

    def ray_offsets(self, x0, y0) -> tuple[np.ndarray, np.ndarray]:
        """(dx, dy) px of the pupil rays from the chief ray at (x0, y0)."""
        nr, nt = 12, 24
        rho2 = ((np.arange(nr) + 0.5) / nr)[:, None]
        th = (2 * np.pi * (np.arange(nt) + 0.5) / nt)[None, :]
        c = self.coma_c(x0, y0)
        rad = (c * rho2 * (2.0 + np.cos(2 * th))).ravel()
        tan = (c * rho2 * np.sin(2 * th)).ravel()
        r = np.hypot(x0 - self.cx, y0 - self.cy)
        ux, uy = ((x0 - self.cx) / r, (y0 - self.cy) / r) if r > 0 else (1.0, 0.0)
        return rad * ux - tan * uy, rad * uy + tan * ux

    def stamp(self, x0, y0, cols, rows) -> np.ndarray:
        dx, dy = self.ray_offsets(x0, y0)
        s = np.sqrt(2.0) * self.sigma_px
        px, py = x0 + dx, y0 + dy
        ex = 0.5 * (erf((cols[None, :] + 0.5 - px[:, None]) / s) - erf((cols[None, :] - 0.5 - px[:, None]) / s))
        ey = 0.5 * (erf((rows[None, :] + 0.5 - py[:, None]) / s) - erf((rows[None, :] - 0.5 - py[:, None]) / s))
        return ey.T @ ex / len(dx)

    def to_dict(self) -> dict:
        return {
            "model": "coma",
            "sigma_px": float(self.sigma_px),
            "coma_px_at_corner": float(self.coma_px_at_corner),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "r_corner_px": float(self.r_corner_px),
        }


# -------------------------------------------------------------------------------------- geometry


def corner_radius_px(camera: CameraModel) -> float:
    """Distance (px) from the principal point to the farthest array corner (outer pixel edge)."""
    xs = np.array([-0.5, camera.width - 0.5])
    ys = np.array([-0.5, camera.height - 0.5])
    return float(np.max(np.hypot(xs[:, None] - camera.cx, ys[None, :] - camera.cy)))


def true_camera(nominal: CameraModel, f_scale: float = 1.0, pp_offset_px=(0.0, 0.0)) -> CameraModel:
    """The lens actually fitted: focal length ``f_scale * nominal.f``, principal point moved by
    ``pp_offset_px`` = (dx, dy) px; the nominal's distortion terms are kept."""
    return replace(nominal, f=nominal.f * f_scale, cx=nominal.cx + pp_offset_px[0], cy=nominal.cy + pp_offset_px[1])


@dataclass(frozen=True)
class RadialMappedCamera:
    """A distortion-free ``base`` camera whose radial mapping is replaced (outside Brown-Conrady):

    * ``division``: Fitzgibbon's division model ``r_u = r_d / (1 + lam r_d^2)`` (normalised
      radii about the principal point), so ``r_d = 2 r_u / (1 + sqrt(1 - 4 lam r_u^2))``;
    * ``equisolid``: blend of pinhole and equisolid fisheye,
      ``r_d = (1 - w) tan(theta) + w 2 sin(theta / 2)``.

    The model's one parameter (``lam`` or ``w``) is set so that a star that the pinhole puts on
    the farthest array corner moves radially by ``corner_shift_px`` (px, positive outward:
    pincushion; negative: barrel). Duck-types the ``CameraModel`` members ``render_frame`` uses."""

    base: CameraModel
    model: str
    corner_shift_px: float

    def __post_init__(self):
        if self.model not in ("division", "equisolid"):
            raise ValueError(f"unknown radial model {self.model!r}")
        if self.base.has_distortion:
            raise ValueError("the base camera must be distortion-free")

    @property
    def width(self) -> int:
        return self.base.width

    @property
    def height(self) -> int:
        return self.base.height

    @property
    def r_corner(self) -> float:
        """Normalised pinhole radius of the farthest corner."""
        return corner_radius_px(self.base) / self.base.f

    @property
    def param(self) -> float:
        """``lam`` (division) or ``w`` (equisolid) giving ``corner_shift_px`` at the corner."""
        ru = self.r_corner
        rd = ru + self.corner_shift_px / self.base.f
        if self.model == "division":
            return (rd / ru - 1.0) / rd**2
        return (rd - ru) / (2.0 * np.sin(np.arctan(ru) / 2.0) - ru)

    def radial(self, ru: np.ndarray) -> np.ndarray:
        """Distorted normalised radius for pinhole normalised radius ``ru``."""
        p = self.param
        if self.model == "division":
            return 2.0 * ru / (1.0 + np.sqrt(1.0 - 4.0 * p * ru * ru))
        return (1.0 - p) * ru + p * 2.0 * np.sin(np.arctan(ru) / 2.0)

    def in_frame(self, x, y, margin: float = 0.0) -> np.ndarray:
        return self.base.in_frame(x, y, margin)

    def vector_to_pixel(self, v):
        v = np.atleast_2d(np.asarray(v, dtype=float))
        vz = v[:, 2]
        front = vz > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(front, v[:, 0] / vz, np.nan)
            w = np.where(front, v[:, 1] / vz, np.nan)
            ru = np.hypot(u, w)
            scale = np.where(ru > 0, self.radial(ru) / ru, 1.0)
        b = self.base
        return b.cx + b.f * u * scale, b.cy + b.f * w * scale

    def to_dict(self) -> dict:
        return {
            **self.base.to_dict(),
            "radial_model": self.model,
            "corner_shift_px": float(self.corner_shift_px),
            "radial_param": float(self.param),
        }


# ----------------------------------------------------------------------------- detector and sky


def sky_gradient_e(shape, lo_e: float, hi_e: float, angle_rad: float) -> np.ndarray:
    """Linear sky ramp (e- per pixel over the exposure) from ``lo_e`` to ``hi_e`` across the array
    along direction ``angle_rad`` (0 = +x, toward increasing column)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    t = np.cos(angle_rad) * xx + np.sin(angle_rad) * yy
    t = (t - t.min()) / max(t.max() - t.min(), 1e-12)
    return lo_e + (hi_e - lo_e) * t


def hot_clusters_e(
    shape, n: int, rng: np.random.Generator, e_range: tuple[float, float] = (100.0, 3000.0), sizes=(2, 3)
):
    """``n`` square clusters of hot pixels (side drawn from ``sizes``), each pixel with a dark
    signal uniform in ``e_range`` (e- over the exposure). Returns (map e-, [[row, col, side], ...])."""
    h, w = shape
    out = np.zeros(shape)
    where = []
    for _ in range(n):
        side = int(rng.choice(sizes))
        r, c = int(rng.integers(0, h - side)), int(rng.integers(0, w - side))
        out[r : r + side, c : c + side] += rng.uniform(*e_range, size=(side, side))
        where.append([r, c, side])
    return out, where


def apply_bad_columns(frame: Frame, columns: list[tuple[int, str]], offset_dn: float = 300.0) -> Frame:
    """Column defects on the DN frame: ``(col, kind)`` with kind ``stuck`` (white level),
    ``dead`` (black level) or ``hot`` (+``offset_dn``, clipped to white)."""
    px = frame.pixels.astype(np.int64)
    black = int(round(frame.black_level[0]))
    white = int(frame.white_level)
    for col, kind in columns:
        if kind == "stuck":
            px[:, col] = white
        elif kind == "dead":
            px[:, col] = black
        elif kind == "hot":
            px[:, col] = np.minimum(px[:, col] + int(offset_dn), white)
        else:
            raise ValueError(f"unknown column defect {kind!r}")
    return replace(frame, pixels=px.astype(frame.pixels.dtype))


# ----------------------------------------------------------------------------------------- scene


def _subset(stars: Stars, idx) -> Stars:
    return Stars(stars.ids[idx], stars.vectors[idx], stars.vmag[idx], stars.rg[idx], stars.bg[idx])


def stars_in_cone(stars: Stars, attitude: np.ndarray, half_angle_rad: float) -> Stars:
    """Stars within ``half_angle_rad`` of the boresight (+z of ``attitude``, v_sensor = A v_icrs)."""
    z = np.asarray(attitude, dtype=float)[2]
    return _subset(stars, np.flatnonzero(stars.vectors @ z >= np.cos(half_angle_rad)))


def drop_stars(stars: Stars, fraction: float, rng: np.random.Generator) -> tuple[Stars, np.ndarray]:
    """Remove ``round(fraction * N)`` stars at random (missed detections, e.g. behind a cloud
    or a dust speck). Returns (kept stars in the original order, dropped ids)."""
    n = len(stars.ids)
    drop = rng.choice(n, size=int(round(fraction * n)), replace=False)
    keep = np.setdiff1d(np.arange(n), drop)
    return _subset(stars, keep), stars.ids[np.sort(drop)]


def scintillate(stars: Stars, sigma: float, rng: np.random.Generator) -> Stars:
    """Per-star flux times a log-normal factor ``exp(sigma N(0,1) - sigma^2 / 2)`` (mean 1):
    ``vmag`` changes by ``-2.5 log10`` of it."""
    f = np.exp(sigma * rng.standard_normal(len(stars.ids)) - 0.5 * sigma**2)
    return replace(stars, vmag=stars.vmag - 2.5 * np.log10(f))


def blackbody_colours(bv, rg, bg, qe=None) -> tuple[np.ndarray, np.ndarray]:
    """Colour ratios of a Planck spectrum at the Ballesteros temperature of ``bv`` through
    ``qe`` (default: the shipped detector QE, its full band); entries without a usable B-V
    (NaN or bluer than ``BV_PHYSICAL_MIN``) keep ``rg``/``bg``. Interpolated in log T on a
    400-point grid (< 1e-5 relative)."""
    from ground.catalog.colour import BV_PHYSICAL_MIN, ballesteros_temperature, blackbody_ratios, default_qe

    qe = qe or default_qe()
    bv = np.asarray(bv, dtype=float)
    rg, bg = np.array(rg, dtype=float), np.array(bg, dtype=float)
    ok = np.isfinite(bv) & (bv > BV_PHYSICAL_MIN)
    if ok.any():
        temp = ballesteros_temperature(bv[ok])
        grid = np.geomspace(temp.min(), temp.max() * 1.0001, 400)
        rg_grid, bg_grid = blackbody_ratios(qe, grid, qe.band)
        rg[ok] = np.interp(np.log(temp), np.log(grid), rg_grid)
        bg[ok] = np.interp(np.log(temp), np.log(grid), bg_grid)
    return rg, bg


def blackbody_sky_stars(m_limit: float = 6.5, epoch: float = 2025.0) -> Stars:
    """``ground.sim.sky_model.sky_stars`` (same stars, order and V), with colour ratios from
    :func:`blackbody_colours` instead of the catalog's MK-template / colour-index model
    (median 3 % apart in rg and bg, 11 % / 13 % at the 90th percentile)."""
    from ground.catalog.build import load_source
    from ground.catalog.colour import load_qe_csv
    from ground.catalog.design import CatalogDesign
    from ground.sim.sky_model import sky_stars

    base = sky_stars(m_limit, epoch)
    design = CatalogDesign(m_thresh=m_limit, epoch=epoch)
    table = load_source(design)
    if table.epoch != epoch:
        table = table.at_epoch(epoch)
    keep = np.flatnonzero(np.isfinite(table.vmag) & (table.vmag <= m_limit))
    if not np.array_equal(table.star_id[keep], base.ids):
        raise RuntimeError("sky star selection changed: blackbody_sky_stars must follow sky_model.sky_stars")
    qe = load_qe_csv(design.qe_path) if design.qe_path else None
    rg, bg = blackbody_colours(table.bv[keep], base.rg, base.bg, qe)
    return replace(base, rg=rg, bg=bg)


def planet(x: float, y: float, electrons_g: float, rg: float, bg: float) -> FalseObject:
    """A bright point source not in any star catalog (PSF-shaped; e- green channel total)."""
    return FalseObject("planet", float(x), float(y), float(electrons_g), float(rg), float(bg))


false_star = planet  #: a non-catalog point source (ghost, nova, asteroid): same model as a planet


def streak(x: float, y: float, x2: float, y2: float, electrons_per_px: float, rg=1.0, bg=1.0) -> FalseObject:
    """Satellite / aircraft trail from (x, y) to (x2, y2) with ``electrons_per_px`` green e- per
    pixel of length (PSF-shaped across)."""
    length = float(np.hypot(x2 - x, y2 - y))
    return FalseObject(
        "satellite", float(x), float(y), float(electrons_per_px * length), float(rg), float(bg), float(x2), float(y2)
    )
