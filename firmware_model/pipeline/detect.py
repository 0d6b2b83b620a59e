"""Star detection on the raw CFA (or mono) frame, without demosaicing.

Steps (vectorised; Python loops only over candidates of multi-peak regions):

1. The frame is split into its four 2x2 phases (for a Bayer frame each phase is one
   colour channel). Per phase, background and noise are the clipped mean and standard
   deviation on a coarse grid of ``block_px`` blocks (1-in-4 subsample, +-4 sigma clip
   about a sparse block median); the background is interpolated bilinearly between block
   centres (no steps on a vignetted sky), the noise expanded piecewise constant.
2. Cosmetic cleaning per phase: a column whose median departs from its neighbours' (stuck,
   dead or offset columns) is shifted to their level and left out of the fit; a pixel above
   ``k_sigma`` whose four same-colour neighbours (adjacent pixels on a mono frame) hold far
   less than the PSF predicts is a hot pixel or cosmic-ray hit; it is replaced for detection
   and listed in ``bad_pixels`` for the fit.
3. The four background-subtracted phases are summed into 2x2 super-pixels (each holds
   R, G, G, B: colour-blind) and filtered with a kernel matched to the PSF (:func:`matched_kernel`:
   [1 2 1] x [1 2 1] up to ~1.3 px sigma, a Gaussian of the PSF's width on super-pixels above:
   a defocused star spread over 8 px loses a third of its SNR to the narrow kernel). A
   super-pixel is significant above ``k_sigma`` times the filtered noise.
4. Connected significant regions are labelled; every local maximum (over
   ``peak_separation`` super-pixels) that is separated from the brighter kept peaks of its
   region within :data:`MERGE_RADIUS_KERNELS` kernel widths by a 3-sigma dip is a candidate,
   flagged BLEND when its region keeps more than one (brightest first, at most
   :data:`REGION_CAP_FACTOR` x ``max_candidates`` kept: bounded work in any clutter).
   Elongated regions (satellite streaks, cosmic-ray tracks) are rejected, and so are
   candidates whose brightest raw pixel holds more of the 6x6 window's signal than a PSF
   can (hot pixels the per-pixel cleaning missed). Candidates are ranked by filtered flux
   and capped at ``max_candidates``.

Pixel coordinates follow docs/CONVENTIONS.md (pixel centres at integers, x = column).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.special import erf, ndtri

from firmware_model.pipeline.raw_frame import Frame
from protocol.star_flags import StarFlag


@dataclass(frozen=True)
class DetectParams:
    """Detection settings (pixels are raw pixels unless named super-pixels)."""

    k_sigma: float = 5.0  # threshold on the super-pixel matched filter (and for sharp pixels)
    block_px: int = 128  # background grid block (raw pixels, multiple of 8)
    psf_sigma_px: float = 1.0  # expected PSF Gaussian sigma, for the sharpness test
    sharp_fraction: float = 0.5  # sharp if same-colour neighbours < this x the PSF-predicted level
    peak_separation: int = 3  # local-maximum footprint (super-pixels)
    max_elongation: float = 3.0  # reject regions whose axis ratio exceeds this (streaks)
    min_streak_area: int = 6  # super-pixels; smaller regions are not tested for elongation
    max_candidates: int = 64  # keep the brightest this many
    max_saturated_fraction: float = 0.5  # above this the frame is declared saturated


@dataclass
class Detections:
    """Candidates, brightest first. ``x, y``: raw-pixel estimate of the peak;
    ``flux``: background-subtracted super-pixel sum weighted by the detection kernel (weights sum
    to 16, as [1 2 1] x [1 2 1]; DN); ``snr``: flux / its noise;
    ``flags``: StarFlag bits; ``noise``: per-phase noise (DN) at the candidate (N, 2, 2);
    ``background``: per-phase background (DN above black) at the candidate (N, 2, 2);
    ``bad_pixels``: sorted linear indices (row * width + col) of pixels cleaned as hot
    pixels or cosmic-ray hits (``n_rejected_sharp`` of them), for the fit to skip.
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
    n_regions: int = 0  #: significant regions found
    n_regions_examined: int = 0  #: of them, the brightest examined (REGION_CAP_FACTOR)
    bad_pixels: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    reason: str = ""

    def __len__(self) -> int:
        return len(self.x)


def _empty(reason: str, **counts) -> Detections:
    z = np.zeros(0)
    return Detections(
        z,
        z.copy(),
        z.copy(),
        z.copy(),
        np.zeros(0, np.int32),
        np.zeros((0, 2, 2)),
        np.zeros((0, 2, 2)),
        reason=reason,
        **counts,
    )


_K121 = np.array([1.0, 2.0, 1.0], dtype=np.float32)


def matched_kernel(psf_sigma_px: float) -> np.ndarray:
    """1-D detection kernel (applied along both axes of the super-pixel image) for a PSF of
    Gaussian sigma ``psf_sigma_px`` (raw px), weights summing to 4: [1 2 1] (sigma 0.71
    super-pixels) while the PSF on super-pixels (sigma/2, widened by the 2x2 binning) is no
    wider, else a Gaussian of that width cut at 3 sigma."""
    s = float(np.sqrt((psf_sigma_px / 2.0) ** 2 + 1.0 / 12.0))
    if s <= np.sqrt(0.5):
        return _K121
    x = np.arange(-int(np.ceil(3.0 * s)), int(np.ceil(3.0 * s)) + 1)
    k = np.exp(-0.5 * (x / s) ** 2)
    return (4.0 * k / k.sum()).astype(np.float32)


#: Significant regions examined at most, as a multiple of ``max_candidates`` (the brightest by
#: filtered peak); beyond it detection work would grow with clutter, not with stars.
REGION_CAP_FACTOR = 8
#: Peaks farther apart than this many detection-kernel widths (super-pixels) are not tested for a
#: dip between them: separate stars (a star's noise bumps lie within its PSF).
MERGE_RADIUS_KERNELS = 3


def frame_problem(frame: Frame, params: DetectParams) -> str:
    """Reason the frame cannot hold usable stars, or ''."""
    px = frame.pixels
    lo, hi = px.min(), px.max()
    if lo == hi:
        return f"frame is uniform (every pixel = {lo})"
    sat = float(np.count_nonzero(px >= frame.white_level)) / px.size if hi >= frame.white_level else 0.0
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
    # an odd step walks across the block's columns: a step dividing the row length would sample
    # the same few columns in every row (a dead column then looked like half the block)
    sparse = blocks[:, :, :: max((b * b) // 64, 1) | 1]
    med = np.median(sparse, axis=2)
    mad = np.maximum(
        np.maximum(np.median(np.abs(sparse - med[:, :, None]), axis=2) * 1.4826, _clipped_width(sparse)), 0.5
    )
    keep = np.abs(blocks - med[:, :, None]) < 4.0 * mad[:, :, None]
    n = np.maximum(keep.sum(axis=2), 1)
    mean = np.where(keep, blocks, 0).sum(axis=2) / n
    var = np.where(keep, (blocks - mean[:, :, None]) ** 2, 0).sum(axis=2) / np.maximum(n - 1, 1)
    # clipping at 4 sigma keeps 99.99% of a Gaussian: no variance correction needed
    return mean, np.sqrt(np.maximum(var, 1.0 / 12.0))  # floor: quantisation noise of 1 DN steps


def _clipped_width(sparse: np.ndarray) -> np.ndarray:
    """Noise width (DN) of blocks whose samples pile up at their minimum (a background clipped at
    the black level, as in 8-bit images: the MAD of such a block is ~0): from two quantiles above
    the clipped fraction, where a clipped Gaussian keeps its shape. 0 for unclipped blocks."""
    n = sparse.shape[2]
    clipped = (sparse <= sparse.min(axis=2, keepdims=True)).mean(axis=2)
    out = np.zeros(clipped.shape)
    hit = clipped > 0.25
    if not hit.any() or n < 8:
        return out
    srt = np.sort(sparse[hit], axis=1)
    p1 = np.clip(clipped[hit] + 0.05, 0.5, 0.85)
    p2 = p1 + 0.1
    q1 = np.take_along_axis(srt, np.round(p1 * (n - 1)).astype(int)[:, None], axis=1)[:, 0]
    q2 = np.take_along_axis(srt, np.round(p2 * (n - 1)).astype(int)[:, None], axis=1)[:, 0]
    out[hit] = (q2 - q1) / (ndtri(p2) - ndtri(p1))
    return out


def _expand(grid: np.ndarray, block: int, shape) -> np.ndarray:
    """Piecewise-constant expansion of a block grid to ``shape`` (last blocks stretched)."""
    reps = []
    for n_blocks, size in zip(grid.shape, shape):
        r = np.full(n_blocks, block)
        r[-1] = size - block * (n_blocks - 1)
        reps.append(r)
    return np.repeat(np.repeat(grid, reps[0], axis=0), reps[1], axis=1)


def _interpolate(grid: np.ndarray, block: int, shape) -> np.ndarray:
    """Bilinear interpolation of a block grid (values at block centres, the last block
    stretched to the edge) to ``shape``, constant beyond the outermost centres. Smooth, so
    a vignetted or glowing background leaves no steps at block boundaries."""
    axes = []
    for n_blocks, size in zip(grid.shape, shape):
        reps = np.full(n_blocks, block)
        reps[-1] = size - block * (n_blocks - 1)
        centres = np.cumsum(reps) - reps / 2.0 - 0.5
        pos = np.arange(size, dtype=float)
        if n_blocks == 1:
            axes.append((np.zeros(size, int), np.zeros(size, np.float32)))
            continue
        i0 = np.clip(np.searchsorted(centres, pos) - 1, 0, n_blocks - 2)
        t = np.clip((pos - centres[i0]) / (centres[i0 + 1] - centres[i0]), 0.0, 1.0).astype(np.float32)
        axes.append((i0, t))
    (iy, ty), (ix, tx) = axes
    g = grid.astype(np.float32)
    if grid.shape[1] > 1:
        g = g[:, ix] * (1 - tx) + g[:, np.minimum(ix + 1, grid.shape[1] - 1)] * tx
    else:
        g = np.repeat(g, shape[1], axis=1)
    if grid.shape[0] > 1:
        return g[iy] * (1 - ty)[:, None] + g[np.minimum(iy + 1, grid.shape[0] - 1)] * ty[:, None]
    return np.repeat(g, shape[0], axis=0)


def detect_stars(frame: Frame, params: DetectParams = DetectParams()) -> Detections:
    """Detect star candidates in a raw frame (module docstring)."""
    problem = frame_problem(frame, params)
    if problem:
        return _empty(problem)
    h2, w2 = frame.height // 2, frame.width // 2
    if h2 < 4 or w2 < 4:
        return _empty(f"frame too small for detection ({frame.width} x {frame.height})")
    block = max(min(params.block_px // 2, h2, w2) // 2 * 2, 4)  # in phase pixels
    black = np.asarray(frame.black_level, dtype=np.float32).reshape(2, 2)
    total = np.zeros((h2, w2), np.float32)
    bg_sum = var_sum = np.zeros((), np.float32)  # 0-d: the first phase's grid gives the shape
    bg_grids, noise_grids, bad, phases = {}, {}, [], {}
    d2 = 1.0 if frame.is_mono else 4.0  # squared distance to the neighbours used (px^2)
    ratio = params.sharp_fraction * np.exp(-d2 / (2.0 * params.psf_sigma_px**2))
    for py in (0, 1):
        for px_ in (0, 1):
            phase = frame.pixels[py : 2 * h2 : 2, px_ : 2 * w2 : 2].astype(np.float32) - black[py, px_]
            med, sig = _phase_background(phase, block)
            bg_grids[py, px_], noise_grids[py, px_] = med, sig
            cols = _clean_columns(phase, float(np.median(sig)))
            if len(cols):
                rows = np.arange(h2)
                bad.append(((2 * rows[:, None] + py) * frame.width + (2 * cols[None, :] + px_)).ravel())
            mono = (frame.pixels, black[py, px_], py, px_) if frame.is_mono else None
            n_r, n_c = _clean_sharp(phase, med, sig, block, params.k_sigma, ratio, mono)
            bad.append((2 * n_r + py) * frame.width + (2 * n_c + px_))
            total += phase
            phases[py, px_] = phase
            bg_sum = bg_sum + med
            var_sum = var_sum + sig**2
    resid = total - _interpolate(bg_sum, block, total.shape)
    bad_pixels = np.sort(np.concatenate(bad))
    n_sharp = len(bad_pixels)
    # separable matched filter over super-pixels; noise: sqrt(sum of the 2-D weights^2) = sum k^2
    kernel = matched_kernel(params.psf_sigma_px)
    filt = ndimage.correlate1d(resid, kernel, axis=0, mode="constant")
    filt = ndimage.correlate1d(filt, kernel, axis=1, mode="constant")
    snr_map = filt / (
        float(np.sum(kernel.astype(float) ** 2)) * np.sqrt(_expand(var_sum.astype(np.float32), block, filt.shape))
    )
    if kernel is not _K121:
        # a wide kernel sums structure that white noise does not predict (residual column defects,
        # background detail smaller than a block): where the filtered background scatters more
        # than predicted, its measured scatter sets the noise. The 3x3 kernel sees little of it,
        # and on compressed real images (JPEG blocks) the same rescaling cost real faint stars.
        snr_map /= np.maximum(_expand(_phase_background(snr_map, block)[1].astype(np.float32), block, filt.shape), 1.0)
    mask = snr_map > params.k_sigma
    labels, n_regions = ndimage.label(mask)
    if n_regions == 0:
        return _empty("no pixel above the detection threshold", n_rejected_sharp=n_sharp, bad_pixels=bad_pixels)
    n_found = n_regions
    if n_regions > REGION_CAP_FACTOR * params.max_candidates:  # glare, clutter, a wrong noise level: bound the work
        peaks = ndimage.maximum(filt, labels, np.arange(1, n_regions + 1))
        top = np.argsort(-peaks)[: REGION_CAP_FACTOR * params.max_candidates] + 1
        labels, n_regions = ndimage.label(np.isin(labels, top))
        mask = labels > 0
    mr_, mc_ = np.nonzero(mask)
    pr, pc = _local_maxima(filt, mr_, mc_, params.peak_separation // 2)
    pr, pc, n_over = _merge_without_dip(
        filt, snr_map, labels, pr, pc, MERGE_RADIUS_KERNELS * len(kernel), REGION_CAP_FACTOR * params.max_candidates
    )
    plabel = labels[pr, pc]
    peaks_per_region = np.bincount(plabel, minlength=n_regions + 1)

    # streaks: second moments of each region's filtered signal (super-pixel units), and of its
    # shape alone (a bright star on a faint trail dominates the signal's moments)
    lab = labels[mr_, mc_]
    nb = n_regions + 1
    area = np.bincount(lab, minlength=nb)
    elongated = np.zeros(nb, bool)
    for wgt in (np.maximum(filt[mr_, mc_], 0).astype(float), np.ones(len(lab))):
        elongated |= _axis_ratio(lab, mr_, mc_, wgt, nb) > params.max_elongation
    elongated &= area >= params.min_streak_area
    is_streak = elongated[plabel]
    n_streak = int(np.count_nonzero(is_streak))
    pr, pc, plabel = pr[~is_streak], pc[~is_streak], plabel[~is_streak]
    sharp = _peaked_candidates(phases, bg_grids, noise_grids, block, pr, pc, params, frame.is_mono)
    n_sharp += int(np.count_nonzero(sharp))
    pr, pc, plabel = pr[~sharp], pc[~sharp], plabel[~sharp]
    if len(pr) == 0:
        return _empty(
            f"no star-like candidate ({n_streak} streaks rejected, {n_sharp} sharp pixels cleaned)",
            n_rejected_sharp=n_sharp,
            n_rejected_streak=n_streak,
            bad_pixels=bad_pixels,
        )

    flux = filt[pr, pc].astype(float)
    order = np.argsort(-flux)
    n_drop = max(len(order) - params.max_candidates, 0) + n_over
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
    det = Detections(
        x=2.0 * x_sp + 0.5,
        y=2.0 * y_sp + 0.5,
        flux=flux,
        snr=snr_map[pr, pc].astype(float),
        flags=flags,
        noise=noise,
        background=bgv,
        n_rejected_sharp=n_sharp,
        n_rejected_streak=n_streak,
        n_dropped_cap=n_drop,
        n_regions=n_found,
        n_regions_examined=n_regions,
        bad_pixels=bad_pixels,
    )
    det.reason = "; ".join(bound_notes(det, n_drop, params.max_candidates))
    return det


def _axis_ratio(lab, r, c, wgt, nb) -> np.ndarray:
    """Major / minor axis of each labelled region from the ``wgt``-weighted second moments of its
    pixels ``(r, c)`` (labels ``lab`` < ``nb``)."""
    s0 = np.maximum(np.bincount(lab, wgt, nb), 1e-12)
    dr = r - (np.bincount(lab, wgt * r, nb) / s0)[lab]
    dc = c - (np.bincount(lab, wgt * c, nb) / s0)[lab]
    mrr = np.bincount(lab, wgt * dr * dr, nb) / s0
    mcc = np.bincount(lab, wgt * dc * dc, nb) / s0
    mrc = np.bincount(lab, wgt * dr * dc, nb) / s0
    tr, det = mrr + mcc, mrr * mcc - mrc**2
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    return np.sqrt((tr / 2 + disc) / np.maximum(tr / 2 - disc, 1e-3))


def bound_notes(det: Detections, n_dropped_cap: int, max_candidates: int) -> list[str]:
    """What the work bounds left out: significant regions not examined, candidates beyond the cap."""
    notes = []
    if det.n_regions > det.n_regions_examined:
        notes.append(
            f"{det.n_regions} regions above the threshold: only the {det.n_regions_examined} brightest examined"
        )
    if n_dropped_cap:
        notes.append(f"{n_dropped_cap} fainter candidates dropped by the cap of {max_candidates}")
    return notes


def _local_maxima(img: np.ndarray, r: np.ndarray, c: np.ndarray, half: int):
    """Those of the pixels (r, c) that are the maximum of their (2 half + 1)^2 box."""
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


#: A column whose median departs from its neighbours' by more than this many noise sigmas is a
#: column defect (stuck, dead or offset): no star or sky feature moves a whole column's median.
COLUMN_DEFECT_SIGMAS = 2.0


def _clean_columns(phase: np.ndarray, noise: float) -> np.ndarray:
    """Column defects of one phase (``COLUMN_DEFECT_SIGMAS``): shifted, in place, to their
    neighbours' level so that detection does not see a line; returns their indices (the fit
    leaves their pixels out)."""
    colmed = np.median(phase[:: max(phase.shape[0] // 64, 1)], axis=0)  # ~64 rows: the median is robust
    excess = colmed - ndimage.median_filter(colmed, size=9, mode="nearest")
    cols = np.flatnonzero(np.abs(excess) > COLUMN_DEFECT_SIGMAS * noise)
    if len(cols):
        phase[:, cols] -= excess[cols][None, :].astype(np.float32)
    return cols


def _clean_sharp(
    phase: np.ndarray, med: np.ndarray, sig: np.ndarray, block: int, k_sigma: float, ratio: float, mono=None
):
    """Replace, in place, phase pixels much sharper than the PSF (hot pixels, cosmic-ray
    hits) by the mean of the middle two of their four neighbours; returns their (rows,
    cols). Neighbours are the same-colour pixels 2 px away (the phase's own neighbours) or,
    for mono frames (``mono = (pixels, black, py, px)``), the adjacent raw pixels. Values are
    taken above the local block background ``med``. Sharp: excess above ``k_sigma`` x
    ``sig`` and the second largest neighbour (+1 sigma margin) below ``ratio`` x the
    excess. For a Gaussian PSF of sigma s every pixel, peak or wing, has a second-largest
    neighbour at distance d of at least exp(-d^2 / (2 s^2)) of its own value, while an
    isolated or paired hot pixel has background there."""
    rows, cols = np.nonzero(phase > _expand((med + k_sigma * sig).astype(np.float32), block, phase.shape))
    h, w = phase.shape
    bg = _grid_at(med, rows // block, cols // block).astype(np.float32)
    thr = _grid_at(sig, rows // block, cols // block).astype(np.float32)
    done_r, done_c = [], []
    for _ in range(1 if mono is not None else 3):  # chains of hot pixels clean from their ends inwards
        if mono is None:
            a, b = phase[np.maximum(rows - 1, 0), cols], phase[np.minimum(rows + 1, h - 1), cols]
            c, d = phase[rows, np.maximum(cols - 1, 0)], phase[rows, np.minimum(cols + 1, w - 1)]
        else:
            a, b, c, d = _raw_neighbours(rows, cols, *mono)
        l1, s1, l2, s2 = np.maximum(a, b), np.minimum(a, b), np.maximum(c, d), np.minimum(c, d)
        second = np.maximum(np.minimum(l1, l2), np.maximum(s1, s2)) - bg
        middle = 0.5 * (a + b + c + d - np.maximum(l1, l2) - np.minimum(s1, s2))
        sharp = second + thr < ratio * (phase[rows, cols] - bg)
        if not sharp.any():
            break
        phase[rows[sharp], cols[sharp]] = middle[sharp]
        done_r.append(rows[sharp])
        done_c.append(cols[sharp])
        keep = ~sharp
        rows, cols, thr, bg = rows[keep], cols[keep], thr[keep], bg[keep]
    if not done_r:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(done_r), np.concatenate(done_c)


def _peaked_candidates(phases, bg_grids, noise_grids, block, pr, pc, params, mono) -> np.ndarray:
    """True for candidates whose brightest raw pixel holds far more of the 6x6 raw window's
    signal than a PSF allows: hot pixels and cosmic-ray hits the per-pixel cleaning missed
    (it needs ~45 sigma; this pools 36 pixels). A centred Gaussian puts p0 = erf(1 /
    (2 sqrt 2 s))^2 of the flux in one pixel, erf(3 / (sqrt 2 s))^2 in the window; colour can at most double that on a CFA
    (rg or bg up to ~2.5 against a channel mean ~1.2); 1.5x margin. Sharp if the peak
    exceeds that share of the window sum by 3 standard deviations."""
    n = len(pr)
    if n == 0:
        return np.zeros(0, bool)
    h2, w2 = phases[0, 0].shape
    rr = np.clip(2 * pr[:, None, None] - 2 + np.arange(6)[None, :, None], 0, 2 * h2 - 1)
    cc = np.clip(2 * pc[:, None, None] - 2 + np.arange(6)[None, None, :], 0, 2 * w2 - 1)
    rr, cc = np.broadcast_arrays(rr, cc)
    win = np.empty(rr.shape, np.float32)
    gy, gx = pr // block, pc // block
    sig2 = np.zeros(n)
    for a in (0, 1):
        for b in (0, 1):
            m = (rr % 2 == a) & (cc % 2 == b)
            bg = np.broadcast_to(_grid_at(bg_grids[a, b], gy, gx)[:, None, None], rr.shape)
            win[m] = phases[a, b][rr[m] // 2, cc[m] // 2] - bg[m]
            sig2 += _grid_at(noise_grids[a, b], gy, gx) ** 2 / 4.0
    # peak-pixel share of the flux inside the 6x6 window (a wide PSF spills out of the window)
    p0 = (erf(1.0 / (2.0 * np.sqrt(2.0) * params.psf_sigma_px)) / erf(3.0 / (np.sqrt(2.0) * params.psf_sigma_px))) ** 2
    share = min(0.9, 1.5 * p0 * (1.0 if mono else 2.0))
    flat = win.reshape(n, -1)
    peak = flat.max(axis=1)
    total = flat.sum(axis=1)
    sd = np.sqrt(sig2 * (1.0 + share**2 * flat.shape[1]))
    return peak - share * total > 3.0 * sd


def _raw_neighbours(rows, cols, pixels, black, py, px):
    """Black-subtracted values of the 4 adjacent raw pixels of phase pixels (rows, cols)."""
    hr, wr = pixels.shape
    r, c = 2 * rows + py, 2 * cols + px
    return tuple(
        pixels[np.clip(r + dr, 0, hr - 1), np.clip(c + dc, 0, wr - 1)].astype(np.float32) - black
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1))
    )


def _merge_without_dip(filt, snr_map, labels, pr, pc, radius: int, limit: int):
    """Drop a weaker peak when the filtered image does not dip by 3 sigma between it and a
    brighter kept peak of the same region within ``radius`` super-pixels (noise bumps on one star
    are not blends; farther peaks are separate stars). Peaks are taken brightest first and at
    most ``limit`` are kept: the work is bounded whatever the clutter (kept peaks are looked up on
    a grid of ``radius`` cells). Returns the kept rows, columns and the number left over."""
    plabel = labels[pr, pc]
    counts = np.bincount(plabel)
    keep = np.zeros(len(pr), bool)
    cells: dict[tuple[int, int, int], list[int]] = {}
    n_kept, n_over = 0, 0
    order = np.argsort(-filt[pr, pc], kind="stable")
    for i, j in enumerate(order):
        if n_kept == limit:
            n_over = len(order) - i
            break
        rj, cj, lab = int(pr[j]), int(pc[j]), int(plabel[j])
        if counts[lab] == 1:  # alone in its region
            keep[j], n_kept = True, n_kept + 1
            continue
        vj = filt[rj, cj]
        noise_j = vj / snr_map[rj, cj]
        gy, gx = rj // radius, cj // radius
        separate = True
        for q in (q for dy in (-1, 0, 1) for dx in (-1, 0, 1) for q in cells.get((lab, gy + dy, gx + dx), ())):
            dr, dc = int(pr[q]) - rj, int(pc[q]) - cj
            n = max(abs(dr), abs(dc))
            if n > radius:
                continue
            t = np.arange(2 * n + 1) / (2.0 * n) if n else np.zeros(1)
            rr = np.round(rj + t * dr).astype(int)
            cc = np.round(cj + t * dc).astype(int)
            if vj - filt[rr, cc].min() < 3.0 * noise_j:
                separate = False
                break
        if separate:
            cells.setdefault((lab, gy, gx), []).append(j)
            keep[j], n_kept = True, n_kept + 1
    return pr[keep], pc[keep], n_over
