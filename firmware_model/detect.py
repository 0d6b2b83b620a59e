"""Star detection on the raw CFA (or mono) frame, without demosaicing.

Steps (all vectorised; no Python loop over pixels):

1. The frame is split into its four 2x2 phases (for a Bayer frame each phase is one
   colour channel). Per phase, background and noise (median and 1.4826 MAD) are estimated
   on a coarse grid of ``block_px`` blocks from a 1-in-4 subsample, median-filtered over
   3x3 blocks to shrug off bright stars, and expanded back piecewise constant.
2. The four background-subtracted phases are summed into 2x2 super-pixels (each holds
   R, G, G, B: colour-blind) and box-filtered over 3x3 super-pixels (a matched filter for
   a PSF of ~1-2 px sigma). A super-pixel is significant above ``k_sigma`` times the
   filtered noise.
3. Connected significant regions are labelled; every local maximum (over
   ``peak_separation`` super-pixels) inside a region is a candidate, flagged BLEND when
   its region has more than one.
4. Rejection: hot pixels and cosmic-ray hits are sharper than the PSF (a raw peak whose
   same-colour neighbours hold far less than the PSF predicts); streaks (satellites,
   cosmic-ray tracks) are elongated regions. Candidates are ranked by filtered flux and
   capped at ``max_candidates``.

Pixel coordinates follow docs/CONVENTIONS.md (pixel centres at integers, x = column).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from firmware_model.frame import Frame, GREEN, pattern_codes
from firmware_model.star_flags import StarFlag


@dataclass(frozen=True)
class DetectParams:
    """Detection settings (pixels are raw pixels unless named super-pixels)."""

    k_sigma: float = 5.0  # threshold on the 3x3 super-pixel matched filter
    block_px: int = 128  # background grid block (raw pixels, multiple of 8)
    psf_sigma_px: float = 1.0  # expected PSF Gaussian sigma, for the sharpness test
    sharp_fraction: float = 0.3  # reject if neighbours < this x the PSF-predicted level
    peak_separation: int = 3  # local-maximum footprint (super-pixels)
    max_elongation: float = 3.0  # reject regions whose axis ratio exceeds this (streaks)
    min_streak_area: int = 6  # super-pixels; smaller regions are not tested for elongation
    max_candidates: int = 64  # keep the brightest this many
    max_saturated_fraction: float = 0.5  # above this the frame is declared saturated


@dataclass
class Detections:
    """Candidates, brightest first. ``x, y``: raw-pixel estimate of the peak;
    ``flux``: background-subtracted 3x3 super-pixel sum (DN); ``snr``: flux / its noise;
    ``flags``: StarFlag bits; ``noise``: per-phase noise (DN) at the candidate (N, 2, 2);
    ``background``: per-phase background (DN above black) at the candidate (N, 2, 2).
    ``reason`` says why the list is empty (or what was dropped)."""

    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    snr: np.ndarray
    flags: np.ndarray
    noise: np.ndarray
    background: np.ndarray
    n_rejected_sharp: int = 0
    n_rejected_streak: int = 0
    n_dropped_cap: int = 0
    reason: str = ""

    def __len__(self) -> int:
        return len(self.x)


def _empty(reason: str, **counts) -> Detections:
    z = np.zeros(0)
    return Detections(z, z.copy(), z.copy(), z.copy(), np.zeros(0, np.int32), np.zeros((0, 2, 2)),
                      np.zeros((0, 2, 2)), reason=reason, **counts)


def frame_problem(frame: Frame, params: DetectParams) -> str:
    """Reason the frame cannot hold usable stars, or ''."""
    px = frame.pixels
    lo, hi = px.min(), px.max()
    if lo == hi:
        return f"frame is uniform (every pixel = {lo})"
    sat = float(np.count_nonzero(px >= frame.white_level)) / px.size
    if sat > params.max_saturated_fraction:
        return f"frame is saturated ({100 * sat:.0f}% of pixels at the white level)"
    return ""


def _phase_background(phase: np.ndarray, block: int):
    """Coarse (background, noise) grids of one phase image (block in phase pixels):
    clipped mean and standard deviation of a 1-in-4 subsample, the clip at +-4 sigma about a
    sparse per-block median. Means, not medians: integer DN make medians biased by up to
    0.5 DN, which the 36-pixel matched filter would multiply."""
    b = max(block // 2, 2)
    ny, nx = max(phase.shape[0] // block, 1), max(phase.shape[1] // block, 1)
    dense = phase[: ny * block : 2, : nx * block : 2][: ny * b, : nx * b]
    blocks = dense.reshape(ny, b, nx, b).transpose(0, 2, 1, 3).reshape(ny, nx, b * b)
    sparse = blocks[:, :, :: max((b * b) // 64, 1)]
    med = np.median(sparse, axis=2)
    mad = np.maximum(np.median(np.abs(sparse - med[:, :, None]), axis=2) * 1.4826, 0.5)
    keep = np.abs(blocks - med[:, :, None]) < 4.0 * mad[:, :, None]
    n = np.maximum(keep.sum(axis=2), 1)
    mean = np.where(keep, blocks, 0).sum(axis=2) / n
    var = np.where(keep, (blocks - mean[:, :, None]) ** 2, 0).sum(axis=2) / np.maximum(n - 1, 1)
    # clipping at 4 sigma keeps 99.99% of a Gaussian: no variance correction needed
    return mean, np.sqrt(np.maximum(var, 1.0 / 12.0))  # floor: quantisation noise of 1 DN steps


def _expand(grid: np.ndarray, block: int, shape) -> np.ndarray:
    out = np.repeat(np.repeat(grid, block, axis=0), block, axis=1)
    pad_y, pad_x = max(shape[0] - out.shape[0], 0), max(shape[1] - out.shape[1], 0)
    if pad_y or pad_x:
        out = np.pad(out, ((0, pad_y), (0, pad_x)), mode="edge")
    return out[: shape[0], : shape[1]]


def detect_stars(frame: Frame, params: DetectParams = DetectParams()) -> Detections:
    """Detect star candidates in a raw frame (module docstring)."""
    problem = frame_problem(frame, params)
    if problem:
        return _empty(problem)
    h2, w2 = frame.height // 2, frame.width // 2
    if h2 < 4 or w2 < 4:
        return _empty(f"frame too small for detection ({frame.width} x {frame.height})")
    block = max(params.block_px // 2, 4)  # in phase pixels
    black = np.asarray(frame.black_level, dtype=np.float32).reshape(2, 2)
    resid = np.zeros((h2, w2), np.float32)
    var = np.zeros((h2, w2), np.float32)
    bg_grids, noise_grids = {}, {}
    for py in (0, 1):
        for px_ in (0, 1):
            phase = frame.pixels[py : 2 * h2 : 2, px_ : 2 * w2 : 2].astype(np.float32) - black[py, px_]
            med, sig = _phase_background(phase, block)
            bg_grids[py, px_], noise_grids[py, px_] = med, sig
            resid += phase - _expand(med.astype(np.float32), block, phase.shape)
            var += _expand((sig ** 2).astype(np.float32), block, phase.shape)
    filt = ndimage.uniform_filter(resid, size=3, mode="constant") * 9.0
    noise_filt = 3.0 * np.sqrt(var)  # 9 independent super-pixels
    snr_map = filt / noise_filt
    mask = snr_map > params.k_sigma
    labels, n_regions = ndimage.label(mask)
    if n_regions == 0:
        return _empty("no pixel above the detection threshold")
    pr, pc = _local_maxima(filt, mask, params.peak_separation // 2)
    plabel = labels[pr, pc]
    peaks_per_region = np.bincount(plabel, minlength=n_regions + 1)

    # streaks: second moments of each region's filtered signal (super-pixel units)
    mr_, mc_ = np.nonzero(mask)
    lab = labels[mr_, mc_]
    wgt = np.maximum(filt[mr_, mc_], 0).astype(float)
    nb = n_regions + 1
    area = np.bincount(lab, minlength=nb)
    s0 = np.maximum(np.bincount(lab, wgt, nb), 1e-12)
    m_r = np.bincount(lab, wgt * mr_, nb) / s0
    m_c = np.bincount(lab, wgt * mc_, nb) / s0
    drr, dcc = mr_ - m_r[lab], mc_ - m_c[lab]
    mrr = np.bincount(lab, wgt * drr * drr, nb) / s0
    mcc = np.bincount(lab, wgt * dcc * dcc, nb) / s0
    mrc = np.bincount(lab, wgt * drr * dcc, nb) / s0
    tr, det = mrr + mcc, mrr * mcc - mrc ** 2
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    l1, l2 = tr / 2 + disc, np.maximum(tr / 2 - disc, 1e-3)
    elongated = (area >= params.min_streak_area) & (np.sqrt(l1 / l2) > params.max_elongation)
    is_streak = elongated[plabel]
    n_streak = int(np.count_nonzero(is_streak))
    pr, pc, plabel = pr[~is_streak], pc[~is_streak], plabel[~is_streak]

    # raw peak inside each 2x2 super-pixel's 3x3 neighbourhood and the sharpness test
    sharp = _sharp_peaks(frame, pr, pc, noise_grids, bg_grids, block, params)
    n_sharp = int(np.count_nonzero(sharp))
    pr, pc, plabel = pr[~sharp], pc[~sharp], plabel[~sharp]
    if len(pr) == 0:
        return _empty(
            f"all {n_sharp + n_streak} candidates rejected ({n_sharp} sharp: hot pixels / cosmic rays; "
            f"{n_streak} streaks)", n_rejected_sharp=n_sharp, n_rejected_streak=n_streak)

    flux = filt[pr, pc].astype(float)
    order = np.argsort(-flux)
    n_drop = max(len(order) - params.max_candidates, 0)
    order = order[: params.max_candidates]
    pr, pc, plabel, flux = pr[order], pc[order], plabel[order], flux[order]
    # refine the super-pixel peak with the filtered image's 3x3 centre of mass
    y_sp, x_sp = _subpixel_peak(filt, pr, pc)
    flags = np.where(peaks_per_region[plabel] > 1, int(StarFlag.BLEND), 0).astype(np.int32)
    gy, gx = pr // block, pc // block
    noise = np.empty((len(pr), 2, 2))
    bgv = np.empty((len(pr), 2, 2))
    for a in (0, 1):
        for b in (0, 1):
            noise[:, a, b] = _grid_at(noise_grids[a, b], gy, gx)
            bgv[:, a, b] = _grid_at(bg_grids[a, b], gy, gx)
    reason = f"{n_drop} fainter candidates dropped by the cap of {params.max_candidates}" if n_drop else ""
    return Detections(
        x=2.0 * x_sp + 0.5, y=2.0 * y_sp + 0.5, flux=flux, snr=snr_map[pr, pc].astype(float), flags=flags,
        noise=noise, background=bgv, n_rejected_sharp=n_sharp, n_rejected_streak=n_streak,
        n_dropped_cap=n_drop, reason=reason,
    )


def _local_maxima(img: np.ndarray, mask: np.ndarray, half: int):
    """(rows, cols) of masked pixels that are the maximum of their (2 half + 1)^2 box."""
    r, c = np.nonzero(mask)
    h, w = img.shape
    v = img[r, c]
    is_max = np.ones(len(r), bool)
    for dr in range(-half, half + 1):
        for dc in range(-half, half + 1):
            if dr == 0 and dc == 0:
                continue
            rr, cc = r + dr, c + dc
            inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
            nv = img[np.clip(rr, 0, h - 1), np.clip(cc, 0, w - 1)]
            # ties: keep the first pixel in raster order
            later = (dr > 0) | ((dr == 0) & (dc > 0))
            is_max &= ~inside | (v > nv) | ((v == nv) & later)
    return r[is_max], c[is_max]


def _grid_at(grid: np.ndarray, gy, gx) -> np.ndarray:
    return grid[np.minimum(gy, grid.shape[0] - 1), np.minimum(gx, grid.shape[1] - 1)]


def _subpixel_peak(img: np.ndarray, r: np.ndarray, c: np.ndarray):
    h, w = img.shape
    rr = np.clip(r[:, None, None] + np.arange(-1, 2)[None, :, None], 0, h - 1)
    cc = np.clip(c[:, None, None] + np.arange(-1, 2)[None, None, :], 0, w - 1)
    win = np.maximum(img[rr, cc], 0).astype(float)
    s = win.sum(axis=(1, 2))
    s[s == 0] = 1.0
    dy = (win.sum(axis=2) * np.arange(-1, 2)).sum(axis=1) / s
    dx = (win.sum(axis=1) * np.arange(-1, 2)).sum(axis=1) / s
    return r + dy, c + dx


def _sharp_peaks(frame, pr, pc, noise_grids, bg_grids, block, params) -> np.ndarray:
    """True for candidates whose brightest raw pixel is much sharper than the PSF."""
    if len(pr) == 0:
        return np.zeros(0, bool)
    h, w = frame.height, frame.width
    # brightest raw pixel in the 6x6 raw area around the super-pixel
    r0, c0 = 2 * pr - 2, 2 * pc - 2
    rr = np.clip(r0[:, None, None] + np.arange(6)[None, :, None], 0, h - 1)
    cc = np.clip(c0[:, None, None] + np.arange(6)[None, None, :], 0, w - 1)
    black2 = np.asarray(frame.black_level, dtype=float).reshape(2, 2)
    win = frame.pixels[rr, cc].astype(float) - black2[rr % 2, cc % 2]
    k = np.argmax(win.reshape(len(pr), -1), axis=1)
    r_pk = rr[np.arange(len(pr)), k // 6, 0]
    c_pk = cc[np.arange(len(pr)), 0, k % 6]
    gy, gx = (r_pk // 2) // block, (c_pk // 2) // block

    def level(r, c):
        rc, ccl = np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)
        bgv = np.select([(rc % 2 == a) & (ccl % 2 == b) for a in (0, 1) for b in (0, 1)],
                        [_grid_at(bg_grids[a, b], gy, gx) for a in (0, 1) for b in (0, 1)])
        return frame.pixels[rc, ccl].astype(float) - black2[rc % 2, ccl % 2] - bgv

    peak = level(r_pk, c_pk)
    sig = np.select([(r_pk % 2 == a) & (c_pk % 2 == b) for a in (0, 1) for b in (0, 1)],
                    [_grid_at(noise_grids[a, b], gy, gx) for a in (0, 1) for b in (0, 1)])
    if frame.is_mono:
        offsets, d2 = [(-1, 0), (1, 0), (0, -1), (0, 1)], np.full(len(pr), 1.0)
    else:
        is_green = pattern_codes(frame.pattern)[r_pk % 2, c_pk % 2] == GREEN
        diag, axial = [(-1, -1), (-1, 1), (1, -1), (1, 1)], [(-2, 0), (2, 0), (0, -2), (0, 2)]
        offsets = [(np.where(is_green, a[0], b[0]), np.where(is_green, a[1], b[1])) for a, b in zip(diag, axial)]
        d2 = np.where(is_green, 2.0, 4.0)
    neigh = np.mean([level(r_pk + dr, c_pk + dc) for dr, dc in offsets], axis=0)
    expected_ratio = np.exp(-d2 / (2.0 * params.psf_sigma_px ** 2))
    return neigh + sig < params.sharp_fraction * expected_ratio * peak
