"""Centroid and colour fit on the raw CFA pixels of a small window around each candidate.

Model for the background-subtracted-by-black DN in window pixel ``(r, c)`` of channel
``k`` (R, G, B for a Bayer frame; one channel for mono)::

    m(r, c) = b_k + A_k * Ex(c) * Ey(r)
    Ex(c)   = 1/2 [erf((c + 1/2 - x0) / (sqrt 2 s)) - erf((c - 1/2 - x0) / (sqrt 2 s))]

i.e. a Gaussian PSF of standard deviation ``s`` with a common centre ``(x0, y0)``,
integrated over each pixel (docs/CONVENTIONS.md pixel centres), per-channel amplitudes
``A_k`` (the channel totals of the colour-ratio convention, in DN) and per-channel
backgrounds ``b_k``. Weighted non-linear least squares by Levenberg-Marquardt, run on all
windows of a frame at once (numpy arrays of shape (stars, pixels), one iteration loop for
the frame): per-star damping and convergence tests (MINPACK's ftol, xtol, gtol = 1e-8),
at most ``max_nfev`` residual evaluations, analytic Jacobian (forward differences with
``analytic_jacobian=False``, the benchmark baseline). Windows share one shape: pixels off
the frame edge, saturated pixels and pixels cleaned by detection (hot pixels, cosmic-ray
hits) get zero weight, i.e. are excluded. Weights from the background noise per CFA phase
plus the shot noise of an initial linear fit (gain in e-/DN). ``rg = A_R / A_G`` and
``bg = A_B / A_G``; covariances from the Jacobian at the solution by linear propagation
(scaled by the reduced chi-square when it exceeds 1). The fallback when the fit fails is a colour-normalised centre of gravity.
A fit whose sigma is significantly (3 sd) below ``sharp_sigma_fraction`` x the expected
sigma, or a failed fit that ended there (from detection SNR ``sharp_fail_min_snr`` up: a faint
star's failed fit ends anywhere), marks the candidate ``sharp``: a hot pixel or
cosmic-ray hit that the detector's neighbour test let through.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from scipy.special import erf

from firmware_model.pipeline.detect import Detections
from firmware_model.pipeline.raw_frame import BLUE, GREEN, RED, Frame, pattern_codes
from protocol.star_flags import StarFlag

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
    sharp_fail_min_snr: float = 20.0  # a failed fit counts as sharp only from this detection SNR up
    max_nfev: int = 60  # residual evaluations per star (the start counts); not converged: FIT_FAILED
    method: str = "lm"  # "lm": PSF fit; "cog": centre of gravity + linear amplitudes only (fast)
    analytic_jacobian: bool = True  # False: forward-difference Jacobian (benchmark baseline)


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
    d_sigma = -_INV_SQRT2PI / sigma**2 * (up * gu - lo * gl)
    return e, d_centre, d_sigma


class _WindowModel:
    """Residuals and Jacobian of the PSF model on one window (flattened valid pixels): the
    one-window reference of ``_Windows`` (tests), and its linear solve for degenerate windows."""

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
    """Fit every candidate of ``det`` in ``frame`` (module docstring), all windows together."""
    n = len(det)
    out = FitResults(
        x=np.full(n, np.nan),
        y=np.full(n, np.nan),
        sigma=np.full(n, np.nan),
        amp=np.full((n, 3), np.nan),
        background=np.full((n, 3), np.nan),
        cov_xy=np.full((n, 2, 2), np.nan),
        rg=np.full(n, np.nan),
        bg=np.full(n, np.nan),
        cov_colour=np.full((n, 2, 2), np.nan),
        reduced_chi2=np.full(n, np.nan),
        n_pixels=np.zeros(n, int),
        flags=np.asarray(det.flags, dtype=np.int32).copy(),
        sharp=np.zeros(n, bool),
    )
    if params.method not in ("lm", "cog"):
        raise ValueError(f"unknown fit method {params.method!r}; expected 'lm' or 'cog'")
    if n == 0:
        return out
    gain = float(frame.metadata.get("gain_e_per_dn", params.gain_e_per_dn)) if frame.metadata else params.gain_e_per_dn
    _fit_all(frame, det, params, gain, out)
    return out


def _pixel_gaussian_rows(coords, centre, sigma):
    """``pixel_gaussian_1d`` for N rows of consecutive pixel coordinates (N, W) with one
    centre and sigma per row; erf and exp are evaluated once per pixel edge (W + 1)."""
    edges = np.concatenate([coords - 0.5, coords[:, -1:] + 0.5], axis=1) - centre[:, None]
    sig = sigma[:, None]
    erfs = erf(edges / (_SQRT2 * sig))
    gs = np.exp(-0.5 * (edges / sig) ** 2)
    ug = edges * gs
    e = 0.5 * (erfs[:, 1:] - erfs[:, :-1])
    d_centre = -_INV_SQRT2PI / sig * (gs[:, 1:] - gs[:, :-1])
    d_sigma = -_INV_SQRT2PI / sig**2 * (ug[:, 1:] - ug[:, :-1])
    return e, d_centre, d_sigma


def _bad_mask(bad_pixels: np.ndarray, n_pixels: int) -> np.ndarray:
    """A mask of ``bad_pixels`` (linear indices) over a frame of ``n_pixels``, and one entry past
    its end (False) for any index beyond it; looked up instead of ``np.isin``, whose hash-based ``np.unique``
    (numpy >= 2.3) holds the GIL on a frame of many hot pixels and stalls the device's link thread
    (docs/bad_input.md; an index out of the frame is in no window's valid pixels either way)."""
    mask = np.zeros(n_pixels + 1, bool)
    bad = np.asarray(bad_pixels, np.int64)
    mask[bad[(bad >= 0) & (bad < n_pixels)]] = True
    return mask


class _Windows:
    """All candidate windows of a frame as (N, P) arrays, P = (2 hw + 1)^2 pixels in row-major
    order. Pixels outside the frame, saturated or cleaned by detection have ``valid`` False
    and weight 0, so windows clipped by the frame edge share the array shape."""

    def __init__(self, frame, det, hw):
        n, w = len(det), 2 * hw + 1
        off = np.arange(-hw, hw + 1)
        xc = np.rint(np.asarray(det.x, float)).astype(np.int64)  # round half to even, as round()
        yc = np.rint(np.asarray(det.y, float)).astype(np.int64)
        r, c = yc[:, None] + off[None, :], xc[:, None] + off[None, :]  # (N, W) int
        self.n, self.side, self.p = n, w, w * w
        self.row_coords, self.col_coords = r.astype(float), c.astype(float)
        inb = (((r >= 0) & (r < frame.height))[:, :, None] & ((c >= 0) & (c < frame.width))[:, None, :]).reshape(n, -1)
        rr, cc = np.clip(r, 0, frame.height - 1), np.clip(c, 0, frame.width - 1)
        raw = frame.pixels[rr[:, :, None], cc[:, None, :]].reshape(n, -1)
        ri = np.broadcast_to((r % 2)[:, :, None], (n, w, w)).reshape(n, -1)
        ci = np.broadcast_to((c % 2)[:, None, :], (n, w, w)).reshape(n, -1)
        black = np.asarray(frame.black_level, dtype=float).reshape(2, 2)[ri, ci]
        self.data = raw.astype(float) - black
        self.noise = np.asarray(det.noise, dtype=float)[np.arange(n)[:, None], ri, ci]
        self.edge = ~inb.all(axis=1)
        unsat = raw < frame.white_level
        self.saturated = np.any(inb & ~unsat, axis=1)
        valid = inb & unsat
        if len(det.bad_pixels):
            lin = (r.astype(np.int64)[:, :, None] * frame.width + c.astype(np.int64)[:, None, :]).reshape(n, -1)
            n_pixels = frame.height * frame.width  # pixels out of the frame are not valid already
            valid &= ~_bad_mask(det.bad_pixels, n_pixels)[np.clip(lin, 0, n_pixels)]
        self.valid = valid
        if frame.is_mono:
            self.chan, self.nchan, self.slots = np.zeros((n, self.p), int), 1, [GREEN]
        else:
            self.chan, self.nchan, self.slots = pattern_codes(frame.pattern)[ri, ci].astype(int), 3, [RED, GREEN, BLUE]
        self.onehot = (self.chan[:, :, None] == np.arange(self.nchan)[None, None, :]) & valid[:, :, None]
        self.onehot = self.onehot.astype(float)
        self.n_valid = valid.sum(axis=1)
        self.n_per_chan = self.onehot.sum(axis=1)
        self.w = np.where(valid, 1.0 / self.noise, 0.0)  # residual weights, 0 = pixel ignored

    def select(self, idx):
        """Copy restricted to stars ``idx``."""
        sub = object.__new__(_Windows)
        for k, v in vars(self).items():
            sub.__dict__[k] = v[idx] if isinstance(v, np.ndarray) and v.ndim and v.shape[0] == self.n else v
        sub.n = len(idx)
        return sub

    def psf(self, x0, y0, s, derivatives=False):
        """Pixel-integrated PSF (N, P) at per-star centres and sigmas; with derivatives also
        d/dx0, d/dy0, d/ds."""
        ex, dex, dsx = _pixel_gaussian_rows(self.col_coords, x0, s)
        ey, dey, dsy = _pixel_gaussian_rows(self.row_coords, y0, s)
        n = len(x0)
        psf = (ey[:, :, None] * ex[:, None, :]).reshape(n, -1)
        if not derivatives:
            return psf
        d_x = (ey[:, :, None] * dex[:, None, :]).reshape(n, -1)
        d_y = (dey[:, :, None] * ex[:, None, :]).reshape(n, -1)
        d_s = (dsy[:, :, None] * ex[:, None, :] + ey[:, :, None] * dsx[:, None, :]).reshape(n, -1)
        return psf, d_x, d_y, d_s

    def per_pixel(self, v):
        """Per-channel values v (N, nchan) at every window pixel (N, P)."""
        if self.nchan == 1:
            return np.broadcast_to(v, (len(v), self.p))
        return v.ravel()[self.chan + self.nchan * np.arange(len(v))[:, None]]

    def model(self, p):
        """Model DN (N, P) for parameters p (N, 3 + 2 nchan)."""
        k = self.nchan
        psf = self.psf(p[:, 0], p[:, 1], p[:, 2])
        amp, bkg = self.per_pixel(p[:, 3 : 3 + k]), self.per_pixel(p[:, 3 + k :])
        return bkg + amp * psf

    def residuals(self, p, w):
        return (self.model(p) - self.data) * w

    def jacobian(self, p, w):
        """Weighted analytic Jacobian (N, P, 3 + 2 nchan) of the residuals."""
        k = self.nchan
        psf, d_x, d_y, d_s = self.psf(p[:, 0], p[:, 1], p[:, 2], derivatives=True)
        amp = self.per_pixel(p[:, 3 : 3 + k])
        oh = self.onehot
        jac = np.concatenate([np.stack([amp * d_x, amp * d_y, amp * d_s], axis=2), oh * psf[:, :, None], oh], axis=2)
        return jac * w[:, :, None]

    def jacobian_fd(self, p, w):
        """Weighted forward-difference Jacobian (as scipy's "2-point"): the baseline."""
        r0 = self.residuals(p, w)
        jac = np.empty(r0.shape + (p.shape[1],))
        for j in range(p.shape[1]):
            h = _FD_STEP * np.where(p[:, j] >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(p[:, j]))
            q = p.copy()
            q[:, j] += h
            h = q[:, j] - p[:, j]
            jac[:, :, j] = (self.residuals(q, w) - r0) / h[:, None]
        return jac

    def linear_solve(self, x0, y0, s, w):
        """Weighted linear least squares for amplitudes and backgrounds (N, 2 nchan) at fixed
        shape: per channel a 2 x 2 normal system (amplitude and background of one channel do
        not couple to the others); degenerate windows are solved with lstsq as before."""
        psf = self.psf(x0, y0, s)
        w2 = w**2
        woh = self.onehot * w2[:, :, None]
        s11 = woh.sum(axis=1)
        sp1 = np.einsum("np,npk->nk", psf, woh)
        spp = np.einsum("np,npk->nk", psf**2, woh)
        spd = np.einsum("np,npk->nk", psf * self.data, woh)
        s1d = np.einsum("np,npk->nk", self.data, woh)
        det = spp * s11 - sp1**2
        with np.errstate(divide="ignore", invalid="ignore"):
            amp = (s11 * spd - sp1 * s1d) / det
            bkg = (spp * s1d - sp1 * spd) / det
        sol = np.concatenate([amp, bkg], axis=1)
        bad = ~(np.all(det > 1e-9 * spp * s11, axis=1) & np.all(np.isfinite(sol), axis=1))
        for i in np.flatnonzero(bad):
            v = self.valid[i]
            a = np.column_stack([self.onehot[i][v] * psf[i][v][:, None], self.onehot[i][v]]) * w[i][v][:, None]
            sol[i], *_ = np.linalg.lstsq(a, self.data[i][v] * w[i][v], rcond=None)
        return sol

    def centre_of_gravity(self, lin):
        """Centre of gravity of the background-subtracted windows, each channel scaled to
        green by the linear-fit amplitudes when they are all positive (NaN without signal)."""
        k = self.nchan
        amp, bkg = lin[:, :k], lin[:, k:]
        sig = self.data - np.take_along_axis(bkg, self.chan, axis=1)
        if k == 3:
            pos = np.all(amp > 0, axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                scale = np.where(pos[:, None], amp[:, GREEN : GREEN + 1] / amp, 1.0)
            sig = sig * np.take_along_axis(scale, self.chan, axis=1)
        sig = np.where(self.valid, np.maximum(sig, 0.0), 0.0)
        total = sig.sum(axis=1)
        sig3 = sig.reshape(self.n, self.side, self.side)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = (sig3.sum(axis=1) * self.col_coords).sum(axis=1) / total
            y = (sig3.sum(axis=2) * self.row_coords).sum(axis=1) / total
        ok = total > 0
        return np.where(ok, x, np.nan), np.where(ok, y, np.nan)


_FD_STEP = np.sqrt(np.finfo(float).eps)
_TOL = 1e-8  # ftol, xtol, gtol as scipy.optimize.least_squares defaults


def _levenberg_marquardt(win, p0, w, params):
    """Levenberg-Marquardt on all windows at once: per-star damping (Marquardt scaling by
    the Jacobian column norms; lambda x4 after a step whose gain ratio (actual / predicted
    reduction) is below 0.5, /3 above 0.75), per-star convergence tests as
    MINPACK's (ftol, xtol, gtol = 1e-8), at most ``params.max_nfev`` residual evaluations
    (the start counts as one). Returns parameters, residuals at them, converged flags and
    a finite-start flag (N,); the Jacobian is analytic or, with ``params.analytic_jacobian``
    False, forward differences (the benchmark baseline)."""
    n, m = p0.shape
    p = p0.copy()
    r = win.residuals(p, w)
    cost = 0.5 * np.sum(r**2, axis=1)
    started = np.isfinite(cost)
    conv = np.zeros(n, bool)
    lam = np.full(n, 1e-3)
    a = np.zeros((n, m, m))
    g = np.zeros((n, m))
    need = started.copy()  # stars whose Jacobian must be (re)computed
    nfev = 1
    eye = np.eye(m)
    cached: list[Any] = [np.zeros(0, int), None]  # indices and windows of the last subset

    def sel(idx):
        if not np.array_equal(cached[0], idx):
            cached[:] = [idx, win.select(idx)]
        return cached[1]

    while nfev < params.max_nfev:
        work = np.flatnonzero(started & ~conv)
        if not len(work):
            break
        upd = work[need[work]]
        if len(upd):
            sub = sel(upd)
            jac = (sub.jacobian if params.analytic_jacobian else sub.jacobian_fd)(p[upd], w[upd])
            a[upd] = np.matmul(jac.transpose(0, 2, 1), jac)
            g[upd] = np.einsum("npm,np->nm", jac, r[upd])
            need[upd] = False
        d = np.sqrt(np.diagonal(a[work], axis1=1, axis2=2))
        d = np.where(d > 0, d, 1.0)
        # gtol: the residual vector is (nearly) orthogonal to every Jacobian column
        rnorm = np.sqrt(2.0 * cost[work])
        with np.errstate(divide="ignore", invalid="ignore"):
            gmax = np.max(np.abs(g[work]) / d, axis=1) / rnorm
        done = (gmax <= _TOL) | (rnorm == 0)
        conv[work[done]] = True
        work, d = work[~done], d[~done]
        if not len(work):
            break
        a_s = a[work] / (d[:, :, None] * d[:, None, :]) + lam[work, None, None] * eye
        g_s = g[work] / d
        try:
            step_s = np.linalg.solve(a_s, -g_s[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            step_s = np.stack([np.linalg.lstsq(a_s[i], -g_s[i], rcond=None)[0] for i in range(len(work))])
        step = step_s / d
        p_new = p[work] + step
        r_new = sel(work).residuals(p_new, w[work])
        nfev += 1
        cost_new = 0.5 * np.sum(r_new**2, axis=1)
        actual = cost[work] - cost_new
        pred = -np.einsum("nm,nm->n", g[work], step) - 0.5 * np.einsum("nm,nmk,nk->n", step, a[work], step)
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = np.where(pred > 0, actual / pred, -1.0)
        rho = np.where(np.isfinite(cost_new), rho, -1.0)
        acc = rho > 1e-4
        # ftol: neither the actual nor the predicted reduction is significant
        f_done = (np.abs(actual) <= _TOL * cost[work]) & (pred <= _TOL * cost[work]) & (rho <= 2.0)
        f_done &= np.isfinite(cost_new)
        # xtol: the (scaled) step is tiny against the (scaled) parameters
        x_done = np.sqrt(np.sum(step_s**2, axis=1)) <= _TOL * np.sqrt(np.sum((d * p[work]) ** 2, axis=1))
        ia = work[acc]
        p[ia], r[ia], cost[ia] = p_new[acc], r_new[acc], cost_new[acc]
        need[ia] = True
        # trust-region style damping: shrink the step after a poor quadratic prediction (also
        # on accepted steps: faint, large-residual windows otherwise zig-zag for tens of
        # iterations), widen it after a good one
        rho_w = np.where(acc, rho, 0.0)
        lam[work] *= np.where(rho_w < 0.5, 4.0, np.where(rho_w > 0.75, 1.0 / 3.0, 1.0))
        lam[work] = np.clip(lam[work], 1e-12, 1e12)
        conv[work[f_done | (x_done & acc)]] = True
    return p, r, conv, started


# --- the compiled Levenberg-Marquardt (numba, cached on disk): one star at a time, the same
# algorithm and tests as _levenberg_marquardt (the numpy batched loop, kept as the reference) ---


@njit(cache=True, nogil=True)
def _nb_axis(coords, centre, sigma, e, dc, ds):  # pragma: no cover - compiled
    """pixel_gaussian_1d on one window axis (consecutive coordinates), into e, dc, ds."""
    n = len(coords)
    s2 = math.sqrt(2.0) * sigma
    k0 = 1.0 / math.sqrt(2.0 * math.pi)
    lo = coords[0] - 0.5 - centre
    erf_lo = math.erf(lo / s2)
    g_lo = math.exp(-0.5 * (lo / sigma) ** 2)
    for i in range(n):
        up = coords[i] + 0.5 - centre
        erf_up = math.erf(up / s2)
        g_up = math.exp(-0.5 * (up / sigma) ** 2)
        e[i] = 0.5 * (erf_up - erf_lo)
        dc[i] = -k0 / sigma * (g_up - g_lo)
        ds[i] = -k0 / sigma**2 * (up * g_up - lo * g_lo)
        lo, erf_lo, g_lo = up, erf_up, g_up


@njit(cache=True, nogil=True)
def _nb_residuals(p, data, w, chan, nchan, rowc, colc, ex, dex, dsx, ey, dey, dsy, r):  # pragma: no cover
    """Weighted residuals of one window into r; returns the cost (half the sum of squares)."""
    side = len(colc)
    _nb_axis(colc, p[0], p[2], ex, dex, dsx)
    _nb_axis(rowc, p[1], p[2], ey, dey, dsy)
    cost = 0.0
    for i in range(side):
        for j in range(side):
            k = i * side + j
            if w[k] == 0.0:
                r[k] = 0.0
                continue
            ch = chan[k]
            v = (p[3 + nchan + ch] + p[3 + ch] * (ey[i] * ex[j]) - data[k]) * w[k]
            r[k] = v
            cost += v * v
    return 0.5 * cost


@njit(cache=True, nogil=True)
def _nb_normal(p, w, chan, nchan, rowc, colc, r, ex, dex, dsx, ey, dey, dsy, a, g):  # pragma: no cover
    """Normal matrix J^T J and gradient J^T r of one window's weighted analytic Jacobian (each row
    has five non-zero entries: centre, sigma, its channel's amplitude and background); ``ex`` ...
    ``dsy`` hold the axis profiles at ``p`` (the residuals' last evaluation)."""
    side = len(colc)
    a[:, :] = 0.0
    g[:] = 0.0
    jv = np.empty(5)
    ji = np.empty(5, np.int64)
    for i in range(side):
        for j in range(side):
            k = i * side + j
            wk = w[k]
            if wk == 0.0:
                continue
            ch = chan[k]
            amp = p[3 + ch] * wk
            jv[0] = amp * ey[i] * dex[j]
            jv[1] = amp * dey[i] * ex[j]
            jv[2] = amp * (dsy[i] * ex[j] + ey[i] * dsx[j])
            jv[3] = ey[i] * ex[j] * wk
            jv[4] = wk
            ji[0], ji[1], ji[2], ji[3], ji[4] = 0, 1, 2, 3 + ch, 3 + nchan + ch
            rk = r[k]
            for u in range(5):
                g[ji[u]] += jv[u] * rk
                for v in range(u, 5):
                    a[ji[u], ji[v]] += jv[u] * jv[v]
    m = a.shape[0]
    for u in range(m):
        for v in range(u + 1, m):
            a[v, u] = a[u, v]


@njit(cache=True, nogil=True)
def _nb_solve(a, b, x):  # pragma: no cover - compiled
    """x = a^-1 b by Gaussian elimination with partial pivoting; False if singular."""
    m = len(b)
    t = a.copy()
    y = b.copy()
    for c in range(m):
        piv = c
        for q in range(c + 1, m):
            if abs(t[q, c]) > abs(t[piv, c]):
                piv = q
        if t[piv, c] == 0.0:
            return False
        if piv != c:
            for q in range(m):
                t[c, q], t[piv, q] = t[piv, q], t[c, q]
            y[c], y[piv] = y[piv], y[c]
        for q in range(c + 1, m):
            f = t[q, c] / t[c, c]
            if f != 0.0:
                for u in range(c, m):
                    t[q, u] -= f * t[c, u]
                y[q] -= f * y[c]
    for c in range(m - 1, -1, -1):
        acc = y[c]
        for u in range(c + 1, m):
            acc -= t[c, u] * x[u]
        x[c] = acc / t[c, c]
    return True


@njit(cache=True, nogil=True)
def _nb_levenberg_marquardt(data, w, chan, nchan, rowc, colc, p0, max_nfev, tol):  # pragma: no cover
    """_levenberg_marquardt (analytic Jacobian) for every window, one at a time."""
    n, m = p0.shape
    side = rowc.shape[1]
    p_out = p0.copy()
    r_out = np.zeros(data.shape)
    conv = np.zeros(n, np.bool_)
    started = np.zeros(n, np.bool_)
    ex, dex, dsx = np.empty(side), np.empty(side), np.empty(side)
    ey, dey, dsy = np.empty(side), np.empty(side), np.empty(side)
    a = np.zeros((m, m))
    g = np.zeros(m)
    a_s = np.zeros((m, m))
    g_s = np.zeros(m)
    step_s = np.zeros(m)
    step = np.zeros(m)
    d = np.zeros(m)
    p_new = np.zeros(m)
    r_new = np.zeros(data.shape[1])
    for s in range(n):
        p = p_out[s]
        r = r_out[s]
        ds_, ws, cs, rc, cc = data[s], w[s], chan[s], rowc[s], colc[s]
        cost = _nb_residuals(p, ds_, ws, cs, nchan, rc, cc, ex, dex, dsx, ey, dey, dsy, r)
        if not np.isfinite(cost):
            continue
        started[s] = True
        lam = 1e-3
        need = True
        nfev = 1
        while nfev < max_nfev:
            if need:
                _nb_normal(p, ws, cs, nchan, rc, cc, r, ex, dex, dsx, ey, dey, dsy, a, g)
                need = False
            for u in range(m):
                d[u] = math.sqrt(a[u, u]) if a[u, u] > 0.0 else 1.0
            rnorm = math.sqrt(2.0 * cost)
            if rnorm == 0.0:
                conv[s] = True
                break
            gmax = 0.0
            for u in range(m):
                gmax = max(gmax, abs(g[u]) / d[u])
            if gmax / rnorm <= tol:
                conv[s] = True
                break
            for u in range(m):
                for v in range(m):
                    a_s[u, v] = a[u, v] / (d[u] * d[v])
                a_s[u, u] += lam
                g_s[u] = -g[u] / d[u]
            if not _nb_solve(a_s, g_s, step_s):
                step_s[:] = np.linalg.lstsq(a_s, g_s)[0]
            pn2 = 0.0
            sn2 = 0.0
            for u in range(m):
                step[u] = step_s[u] / d[u]
                p_new[u] = p[u] + step[u]
                sn2 += step_s[u] ** 2
                pn2 += (d[u] * p[u]) ** 2
            cost_new = _nb_residuals(p_new, ds_, ws, cs, nchan, rc, cc, ex, dex, dsx, ey, dey, dsy, r_new)
            nfev += 1
            actual = cost - cost_new
            pred = 0.0
            for u in range(m):
                q = 0.0
                for v in range(m):
                    q += a[u, v] * step[v]
                pred += -g[u] * step[u] - 0.5 * step[u] * q
            finite = np.isfinite(cost_new)
            rho = actual / pred if pred > 0.0 else -1.0
            if not finite or not np.isfinite(rho):
                rho = -1.0
            acc = rho > 1e-4
            f_done = abs(actual) <= tol * cost and pred <= tol * cost and rho <= 2.0 and finite
            x_done = math.sqrt(sn2) <= tol * math.sqrt(pn2)
            if acc:
                p[:] = p_new
                r[:] = r_new
                cost = cost_new
                need = True
            rho_w = rho if acc else 0.0
            if rho_w < 0.5:
                lam *= 4.0
            elif rho_w > 0.75:
                lam *= 1.0 / 3.0
            lam = min(max(lam, 1e-12), 1e12)
            if f_done or (x_done and acc):
                conv[s] = True
                break
    return p_out, r_out, conv, started


def _fit_all(frame, det, params, gain, out):
    s0 = params.psf_sigma_px
    hw = params.half_width_px or max(3, int(np.ceil(3.0 * s0)) + 1)
    allwin = _Windows(frame, det, hw)
    flags = out.flags.astype(np.int64)
    flags[allwin.edge] |= int(StarFlag.EDGE)
    flags[allwin.saturated] |= int(StarFlag.SATURATED)
    nchan, slots = allwin.nchan, allwin.slots
    if nchan == 1:
        flags |= int(StarFlag.NO_COLOUR)
    usable = (allwin.n_valid >= 2 * nchan + 4) & np.all(allwin.n_per_chan >= 2, axis=1)
    flags[~usable] |= int(StarFlag.FIT_FAILED)
    out.flags[:] = flags
    idx = np.flatnonzero(usable)
    if not len(idx):
        return
    win = allwin.select(idx)
    nw = len(idx)
    sig0 = np.full(nw, float(s0))
    dx, dy = np.asarray(det.x, float)[idx], np.asarray(det.y, float)[idx]
    w0 = win.w
    lin = win.linear_solve(dx, dy, sig0, w0)
    x_cog, y_cog = win.centre_of_gravity(lin)
    has_cog = np.isfinite(x_cog)
    x_start, y_start = np.where(has_cog, x_cog, dx), np.where(has_cog, y_cog, dy)
    if has_cog.any():
        lin[has_cog] = win.select(np.flatnonzero(has_cog)).linear_solve(
            x_start[has_cog], y_start[has_cog], sig0[has_cog], w0[has_cog]
        )
    # shot-noise weights from the starting model, then held fixed through the fit
    p0 = np.column_stack([x_start, y_start, sig0, lin])
    star = np.maximum(win.model(p0) - np.take_along_axis(lin[:, nchan:], win.chan, axis=1), 0.0)
    w = np.where(win.valid, 1.0 / np.sqrt(win.noise**2 + star / gain), 0.0)
    p0[:, 3:] = win.linear_solve(x_start, y_start, sig0, w)
    out.n_pixels[idx] = win.n_valid
    green = 3 + slots.index(GREEN) if nchan == 3 else 3
    if params.method == "cog":
        for j in np.flatnonzero(has_cog):
            i = idx[j]
            out.x[i], out.y[i] = x_cog[j], y_cog[j]
            _store_amplitudes(out, i, p0[j, 3:], slots, nchan)
        fit = np.flatnonzero(~has_cog)  # no centre of gravity: the PSF fit after all
    else:
        fit = np.arange(nw)
    if not len(fit):
        return
    fwin = win.select(fit)
    if params.analytic_jacobian:
        p, r, conv, started = _nb_levenberg_marquardt(
            fwin.data,
            np.ascontiguousarray(w[fit]),
            fwin.chan,
            nchan,
            fwin.row_coords,
            fwin.col_coords,
            p0[fit],
            params.max_nfev,
            _TOL,
        )
    else:
        p, r, conv, started = _levenberg_marquardt(fwin, p0[fit], w[fit], params)
    shift = np.hypot(p[:, 0] - x_start[fit], p[:, 1] - y_start[fit])
    abs_s = np.abs(p[:, 2])
    ok = (
        started
        & conv
        & (shift <= params.max_shift_px)
        & (params.sigma_range_px[0] <= abs_s)
        & (abs_s <= params.sigma_range_px[1])
        & (p[:, green] > 0)
    )
    # a failed fit that shrank the PSF far below the optics' is not a star either, when the candidate
    # was bright enough for its fit to mean something (a faint star's failed fit wanders anywhere)
    bright = np.asarray(det.snr, float)[idx[fit]] >= params.sharp_fail_min_snr
    too_narrow = abs_s < max(params.sigma_range_px[0], params.sharp_sigma_fraction * params.psf_sigma_px)
    sharp_fail = started & bright & too_narrow
    for j in np.flatnonzero(~ok):
        i, k = idx[fit[j]], fit[j]
        out.sharp[i] = sharp_fail[j]
        if has_cog[k]:
            out.x[i], out.y[i] = x_cog[k], y_cog[k]
        else:
            out.x[i], out.y[i] = det.x[i], det.y[i]
        _store_amplitudes(out, i, lin[k], slots, nchan)
        out.flags[i] = int(out.flags[i]) | int(StarFlag.FIT_FAILED)
    good = np.flatnonzero(ok)
    if not len(good):
        return
    pg = p[good].copy()
    pg[:, 2] = np.abs(pg[:, 2])
    m = pg.shape[1]
    gwin = fwin.select(good)
    dof = np.maximum(gwin.n_valid - m, 1)
    chi2r = np.sum(r[good] ** 2, axis=1) / dof
    # covariance from the Jacobian at the solution (the one the fit used: analytic or differences)
    jac = (gwin.jacobian if params.analytic_jacobian else gwin.jacobian_fd)(p[good], w[fit][good])
    cov = _inverse_normal(np.matmul(jac.transpose(0, 2, 1), jac)) * np.maximum(chi2r, 1.0)[:, None, None]
    sharp_ok = (
        pg[:, 2] + 3.0 * np.sqrt(np.maximum(cov[:, 2, 2], 0.0)) < params.sharp_sigma_fraction * params.psf_sigma_px
    )
    ii = idx[fit[good]]
    out.x[ii], out.y[ii], out.sigma[ii] = pg[:, 0], pg[:, 1], pg[:, 2]
    out.sharp[ii] = sharp_ok
    out.cov_xy[ii] = cov[:, :2, :2]
    out.reduced_chi2[ii] = chi2r
    _store_amplitudes_many(out, ii, pg[:, 3:], slots, nchan)
    if nchan == 3:
        a_r, a_g, a_b = pg[:, 3], pg[:, 4], pg[:, 5]
        z = np.zeros_like(a_g)
        gm = np.stack(
            [np.stack([1.0 / a_g, -a_r / a_g**2, z], axis=1), np.stack([z, -a_b / a_g**2, 1.0 / a_g], axis=1)], axis=1
        )
        out.rg[ii], out.bg[ii] = a_r / a_g, a_b / a_g
        out.cov_colour[ii] = gm @ cov[:, 3:6, 3:6] @ gm.transpose(0, 2, 1)
    poor = chi2r > params.max_reduced_chi2
    out.flags[ii[poor]] |= int(StarFlag.POOR_FIT)


def _inverse_normal(a):
    """Inverses of the normal matrices a (N, M, M), Jacobi-scaled for conditioning; NaN
    where singular."""
    d = np.sqrt(np.diagonal(a, axis1=1, axis2=2))
    d = np.where(d > 0, d, 1.0)
    s = a / (d[:, :, None] * d[:, None, :])
    try:
        inv = np.linalg.inv(s)
    except np.linalg.LinAlgError:
        inv = np.empty_like(s)
        for i in range(len(s)):
            try:
                inv[i] = np.linalg.inv(s[i])
            except np.linalg.LinAlgError:
                inv[i] = np.nan
    return inv / (d[:, :, None] * d[:, None, :])


def _store_amplitudes(out, i, lin, slots, nchan):
    """Amplitudes/backgrounds into their R, G, B slots; linear colour ratios (no covariance)."""
    for k, slot in enumerate(slots):
        out.amp[i, slot], out.background[i, slot] = lin[k], lin[nchan + k]
    if nchan == 3 and lin[1] > 0:
        out.rg[i], out.bg[i] = lin[0] / lin[1], lin[2] / lin[1]


def _store_amplitudes_many(out, ii, lin, slots, nchan):
    """_store_amplitudes for stars ``ii`` at once (``lin`` (len(ii), 2 nchan))."""
    for k, slot in enumerate(slots):
        out.amp[ii, slot], out.background[ii, slot] = lin[:, k], lin[:, nchan + k]
    if nchan == 3:
        pos = lin[:, 1] > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            out.rg[ii[pos]], out.bg[ii[pos]] = lin[pos, 0] / lin[pos, 1], lin[pos, 2] / lin[pos, 1]
