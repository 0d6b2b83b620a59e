"""Centroid and colour fit on the raw CFA pixels of a small window around each candidate.

Model for the background-subtracted-by-black DN in window pixel ``(r, c)`` of channel
``k`` (R, G, B for a Bayer frame; one channel for mono)::

    m(r, c) = b_k + A_k * Ex(c) * Ey(r)
    Ex(c)   = 1/2 [erf((c + 1/2 - x0) / (sqrt 2 s)) - erf((c - 1/2 - x0) / (sqrt 2 s))]

i.e. a Gaussian PSF of standard deviation ``s`` with a common centre ``(x0, y0)``,
integrated over each pixel (docs/CONVENTIONS.md pixel centres), per-channel amplitudes
``A_k`` (the channel totals of the colour-ratio convention, in DN) and per-channel
backgrounds ``b_k``. Weighted non-linear least squares (Levenberg-Marquardt, MINPACK via
``scipy.optimize.least_squares``, analytic Jacobian); weights from the background noise
per CFA phase plus the shot noise of an initial linear fit (gain in e-/DN). Saturated
pixels and pixels cleaned by detection (hot pixels, cosmic-ray hits) are excluded. ``rg = A_R / A_G`` and ``bg = A_B / A_G``; covariances by
linear propagation of the fit covariance (scaled by the reduced chi-square when it
exceeds 1). The fallback when the fit fails is a colour-normalised centre of gravity.
A fit whose sigma is significantly (3 sd) below ``sharp_sigma_fraction`` x the expected
sigma, or a failed fit that ended there, marks the candidate ``sharp``: a hot pixel or
cosmic-ray hit that the detector's neighbour test let through.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.special import erf

from firmware_model.detect import Detections
from firmware_model.frame import Frame, pattern_codes, RED, GREEN, BLUE
from firmware_model.star_flags import StarFlag

_SQRT2 = np.sqrt(2.0)
_INV_SQRT2PI = 1.0 / np.sqrt(2.0 * np.pi)


@dataclass(frozen=True)
class FitParams:
    """Window fit settings."""

    psf_sigma_px: float = 1.0  # starting PSF sigma (px); the fit frees it
    half_width_px: int = 0  # window half width; 0 = max(3, ceil(3 sigma) + 1)
    gain_e_per_dn: float = 1.6  # for shot-noise weights; frame.metadata["gain_e_per_dn"] wins
    max_reduced_chi2: float = 3.0  # above: POOR_FIT
    max_shift_px: float = 2.5  # fitted centre must stay this close to the start
    sigma_range_px: tuple = (0.3, 6.0)  # fitted sigma outside: FIT_FAILED
    sharp_sigma_fraction: float = 0.5  # fitted sigma (+3 sd) below this x psf_sigma_px: sharp artefact
    max_nfev: int = 60
    method: str = "lm"  # "lm": PSF fit; "cog": centre of gravity + linear amplitudes only (fast)
    analytic_jacobian: bool = True  # False: finite differences (benchmark baseline)


@dataclass
class FitResults:
    """Per-star fit results (arrays of length N, or (N, ...)). Amplitudes/backgrounds are
    indexed R, G, B (mono: G only, others NaN), DN; covariances in px^2 and ratio^2."""

    x: np.ndarray
    y: np.ndarray
    sigma: np.ndarray
    amp: np.ndarray  # (N, 3)
    background: np.ndarray  # (N, 3)
    cov_xy: np.ndarray  # (N, 2, 2)
    rg: np.ndarray
    bg: np.ndarray
    cov_colour: np.ndarray  # (N, 2, 2) for (rg, bg)
    reduced_chi2: np.ndarray
    n_pixels: np.ndarray
    flags: np.ndarray
    sharp: np.ndarray  # the fit says: much sharper than the PSF (hot pixel, cosmic-ray hit), not a star


def pixel_gaussian_1d(coords: np.ndarray, centre: float, sigma: float):
    """Pixel-integrated unit Gaussian along one axis and its derivatives w.r.t. centre and sigma."""
    up = coords + 0.5 - centre
    lo = coords - 0.5 - centre
    s2 = _SQRT2 * sigma
    e = 0.5 * (erf(up / s2) - erf(lo / s2))
    gu = np.exp(-0.5 * (up / sigma) ** 2)
    gl = np.exp(-0.5 * (lo / sigma) ** 2)
    d_centre = -_INV_SQRT2PI / sigma * (gu - gl)
    d_sigma = -_INV_SQRT2PI / sigma ** 2 * (up * gu - lo * gl)
    return e, d_centre, d_sigma


class _WindowModel:
    """Residuals and Jacobian of the PSF model on one window (flattened valid pixels)."""

    def __init__(self, rows, cols, chan, nchan, weights):
        self.rows, self.cols, self.chan, self.nchan, self.w = rows, cols, chan, nchan, weights
        self.onehot = (chan[:, None] == np.arange(nchan)[None, :]).astype(float)

    def design(self, x0, y0, s):
        ex, dex, dsx = pixel_gaussian_1d(self.cols, x0, s)
        ey, dey, dsy = pixel_gaussian_1d(self.rows, y0, s)
        return ex, dex, dsx, ey, dey, dsy

    def model(self, p):
        x0, y0, s = p[:3]
        amp, bkg = p[3 : 3 + self.nchan], p[3 + self.nchan :]
        ex, _, _, ey, _, _ = self.design(x0, y0, s)
        return bkg[self.chan] + amp[self.chan] * ex * ey

    def residuals(self, p, data):
        return (self.model(p) - data) * self.w

    def jacobian(self, p, data=None):
        x0, y0, s = p[:3]
        amp = p[3 : 3 + self.nchan]
        ex, dex, dsx, ey, dey, dsy = self.design(x0, y0, s)
        a = amp[self.chan]
        cols = [a * dex * ey, a * ex * dey, a * (dsx * ey + ex * dsy)]
        psf = ex * ey
        jac = np.column_stack(cols + [self.onehot * psf[:, None], self.onehot])
        return jac * self.w[:, None]

    def linear_solve(self, x0, y0, s, data):
        """Weighted linear least squares for amplitudes and backgrounds at fixed shape."""
        ex, _, _, ey, _, _ = self.design(x0, y0, s)
        psf = ex * ey
        a = np.column_stack([self.onehot * psf[:, None], self.onehot]) * self.w[:, None]
        sol, *_ = np.linalg.lstsq(a, data * self.w, rcond=None)
        return sol


def fit_stars(frame: Frame, det: Detections, params: FitParams = FitParams()) -> FitResults:
    """Fit every candidate of ``det`` in ``frame`` (module docstring)."""
    n = len(det)
    out = FitResults(
        x=np.full(n, np.nan), y=np.full(n, np.nan), sigma=np.full(n, np.nan), amp=np.full((n, 3), np.nan),
        background=np.full((n, 3), np.nan), cov_xy=np.full((n, 2, 2), np.nan), rg=np.full(n, np.nan),
        bg=np.full(n, np.nan), cov_colour=np.full((n, 2, 2), np.nan), reduced_chi2=np.full(n, np.nan),
        n_pixels=np.zeros(n, int), flags=np.asarray(det.flags, dtype=np.int32).copy(), sharp=np.zeros(n, bool),
    )
    if params.method not in ("lm", "cog"):
        raise ValueError(f"unknown fit method {params.method!r}; expected 'lm' or 'cog'")
    gain = float(frame.metadata.get("gain_e_per_dn", params.gain_e_per_dn)) if frame.metadata else params.gain_e_per_dn
    for i in range(n):
        _fit_one(frame, det, i, params, gain, out)
    return out


def _fit_one(frame, det, i, params, gain, out):
    s0 = params.psf_sigma_px
    hw = params.half_width_px or max(3, int(np.ceil(3.0 * s0)) + 1)
    xc, yc = int(round(det.x[i])), int(round(det.y[i]))
    r0, r1 = max(yc - hw, 0), min(yc + hw + 1, frame.height)
    c0, c1 = max(xc - hw, 0), min(xc + hw + 1, frame.width)
    flags = StarFlag(int(out.flags[i]))
    if (r1 - r0) < 2 * hw + 1 or (c1 - c0) < 2 * hw + 1:
        flags |= StarFlag.EDGE
    rows, cols = np.mgrid[r0:r1, c0:c1]
    rows, cols = rows.ravel().astype(float), cols.ravel().astype(float)
    raw = frame.pixels[r0:r1, c0:c1].ravel()
    ri, ci = rows.astype(int) % 2, cols.astype(int) % 2
    black = np.asarray(frame.black_level, dtype=float).reshape(2, 2)[ri, ci]
    data = raw.astype(float) - black
    noise = det.noise[i][ri, ci]
    valid = raw < frame.white_level
    if not np.all(valid):
        flags |= StarFlag.SATURATED
    if len(det.bad_pixels):
        lin = rows.astype(np.int64) * frame.width + cols.astype(np.int64)
        valid &= ~np.isin(lin, det.bad_pixels, assume_unique=True)
    if frame.is_mono:
        chan_all, nchan, slots = np.zeros(len(raw), int), 1, [GREEN]
        flags |= StarFlag.NO_COLOUR
    else:
        chan_all, nchan, slots = pattern_codes(frame.pattern)[ri, ci].astype(int), 3, [RED, GREEN, BLUE]
    rows, cols, chan, data, noise = rows[valid], cols[valid], chan_all[valid], data[valid], noise[valid]
    if len(data) < 2 * nchan + 4 or np.any(np.bincount(chan, minlength=nchan) < 2):
        out.flags[i] = int(flags | StarFlag.FIT_FAILED)
        return
    wm = _WindowModel(rows, cols, chan, nchan, 1.0 / noise)
    lin = wm.linear_solve(det.x[i], det.y[i], s0, data)
    x_cog, y_cog = _centre_of_gravity(rows, cols, chan, data, lin, nchan)
    if np.isfinite(x_cog):
        lin = wm.linear_solve(x_cog, y_cog, s0, data)
        x_start, y_start = x_cog, y_cog
    else:
        x_start, y_start = det.x[i], det.y[i]
    # shot-noise weights from the starting model, then held fixed through the fit
    p0 = np.concatenate([[x_start, y_start, s0], lin])
    star = np.maximum(wm.model(p0) - lin[nchan:][chan], 0.0)
    wm.w = 1.0 / np.sqrt(noise ** 2 + star / gain)
    p0[3:] = wm.linear_solve(x_start, y_start, s0, data)
    out.n_pixels[i] = len(data)
    if params.method == "cog" and np.isfinite(x_cog):
        out.x[i], out.y[i] = x_cog, y_cog
        _store_amplitudes(out, i, p0[3:], slots, nchan)
        out.flags[i] = int(flags)
        return
    ok = False
    try:
        jac = wm.jacobian if params.analytic_jacobian else "2-point"
        res = least_squares(wm.residuals, p0, jac=jac, args=(data,), method="lm",
                            x_scale="jac", max_nfev=params.max_nfev)
        p = res.x
        # a failed fit that shrank the PSF far below the optics' is not a star either
        out.sharp[i] = abs(p[2]) < max(params.sigma_range_px[0], params.sharp_sigma_fraction * params.psf_sigma_px)
        ok = (res.success and np.hypot(p[0] - x_start, p[1] - y_start) <= params.max_shift_px
              and params.sigma_range_px[0] <= abs(p[2]) <= params.sigma_range_px[1]
              and p[3 + slots.index(GREEN) if nchan == 3 else 3] > 0)
    except (ValueError, np.linalg.LinAlgError):
        pass
    if not ok:
        if np.isfinite(x_cog):
            out.x[i], out.y[i] = x_cog, y_cog
        else:
            out.x[i], out.y[i] = det.x[i], det.y[i]
        _store_amplitudes(out, i, lin, slots, nchan)
        out.flags[i] = int(flags | StarFlag.FIT_FAILED)
        return
    p[2] = abs(p[2])
    dof = max(len(data) - len(p), 1)
    chi2r = float(np.sum(res.fun ** 2) / dof)
    jac = res.jac
    try:
        cov = np.linalg.inv(jac.T @ jac) * max(chi2r, 1.0)
    except np.linalg.LinAlgError:
        cov = np.full((len(p), len(p)), np.nan)
    out.x[i], out.y[i], out.sigma[i] = p[0], p[1], p[2]
    out.sharp[i] = p[2] + 3.0 * np.sqrt(max(cov[2, 2], 0.0)) < params.sharp_sigma_fraction * params.psf_sigma_px
    out.cov_xy[i] = cov[:2, :2]
    out.reduced_chi2[i] = chi2r
    _store_amplitudes(out, i, p[3:], slots, nchan)
    if nchan == 3:
        a_r, a_g, a_b = p[3], p[4], p[5]
        g = np.array([[1.0 / a_g, -a_r / a_g ** 2, 0.0], [0.0, -a_b / a_g ** 2, 1.0 / a_g]])
        out.rg[i], out.bg[i] = a_r / a_g, a_b / a_g
        out.cov_colour[i] = g @ cov[3:6, 3:6] @ g.T
    if chi2r > params.max_reduced_chi2:
        flags |= StarFlag.POOR_FIT
    out.flags[i] = int(flags)


def _store_amplitudes(out, i, lin, slots, nchan):
    """Amplitudes/backgrounds into their R, G, B slots; linear colour ratios (no covariance)."""
    for k, slot in enumerate(slots):
        out.amp[i, slot], out.background[i, slot] = lin[k], lin[nchan + k]
    if nchan == 3 and lin[1] > 0:
        out.rg[i], out.bg[i] = lin[0] / lin[1], lin[2] / lin[1]


def _centre_of_gravity(rows, cols, chan, data, lin, nchan):
    """Centre of gravity of the background-subtracted window, each channel scaled to green
    by the linear-fit amplitudes when they are positive (NaN when there is no signal)."""
    amp, bkg = lin[:nchan], lin[nchan:]
    sig = data - bkg[chan]
    if nchan == 3 and np.all(amp > 0):
        sig = sig * (amp[GREEN] / amp)[chan]
    sig = np.maximum(sig, 0.0)
    total = sig.sum()
    if total <= 0:
        return np.nan, np.nan
    return float((sig * cols).sum() / total), float((sig * rows).sum() / total)
