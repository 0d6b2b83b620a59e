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
from numba import njit
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
    n_rejected_extended: int = 0  #: candidates on or beside an extended object (:func:`_near_extended`)
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


def _frame_problem(lo, hi, n_sat: int, size: int, params: DetectParams) -> str:
    """Reason the frame cannot hold usable stars, or '' (from its minimum, maximum and the number
    of pixels at the white level)."""
    if lo == hi:
        return f"frame is uniform (every pixel = {lo})"
    sat = n_sat / size
    if sat > params.max_saturated_fraction:
        return f"frame is saturated ({100 * sat:.0f}% of pixels at the white level)"
    return ""


def frame_problem(frame: Frame, params: DetectParams) -> str:
    """Reason the frame cannot hold usable stars, or ''."""
    lo, hi, n_sat = _nb_range(_kernel_pixels(frame.pixels), float(frame.white_level))
    return _frame_problem(lo, hi, n_sat, frame.pixels.size, params)


def _kernel_pixels(px: np.ndarray) -> np.ndarray:
    """The pixels as the compiled kernels take them: native byte order (FITS data are big-endian)
    and a type numba knows (float16 becomes float32); the array itself when it already is."""
    if px.dtype == np.float16:
        return px.astype(np.float32)
    if not px.dtype.isnative:
        return px.astype(px.dtype.newbyteorder("="))
    return px


def _median_last(a: np.ndarray) -> np.ndarray:
    """np.median along the last axis (same values), by one partition: np.median's overhead is
    several times the work on the small arrays detection takes medians of."""
    n = a.shape[-1]
    if n % 2:
        return np.partition(a, n // 2, axis=-1)[..., n // 2]
    part = np.partition(a, n // 2, axis=-1)  # one kth: numpy's several-kth path is slower
    return (part[..., : n // 2].max(axis=-1) + part[..., n // 2]) * a.dtype.type(0.5)


def _background_grids(img: np.ndarray, black: np.ndarray, block: int, step: int):
    """Coarse (background, noise) grids, shape (step, step, ny, nx), of the ``step`` x ``step``
    phases of ``img`` (2: the CFA phases of a frame, minus ``black``; 1: the image itself), block
    in phase pixels: clipped mean and standard deviation of a 1-in-4 subsample, the clip at
    +-4 sigma about a sparse per-block median. Means, not medians: integer DN make medians biased
    by up to 0.5 DN, which the 36-pixel matched filter would multiply."""
    b = max(block // 2, 2)
    hp, wp = img.shape[0] // step, img.shape[1] // step
    ny, nx = max(hp // block, 1), max(wp // block, 1)
    sstep = max((b * b) // 64, 1) | 1
    # an odd sample step walks across the block's columns: a step dividing the row length would
    # sample the same few columns in every row (a dead column then looked like half the block)
    med = np.empty((step, step, ny, nx), np.float32)
    lim = np.empty((step, step, ny, nx))
    for py in range(step):
        for px in range(step):
            sparse = _nb_block_samples(img, step, py, px, np.float32(black[py, px]), b, ny, nx, sstep)
            med[py, px] = _median_last(sparse)
            lim[py, px] = 4.0 * np.maximum(
                np.maximum(_median_last(np.abs(sparse - med[py, px][:, :, None])) * 1.4826, _clipped_width(sparse)),
                0.5,
            )
    mean, var = _nb_block_stats(img, step, black.astype(np.float32), b, med, lim)
    # clipping at 4 sigma keeps 99.99% of a Gaussian: no variance correction needed; the floor is
    # the quantisation noise of 1 DN steps
    return mean, np.sqrt(np.maximum(var, 1.0 / 12.0))


#: A column whose median departs from its neighbours' by more than this many noise sigmas is a
#: column defect (stuck, dead or offset): no star or sky feature moves a whole column's median.
COLUMN_DEFECT_SIGMAS = 2.0


#: The background grid's blocks shrink to this (raw px) where bilinear interpolation between block
#: centres cannot follow the background (stray light near the Sun, the Moon or the Earth rises by
#: orders of magnitude across the field): the background grid spans more than
#: :data:`GRADIENT_RATIO` times its lowest value and :data:`GRADIENT_SPAN_SIGMAS` times the noise,
#: and the interpolation's midpoint error (a second difference over 8) exceeds
#: :data:`GRADIENT_TRIGGER` of the noise somewhere. Vignetting and skyglow on real frames span at
#: most 4 times (the shared real frames: 1.1-4.0), so their detection is unchanged.
GRADIENT_BLOCK_PX = 32
GRADIENT_RATIO = 10.0
GRADIENT_SPAN_SIGMAS = 20.0
GRADIENT_TRIGGER = 0.1


def _curved(bg: np.ndarray, sig: np.ndarray) -> bool:
    """Whether the (2, 2, ny, nx) background grid ``bg`` (noise ``sig``) is a steep gradient that
    bilinear interpolation misses (see :data:`GRADIENT_BLOCK_PX`)."""
    total = _grid_sum(bg)
    lo, hi = float(total.min()), float(total.max())
    noise = float(np.median(np.sqrt(_grid_sum(sig**2))))
    if not (hi > GRADIENT_RATIO * max(lo, 0.0) and hi - lo > GRADIENT_SPAN_SIGMAS * noise):
        return False
    worst = 0.0
    if bg.shape[3] >= 3:
        d2 = np.abs(bg[..., 2:] - 2.0 * bg[..., 1:-1] + bg[..., :-2]) / 8.0
        worst = max(worst, float(np.max(d2 / sig[..., 1:-1])))
    if bg.shape[2] >= 3:
        d2 = np.abs(bg[:, :, 2:] - 2.0 * bg[:, :, 1:-1] + bg[:, :, :-2]) / 8.0
        worst = max(worst, float(np.max(d2 / sig[:, :, 1:-1])))
    return worst > GRADIENT_TRIGGER


def _column_defects(pix: np.ndarray, black: np.ndarray, sig: np.ndarray, width: int):
    """Column defects per phase (``COLUMN_DEFECT_SIGMAS`` against the phase's median noise): the
    offsets (2, 2, w2) that shift them to their neighbours' level, so that detection does not see
    a line, and the linear indices of their pixels (the fit leaves them out)."""
    h2, w2 = pix.shape[0] // 2, pix.shape[1] // 2
    step = max(h2 // 64, 1)  # ~64 rows: the median is robust
    colex = np.zeros((2, 2, w2), np.float32)
    bad = []
    for py in (0, 1):
        for px in (0, 1):
            sub = pix[py : 2 * h2 : 2 * step, px : 2 * w2 : 2].astype(np.float32) - black[py, px]
            colmed = _median_last(np.ascontiguousarray(sub.T))
            excess = colmed - ndimage.median_filter(colmed, size=9, mode="nearest")
            cols = np.flatnonzero(np.abs(excess) > COLUMN_DEFECT_SIGMAS * float(np.median(sig[py, px])))
            if len(cols):
                colex[py, px, cols] = excess[cols]
                rows = np.arange(h2)
                bad.append(((2 * rows[:, None] + py) * width + (2 * cols[None, :] + px)).ravel())
    return colex, bad


def _grid_sum(g: np.ndarray) -> np.ndarray:
    """Sum of the four phase grids (2, 2, ny, nx), in phase order."""
    return g[0, 0] + g[0, 1] + g[1, 0] + g[1, 1]


def _interp_axis(n_blocks: int, block: int, size: int, extrapolate: bool = False):
    """Bilinear weights along one axis for grid values at block centres (the last block stretched
    to the edge), constant beyond the outermost centres (``extrapolate``: linear, for a background
    with a strong gradient): lower index and weight of the upper one."""
    if n_blocks == 1:
        return np.zeros(size, np.int64), np.zeros(size, np.float32)
    reps = np.full(n_blocks, block)
    reps[-1] = size - block * (n_blocks - 1)
    centres = np.cumsum(reps) - reps / 2.0 - 0.5
    pos = np.arange(size, dtype=float)
    i0 = np.clip(np.searchsorted(centres, pos) - 1, 0, n_blocks - 2)
    t = (pos - centres[i0]) / (centres[i0 + 1] - centres[i0])
    if not extrapolate:
        t = np.clip(t, 0.0, 1.0)
    return i0.astype(np.int64), t.astype(np.float32)


def _interp_cols(grid: np.ndarray, ix: np.ndarray, tx: np.ndarray) -> np.ndarray:
    """The grid interpolated along its rows to every column (ny, size), float32."""
    return grid[:, ix] * (1 - tx) + grid[:, np.minimum(ix + 1, grid.shape[1] - 1)] * tx


# --- compiled kernels (numba; cached on disk, so only the first run after an install compiles) ---


@njit(cache=True, nogil=True)
def _nb_range(px, white):  # pragma: no cover - compiled
    """Minimum, maximum and number of pixels at or above ``white``: one pass."""
    lo = px.flat[0]
    hi = px.flat[0]
    n = 0
    for r in range(px.shape[0]):
        for c in range(px.shape[1]):
            v = px[r, c]
            if v < lo:
                lo = v
            if v > hi:
                hi = v
            if v >= white:
                n += 1
    return lo, hi, n


@njit(cache=True, nogil=True)
def _nb_block_samples(img, step, py, px, black, b, ny, nx, sstep):  # pragma: no cover - compiled
    """Sparse samples (ny, nx, ns) of each block of one phase's 1-in-4 subsample."""
    ns = (b * b + sstep - 1) // sstep
    out = np.empty((ny, nx, ns), np.float32)
    for i in range(ny):
        for j in range(nx):
            k = 0
            for t in range(0, b * b, sstep):
                u, v = t // b, t % b
                out[i, j, k] = np.float32(img[2 * (i * b + u) * step + py, 2 * (j * b + v) * step + px]) - black
                k += 1
    return out


@njit(cache=True, nogil=True)
def _nb_block_stats(img, step, black, b, med, lim):  # pragma: no cover - compiled
    """Mean and variance of each block's 1-in-4 subsample within ``lim`` of ``med``, for all
    ``step`` x ``step`` phases in one pass (arrays (step, step, ny, nx))."""
    ny, nx = med.shape[2], med.shape[3]
    mean = np.zeros((step, step, ny, nx))
    var = np.zeros((step, step, ny, nx))
    cnt = np.zeros((step, step, nx), np.int64)
    s1 = np.zeros((step, step, nx))
    s2 = np.zeros((step, step, nx))
    for i in range(ny):
        cnt[:] = 0
        s1[:] = 0.0
        s2[:] = 0.0
        for u in range(b):
            for a in range(step):
                r = 2 * (i * b + u) * step + a
                for j in range(nx):
                    for bb in range(step):
                        m = med[a, bb, i, j]
                        lm = lim[a, bb, i, j]
                        blk = black[a, bb]
                        n_ = 0
                        t1 = 0.0
                        t2 = 0.0
                        for v in range(b):  # branch-free: the loop vectorises
                            d = (np.float32(img[r, 2 * (j * b + v) * step + bb]) - blk) - m
                            keep = abs(d) < lm
                            n_ += keep
                            dk = float(d) if keep else 0.0
                            t1 += dk
                            t2 += dk * dk
                        cnt[a, bb, j] += n_
                        s1[a, bb, j] += t1
                        s2[a, bb, j] += t2
        for a in range(step):
            for bb in range(step):
                for j in range(nx):
                    n_ = cnt[a, bb, j]
                    if n_ > 0:
                        mean[a, bb, i, j] = med[a, bb, i, j] + s1[a, bb, j] / n_
                        var[a, bb, i, j] = max(s2[a, bb, j] - s1[a, bb, j] ** 2 / n_, 0.0) / max(n_ - 1, 1)
    return mean, var


@njit(cache=True, nogil=True)
def _nb_superpixels(pix, black, colex, thr, block, gx, iy, ty, cand):  # pragma: no cover - compiled
    """One pass over the frame: 2x2 super-pixel sums of the black- and column-corrected phases
    less the background (bilinear between block centres: ``gx`` the grid already interpolated
    along rows, ``iy, ty`` lower grid row and upper weight per row), shape (h2, w2), and the
    linear indices of phase pixels above their block's ``thr`` (into ``cand``; returns how many
    there are, also beyond its length)."""
    h2, w2 = pix.shape[0] // 2, pix.shape[1] // 2
    width = pix.shape[1]
    ny, nx = thr.shape[2], thr.shape[3]
    nyg = gx.shape[0]
    total = np.empty((h2, w2), np.float32)
    thr_row = np.empty((2, 2, w2), np.float32)
    v = np.empty((2, 2, w2), np.float32)
    cap = len(cand)
    n = 0
    cur = -1
    one = np.float32(1.0)
    for rr in range(h2):
        gy = min(rr // block, ny - 1)
        if gy != cur:
            cur = gy
            for a in range(2):
                for bb in range(2):
                    for cc in range(w2):
                        thr_row[a, bb, cc] = thr[a, bb, gy, min(cc // block, nx - 1)]
        for a in range(2):
            for bb in range(2):
                blk = black[a, bb]
                row = pix[2 * rr + a]
                for cc in range(w2):
                    v[a, bb, cc] = np.float32(row[2 * cc + bb]) - blk - colex[a, bb, cc]
        i0 = iy[rr]
        i1 = min(i0 + 1, nyg - 1)
        t = ty[rr]
        for cc in range(w2):
            total[rr, cc] = (v[0, 0, cc] + v[0, 1, cc] + v[1, 0, cc] + v[1, 1, cc]) - (
                gx[i0, cc] * (one - t) + gx[i1, cc] * t
            )
        # the threshold test as a branch-free count first: most rows hold no candidate
        hits = 0
        for a in range(2):
            for bb in range(2):
                for cc in range(w2):
                    hits += v[a, bb, cc] - thr_row[a, bb, cc] > 0
        if hits == 0:
            continue
        for a in range(2):
            for bb in range(2):
                for cc in range(w2):
                    if v[a, bb, cc] > thr_row[a, bb, cc]:
                        if n < cap:
                            cand[n] = (2 * rr + a) * width + 2 * cc + bb
                        n += 1
    return total, n


@njit(cache=True, nogil=True)
def _nb_clean_sharp(px_all, black, colex, bg, sig, cand, block, ratio, mono, width):  # pragma: no cover
    """Pixels much sharper than the PSF (hot pixels, cosmic-ray hits) among the candidates
    ``cand`` (linear indices above k sigma): returns their linear indices, the value each is
    replaced with (the mean of the middle two of its four neighbours) and its value before.
    Neighbours are the same-colour pixels 2 px away (phase neighbours, already cleaned values
    where an earlier round replaced them) or, for mono frames, the adjacent raw pixels. Sharp: the
    second largest neighbour above the block background (+1 sigma) below ``ratio`` x the
    excess. For a Gaussian PSF of sigma s every pixel, peak or wing, has a second-largest
    neighbour at distance d of at least exp(-d^2 / (2 s^2)) of its own value, while an isolated
    or paired hot pixel has background there. Rounds (3 on CFA frames: chains of hot pixels
    clean from their ends inwards) see the values of the round before."""
    h2, w2 = px_all.shape[0] // 2, px_all.shape[1] // 2
    hr, wr = px_all.shape[0], px_all.shape[1]
    ny, nx = bg.shape[2], bg.shape[3]
    order = np.argsort(cand)
    lin = cand[order]
    n = len(lin)
    cur = np.empty(n, np.float32)
    active = np.ones(n, np.bool_)
    for i in range(n):
        r, c = lin[i] // width, lin[i] % width
        cur[i] = np.float32(px_all[r, c]) - black[r % 2, c % 2] - colex[r % 2, c % 2, c // 2]
    orig = cur.copy()
    done = np.zeros(n, np.bool_)
    newv = np.empty(n, np.float32)
    nb = np.empty(4, np.float32)
    for _round in range(1 if mono else 3):
        n_sharp = 0
        for i in range(n):
            if not active[i]:
                continue
            r, c = lin[i] // width, lin[i] % width
            a, b = r % 2, c % 2
            pr, pc = r // 2, c // 2
            gy, gx = min(pr // block, ny - 1), min(pc // block, nx - 1)
            bgv = np.float32(bg[a, b, gy, gx])
            thr = np.float32(sig[a, b, gy, gx])
            for k in range(4):
                dr = -1 if k == 0 else (1 if k == 1 else 0)
                dc = -1 if k == 2 else (1 if k == 3 else 0)
                if mono:
                    rr = min(max(r + dr, 0), hr - 1)
                    cc = min(max(c + dc, 0), wr - 1)
                    nb[k] = np.float32(px_all[rr, cc]) - black[a, b]
                else:
                    qr = min(max(pr + dr, 0), h2 - 1)
                    qc = min(max(pc + dc, 0), w2 - 1)
                    rr, cc = 2 * qr + a, 2 * qc + b
                    q = rr * width + cc
                    j = np.searchsorted(lin, q)
                    if j < n and lin[j] == q:
                        nb[k] = cur[j]
                    else:
                        nb[k] = np.float32(px_all[rr, cc]) - black[a, b] - colex[a, b, qc]
            l1, s1 = max(nb[0], nb[1]), min(nb[0], nb[1])
            l2, s2 = max(nb[2], nb[3]), min(nb[2], nb[3])
            second = max(min(l1, l2), max(s1, s2)) - bgv
            middle = np.float32(0.5) * (nb[0] + nb[1] + nb[2] + nb[3] - max(l1, l2) - min(s1, s2))
            if float(second + thr) < ratio * float(cur[i] - bgv):
                newv[i] = middle
                done[i] = True
                n_sharp += 1
        if n_sharp == 0:
            break
        for i in range(n):
            if active[i] and done[i]:
                cur[i] = newv[i]
                active[i] = False
    m = 0
    for i in range(n):
        if done[i]:
            m += 1
    out_lin = np.empty(m, np.int64)
    out_new = np.empty(m, np.float32)
    out_old = np.empty(m, np.float32)
    m = 0
    for i in range(n):
        if done[i]:
            out_lin[m], out_new[m], out_old[m] = lin[i], cur[i], orig[i]
            m += 1
    return out_lin, out_new, out_old


@njit(cache=True, nogil=True)
def _nb_patch_total(total, lin, delta, width):  # pragma: no cover - compiled
    for i in range(len(lin)):
        total[(lin[i] // width) // 2, (lin[i] % width) // 2] += delta[i]


@njit(cache=True, nogil=True)
def _nb_filter(total, kernel, den, block, k_sigma, mr, mc):  # pragma: no cover - compiled
    """The separable correlation of ``total`` with ``kernel`` on both axes (zero outside the
    image) and the super-pixels whose filtered value exceeds ``k_sigma`` x their block's ``den``,
    in raster order, into ``mr, mc`` (none with empty arrays; returns how many there are, also
    beyond their length)."""
    h, w = total.shape
    L = len(kernel)
    hk = L // 2
    filt = np.empty((h, w), np.float32)
    buf = np.zeros(w + 2 * hk, np.float32)
    acc = np.empty(w)
    den_row = np.empty(w, np.float32)
    cap = len(mr)
    n = 0
    nyd, nxd = den.shape
    cur = -1
    for r in range(h):
        acc[:] = 0.0
        for i in range(L):
            rr = r + i - hk
            if 0 <= rr < h:
                k = float(kernel[i])
                src = total[rr]
                for c in range(w):
                    acc[c] += k * src[c]
        for c in range(w):
            buf[c + hk] = np.float32(acc[c])
        acc[:] = 0.0
        for j in range(L):
            k = float(kernel[j])
            for c in range(w):
                acc[c] += k * buf[c + j]
        out = filt[r]
        for c in range(w):
            out[c] = np.float32(acc[c])
        if cap:
            gy = min(r // block, nyd - 1)
            if gy != cur:
                cur = gy
                for c in range(w):
                    den_row[c] = den[gy, min(c // block, nxd - 1)]
            hits = 0  # branch-free count first: most rows hold no significant pixel
            for c in range(w):
                hits += out[c] / den_row[c] > k_sigma
            if hits == 0:
                continue
            for c in range(w):
                if out[c] / den_row[c] > k_sigma:
                    if n < cap:
                        mr[n] = r
                        mc[n] = c
                    n += 1
    return filt, n


@njit(cache=True, nogil=True)
def _nb_find(parent, i):  # pragma: no cover - compiled
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=True, nogil=True)
def _nb_label(mr, mc):  # pragma: no cover - compiled
    """4-connected labels (1..n, numbered by first pixel in raster order, as ndimage.label) of the
    pixels (mr, mc) given in raster order."""
    n = len(mr)
    parent = np.arange(n)
    j = 0  # walks the previous row
    row_start = 0
    for i in range(n):
        r, c = mr[i], mc[i]
        if i > 0 and mr[i - 1] != r:
            row_start = i
        if i > row_start and mc[i - 1] == c - 1:
            a, b = _nb_find(parent, i), _nb_find(parent, i - 1)
            if a != b:
                parent[max(a, b)] = min(a, b)
        while j < n and (mr[j] < r - 1 or (mr[j] == r - 1 and mc[j] < c)):
            j += 1
        if j < n and mr[j] == r - 1 and mc[j] == c:
            a, b = _nb_find(parent, i), _nb_find(parent, j)
            if a != b:
                parent[max(a, b)] = min(a, b)
    lab = np.zeros(n, np.int64)
    root_lab = np.zeros(n, np.int64)
    k = 0
    for i in range(n):
        rt = _nb_find(parent, i)
        if root_lab[rt] == 0:
            k += 1
            root_lab[rt] = k
        lab[i] = root_lab[rt]
    return lab


@njit(cache=True, nogil=True)
def _nb_local_maxima(img, r, c, half):  # pragma: no cover - compiled
    """Indices of the pixels (r, c) that are the maximum of their (2 half + 1)^2 box (ties: the
    first in raster order is kept)."""
    h, w = img.shape
    out = np.empty(len(r), np.int64)
    m = 0
    for i in range(len(r)):
        v = img[r[i], c[i]]
        ok = True
        for dr in range(-half, half + 1):
            for dc in range(-half, half + 1):
                if dr == 0 and dc == 0:
                    continue
                rr, cc = r[i] + dr, c[i] + dc
                if rr < 0 or rr >= h or cc < 0 or cc >= w:
                    continue
                nv = img[rr, cc]
                later = dr > 0 or (dr == 0 and dc > 0)
                if not (v > nv or (v == nv and later)):
                    ok = False
                    break
            if not ok:
                break
        if ok:
            out[m] = i
            m += 1
    return out[:m]


@dataclass
class PreparedFrame:
    """The part of detection that does not depend on the PSF width, computed once per frame and
    shared by the passes of a PSF measurement (:func:`prepare_detection`): per-phase background
    and noise grids, column defects, the background-subtracted super-pixel sums before
    hot-pixel cleaning and the pixels above the threshold (the hot-pixel candidates)."""

    frame: Frame
    k_sigma: float
    block_px: int
    block: int
    black: np.ndarray
    px_all: np.ndarray
    pix: np.ndarray
    bg_all: np.ndarray
    sig_all: np.ndarray
    colex: np.ndarray
    bad_columns: list
    total: np.ndarray
    cand: np.ndarray
    den: np.ndarray


def prepare_detection(frame: Frame, params: DetectParams = DetectParams()) -> PreparedFrame | Detections:
    """The PSF-independent part of :func:`detect_stars` (two passes over the frame, one of them
    over a 1-in-4 subsample), or an empty :class:`Detections` with the reason the frame cannot
    hold stars."""
    h2, w2 = frame.height // 2, frame.width // 2
    px_all = _kernel_pixels(frame.pixels)
    lo, hi, n_sat = _nb_range(px_all, float(frame.white_level))
    problem = _frame_problem(lo, hi, n_sat, px_all.size, params)
    if problem:
        return _empty(problem)
    if h2 < 4 or w2 < 4:
        return _empty(f"frame too small for detection ({frame.width} x {frame.height})")
    block = max(min(params.block_px // 2, h2, w2) // 2 * 2, 4)  # in phase pixels
    black = np.asarray(frame.black_level, dtype=np.float32).reshape(2, 2)
    pix = px_all if px_all.shape == (2 * h2, 2 * w2) else px_all[: 2 * h2, : 2 * w2]
    if not pix.flags.c_contiguous:  # odd-sized mono frames, views: the kernels want C order
        pix = np.ascontiguousarray(pix)
    # per-phase clipped mean and noise grids (2, 2, ny, nx) from a 1-in-4 subsample
    bg_all, sig_all = _background_grids(pix, black, block, 2)
    steep = block > GRADIENT_BLOCK_PX // 2 and _curved(bg_all, sig_all)
    if steep:
        block = GRADIENT_BLOCK_PX // 2
        bg_all, sig_all = _background_grids(pix, black, block, 2)
    colex, bad = _column_defects(pix, black, sig_all, frame.width)
    thr = (bg_all + params.k_sigma * sig_all).astype(np.float32)
    bg_sum = _grid_sum(bg_all)
    var_sum = _grid_sum(sig_all.astype(np.float32) ** 2)
    iy, ty = _interp_axis(bg_sum.shape[0], block, h2, steep)
    ix, tx = _interp_axis(bg_sum.shape[1], block, w2, steep)
    gx = np.ascontiguousarray(_interp_cols(bg_sum.astype(np.float32), ix, tx))
    # one pass over the frame: column-corrected, background-subtracted super-pixel sums and the
    # pixels above the threshold
    cand = np.empty(max(pix.size // 64, 4096), np.int64)
    total, n_cand = _nb_superpixels(pix, black, colex, thr, block, gx, iy, ty, cand)
    if n_cand > len(cand):  # a frame far from sparse stars on a dark sky: one more pass
        cand = np.empty(n_cand, np.int64)
        total, n_cand = _nb_superpixels(pix, black, colex, thr, block, gx, iy, ty, cand)
    return PreparedFrame(
        frame,
        params.k_sigma,
        params.block_px,
        block,
        black,
        px_all,
        pix,
        bg_all,
        sig_all,
        colex,
        bad,
        total,
        cand[:n_cand],
        np.sqrt(var_sum.astype(np.float32)),
    )


def detect_stars(
    frame: Frame, params: DetectParams = DetectParams(), prepared: PreparedFrame | Detections | None = None
) -> Detections:
    """Detect star candidates in a raw frame (module docstring); ``prepared``: the frame's
    :func:`prepare_detection` with the same ``k_sigma`` and ``block_px``, when several passes
    share it."""
    if prepared is None:
        prepared = prepare_detection(frame, params)
    if isinstance(prepared, Detections):
        return prepared
    if prepared.frame is not frame or (prepared.k_sigma, prepared.block_px) != (params.k_sigma, params.block_px):
        raise ValueError("prepared detection is of another frame or other k_sigma / block_px")
    prep = prepared
    block, black, pix, bg_all, sig_all, colex = prep.block, prep.black, prep.pix, prep.bg_all, prep.sig_all, prep.colex
    bg_grids = {(a, b): bg_all[a, b] for a in (0, 1) for b in (0, 1)}
    noise_grids = {(a, b): sig_all[a, b] for a in (0, 1) for b in (0, 1)}
    d2 = 1.0 if frame.is_mono else 4.0  # squared distance to the neighbours used (px^2)
    ratio = params.sharp_fraction * np.exp(-d2 / (2.0 * params.psf_sigma_px**2))
    sharp_lin, sharp_val, sharp_old = _nb_clean_sharp(
        prep.px_all, black, colex, bg_all, sig_all, prep.cand, block, float(ratio), bool(frame.is_mono), frame.width
    )
    total = prep.total
    if len(sharp_lin):  # the cleaned pixels' change, undone below: the prepared sums serve other passes
        rr_, cc_ = (sharp_lin // frame.width) // 2, (sharp_lin % frame.width) // 2
        saved = total[rr_, cc_].copy()
        _nb_patch_total(total, sharp_lin, sharp_val - sharp_old, frame.width)
    bad_pixels = np.sort(np.concatenate([*prep.bad_columns, sharp_lin.astype(np.int64)]))
    n_sharp = len(bad_pixels)
    # background subtraction, separable matched filter over super-pixels and threshold; noise:
    # sqrt(sum of the 2-D weights^2) = sum k^2
    kernel = matched_kernel(params.psf_sigma_px)
    ksq = np.float32(np.sum(kernel.astype(float) ** 2))
    den = (ksq * prep.den).astype(np.float32)
    wide = kernel is not _K121
    kk = np.float32(params.k_sigma)
    mr_ = np.empty(0 if wide else max(total.size // 64, 1024), np.int64)
    mc_ = np.empty_like(mr_)
    filt, n_mask = _nb_filter(total, kernel, den, block, kk, mr_, mc_)
    if n_mask > len(mr_):  # more than 1/64 of the image significant: one more pass for the list
        mr_, mc_ = np.empty(n_mask, np.int64), np.empty(n_mask, np.int64)
        filt, n_mask = _nb_filter(total, kernel, den, block, kk, mr_, mc_)
    mr_, mc_ = mr_[:n_mask], mc_[:n_mask]
    if len(sharp_lin):
        total[rr_, cc_] = saved
    if wide:
        # a wide kernel sums structure that white noise does not predict (residual column defects,
        # background detail smaller than a block): where the filtered background scatters more
        # than predicted, its measured scatter sets the noise. The 3x3 kernel sees little of it,
        # and on compressed real images (JPEG blocks) the same rescaling cost real faint stars.
        snr_map = filt / _expand(den, block, filt.shape)
        scatter = _background_grids(snr_map, np.zeros((2, 2), np.float32), block, 1)[1][0, 0]
        den = den * np.maximum(scatter.astype(np.float32), 1.0)
        mr_, mc_ = np.nonzero(filt / _expand(den, block, filt.shape) > params.k_sigma)
    if len(mr_) == 0:
        return _empty("no pixel above the detection threshold", n_rejected_sharp=n_sharp, bad_pixels=bad_pixels)
    lab = _nb_label(mr_, mc_)
    n_regions = int(lab.max())
    n_found = n_regions
    if n_regions > REGION_CAP_FACTOR * params.max_candidates:  # glare, clutter, a wrong noise level: bound the work
        peaks = np.full(n_regions + 1, -np.inf, np.float32)
        np.maximum.at(peaks, lab, filt[mr_, mc_])
        top = np.argsort(-peaks[1:], kind="stable")[: REGION_CAP_FACTOR * params.max_candidates] + 1
        keep = np.zeros(n_regions + 1, bool)
        keep[top] = True
        sel = keep[lab]
        mr_, mc_ = mr_[sel], mc_[sel]
        lab = _nb_label(mr_, mc_)
        n_regions = int(lab.max())
    gy_, gx_ = np.minimum(mr_ // block, den.shape[0] - 1), np.minimum(mc_ // block, den.shape[1] - 1)
    snr_pts = filt[mr_, mc_] / den[gy_, gx_]
    ip = _nb_local_maxima(filt, mr_, mc_, params.peak_separation // 2)
    pr, pc, plabel_all = mr_[ip], mc_[ip], lab[ip]
    keep_p, n_over = _merge_without_dip(
        filt,
        snr_pts[ip],
        plabel_all,
        pr,
        pc,
        MERGE_RADIUS_KERNELS * len(kernel),
        REGION_CAP_FACTOR * params.max_candidates,
    )
    pr, pc, plabel, psnr = pr[keep_p], pc[keep_p], plabel_all[keep_p], snr_pts[ip][keep_p]
    peaks_per_region = np.bincount(plabel, minlength=n_regions + 1)

    # streaks: second moments of each region's filtered signal (super-pixel units), and of its
    # shape alone (a bright star on a faint trail dominates the signal's moments)
    nb = n_regions + 1
    area = np.bincount(lab, minlength=nb)
    elongated = np.zeros(nb, bool)
    for wgt in (np.maximum(filt[mr_, mc_], 0).astype(float), np.ones(len(lab))):
        elongated |= _axis_ratio(lab, mr_, mc_, wgt, nb) > params.max_elongation
    elongated &= area >= params.min_streak_area
    is_streak = elongated[plabel]
    n_streak = int(np.count_nonzero(is_streak))
    pr, pc, plabel, psnr = pr[~is_streak], pc[~is_streak], plabel[~is_streak], psnr[~is_streak]
    near_extended = _near_extended(filt, lab, mr_, mc_, nb, pr, pc, kernel, params.psf_sigma_px)
    n_extended = int(np.count_nonzero(near_extended))
    pr, pc, plabel, psnr = pr[~near_extended], pc[~near_extended], plabel[~near_extended], psnr[~near_extended]
    sharp = _peaked_candidates(
        (pix, black, colex, sharp_lin, sharp_val), bg_all, sig_all, block, pr, pc, params, frame.is_mono
    )
    n_sharp += int(np.count_nonzero(sharp))
    pr, pc, plabel, psnr = pr[~sharp], pc[~sharp], plabel[~sharp], psnr[~sharp]
    if len(pr) == 0:
        return _empty(
            f"no star-like candidate ({n_streak} streaks rejected, {n_extended} on extended objects,"
            f" {n_sharp} sharp pixels cleaned)",
            n_rejected_sharp=n_sharp,
            n_rejected_streak=n_streak,
            n_rejected_extended=n_extended,
            bad_pixels=bad_pixels,
        )

    flux = filt[pr, pc].astype(float)
    order = np.argsort(-flux)
    n_drop = max(len(order) - params.max_candidates, 0) + n_over
    order = order[: params.max_candidates]
    pr, pc, plabel, flux, psnr = pr[order], pc[order], plabel[order], flux[order], psnr[order]
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
        snr=psnr.astype(float),
        flags=flags,
        noise=noise,
        background=bgv,
        n_rejected_sharp=n_sharp,
        n_rejected_streak=n_streak,
        n_rejected_extended=n_extended,
        n_dropped_cap=n_drop,
        n_regions=n_found,
        n_regions_examined=n_regions,
        bad_pixels=bad_pixels,
    )
    det.reason = "; ".join(bound_notes(det, n_drop, params.max_candidates))
    return det


#: A region is an extended object (the Moon's disc, the Earth's limb, a glare patch) when the part
#: of it above half its filtered peak covers more than this many times a point source's half-peak
#: area (a star saturated 10^4 times over reaches ~15 times), and at least :data:`EXTENDED_MIN_SP`.
EXTENDED_FACTOR = 40.0
EXTENDED_MIN_SP = 64  #: super-pixels
#: Candidates within this many detection-kernel widths of an extended object's box are refused too
#: (the blurred limb and its scattered light).
EXTENDED_MARGIN_KERNELS = 2


def _near_extended(filt, lab, r, c, nb, pr, pc, kernel, psf_sigma_px: float) -> np.ndarray:
    """True for the candidates ``(pr, pc)`` inside the box (plus a margin) of a region far larger
    than the PSF: its pixels ``(r, c)`` (labels ``lab`` < ``nb``) above half its filtered peak
    cover more than :data:`EXTENDED_FACTOR` times a point source's half-peak area (super-pixels).
    A point source's filtered image has the Gaussian sigma ``sqrt((s/2)^2 + 1/12 + k^2)``
    super-pixels (``s`` the PSF sigma in px, ``1/12`` the binning, ``k`` the kernel's sigma) and
    half-peak area ``2 pi ln 2`` sigma^2."""
    out = np.zeros(len(pr), bool)
    if len(r) == 0 or len(pr) == 0:
        return out
    vals = filt[r, c]
    peak = np.full(nb, -np.inf, np.float32)
    np.maximum.at(peak, lab, vals)
    upper = np.bincount(lab, vals > 0.5 * peak[lab], nb)
    x = np.arange(len(kernel)) - len(kernel) // 2
    k2 = float(np.sum(kernel * x**2) / np.sum(kernel))
    point = 2.0 * np.pi * np.log(2.0) * ((psf_sigma_px / 2.0) ** 2 + 1.0 / 12.0 + k2)
    ext = np.flatnonzero(upper > max(EXTENDED_FACTOR * point, EXTENDED_MIN_SP))
    margin = EXTENDED_MARGIN_KERNELS * len(kernel)
    for k in ext:
        sel = lab == k
        rr, cc = r[sel], c[sel]
        out |= (
            (pr >= rr.min() - margin)
            & (pr <= rr.max() + margin)
            & (pc >= cc.min() - margin)
            & (pc <= cc.max() + margin)
        )
    return out


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


def _peaked_candidates(phases, bg_all, sig_all, block, pr, pc, params, mono) -> np.ndarray:
    """True for candidates whose brightest raw pixel holds far more of the 6x6 raw window's
    signal than a PSF allows: hot pixels and cosmic-ray hits the per-pixel cleaning missed
    (it needs ~45 sigma; this pools 36 pixels). A centred Gaussian puts p0 = erf(1 /
    (2 sqrt 2 s))^2 of the flux in one pixel, erf(3 / (sqrt 2 s))^2 in the window; colour can at most double that on a CFA
    (rg or bg up to ~2.5 against a channel mean ~1.2); 1.5x margin. Sharp if the peak
    exceeds that share of the window sum by 3 standard deviations. The windows are taken from
    the phases as detection cleaned them (black level, column offsets, replaced sharp pixels)."""
    if len(pr) == 0:
        return np.zeros(0, bool)
    pix, black, colex, sharp_lin, sharp_val = phases
    srt = np.argsort(sharp_lin)
    # peak-pixel share of the flux inside the 6x6 window (a wide PSF spills out of the window)
    p0 = (erf(1.0 / (2.0 * np.sqrt(2.0) * params.psf_sigma_px)) / erf(3.0 / (np.sqrt(2.0) * params.psf_sigma_px))) ** 2
    share = min(0.9, 1.5 * p0 * (1.0 if mono else 2.0))
    return _nb_peaked(pix, black, colex, sharp_lin[srt], sharp_val[srt], bg_all, sig_all, block, pr, pc, float(share))


@njit(cache=True, nogil=True)
def _nb_peaked(pix, black, colex, sl, sv, bg, sig, block, pr, pc, share):  # pragma: no cover - compiled
    """_peaked_candidates' test per candidate (``sl, sv``: sorted cleaned pixels, their values)."""
    h2, w2 = pix.shape[0] // 2, pix.shape[1] // 2
    width = pix.shape[1]
    ny, nx = bg.shape[2], bg.shape[3]
    out = np.zeros(len(pr), np.bool_)
    for i in range(len(pr)):
        gy, gx = min(pr[i] // block, ny - 1), min(pc[i] // block, nx - 1)
        peak = -np.inf
        total = 0.0
        for u in range(6):
            rr = min(max(2 * pr[i] - 2 + u, 0), 2 * h2 - 1)
            a = rr % 2
            for v in range(6):
                cc = min(max(2 * pc[i] - 2 + v, 0), 2 * w2 - 1)
                b = cc % 2
                val = np.float32(pix[rr, cc]) - black[a, b] - colex[a, b, cc // 2]
                if len(sl):
                    q = rr * width + cc
                    j = np.searchsorted(sl, q)
                    if j < len(sl) and sl[j] == q:
                        val = sv[j]
                x = float(np.float32(val - bg[a, b, gy, gx]))
                peak = max(peak, x)
                total += x
        sig2 = 0.0
        for a in range(2):
            for b in range(2):
                sig2 += sig[a, b, gy, gx] ** 2 / 4.0
        sd = np.sqrt(sig2 * (1.0 + share**2 * 36))
        out[i] = peak - share * total > 3.0 * sd
    return out


def _merge_without_dip(filt, snr, plabel, pr, pc, radius: int, limit: int):
    """Drop a weaker peak when the filtered image does not dip by 3 sigma between it and a
    brighter kept peak of the same region (labels ``plabel``, detection SNR ``snr``) within
    ``radius`` super-pixels (noise bumps on one star are not blends; farther peaks are separate
    stars). Peaks are taken brightest first and at most ``limit`` are kept: the work is bounded
    whatever the clutter (kept peaks are looked up on a grid of ``radius`` cells). Returns the
    mask of kept peaks and the number left over."""
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
        noise_j = vj / snr[j]
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
    return keep, n_over
