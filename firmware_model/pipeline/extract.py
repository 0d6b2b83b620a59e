"""Single entry point from a raw frame to star measurements: detection, centroid and
colour fit, and (with a camera model) sensor-frame unit vectors.

``extract_stars(frame, camera=None, params=ExtractParams()) -> StarList``. Pure: no I/O,
no global state. Times per stage are measured with ``time.perf_counter`` (seconds).

**PSF width, measured per frame.** Detection's hot-pixel tests, the fit's start and window
and its sharp-artefact test all depend on the PSF Gaussian sigma. Unless the parameters fix it
(``ExtractParams.psf_sigma_px``, an override), detection and fit run with a starting guess,
the sigma is measured as the median fitted sigma of the brightest clean stars
(:func:`measure_psf_sigma`), and when that disagrees with the value used by more than
``psf_tolerance`` (relative) detection and fit run again with the measurement (at most
``psf_max_passes`` passes in all). A guess far too wide makes detection clean star cores as
hot pixels; the fit on the remaining pixels still measures the width well enough to recover.
A guess far too narrow for a PSF that is not Gaussian (a defocus ring) makes most fits fail,
and the few converged ones (hot-pixel clusters) then measure a width near the guess: when more
than :data:`PSF_FAIL_FRACTION` of the brightest candidates' fits fail, one pass runs at
:data:`PSF_WIDEN_FACTOR` times the width (or the measurement, if wider), and the measurement
goes on from whichever of the two passes had fewer failed fits.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from firmware_model.camera import CameraModel
from firmware_model.pipeline.centroid import FitParams, FitResults, fit_stars
from firmware_model.pipeline.detect import Detections, DetectParams, bound_notes, detect_stars, prepare_detection
from firmware_model.pipeline.raw_frame import Frame
from protocol.star_flags import UNTRUSTED, StarFlag

#: Accepted range of a set PSF sigma (px): [low, high).
PSF_SIGMA_RANGE_PX = (0.1, 20.0)
#: Detection keeps this many times the candidate cap; the cap applies after the fit's sharpness test.
CAP_MARGIN = 2
#: Brightest clean stars whose fitted sigmas make the PSF measurement, and the fewest accepted.
PSF_SAMPLE_STARS = 20
PSF_MIN_STARS = 3
#: Share of failed fits among the brightest candidates above which the PSF guess is widened once.
PSF_FAIL_FRACTION = 0.3
PSF_WIDEN_FACTOR = 2.0
#: Flags that exclude a star from the PSF measurement (POOR_FIT stays: a non-Gaussian PSF
#: makes every bright star a poor Gaussian fit, but its fitted width is still the best measure).
_PSF_EXCLUDE = int(StarFlag.SATURATED | StarFlag.EDGE | StarFlag.BLEND | StarFlag.FIT_FAILED)


@dataclass(frozen=True)
class ExtractParams:
    """``psf_sigma_px``: the optics' PSF Gaussian sigma (px) as an override; None (default)
    measures it on each frame starting from ``psf_start_px`` (module docstring). The
    ``psf_sigma_px`` fields of ``detect`` and ``fit`` are set from it for every pass."""

    detect: DetectParams = DetectParams()
    fit: FitParams = FitParams()
    psf_sigma_px: float | None = None
    psf_start_px: float = 1.0
    psf_tolerance: float = 0.1
    psf_max_passes: int = 4


@dataclass
class StarList:
    """Measured stars, brightest first. ``x, y`` px (docs/CONVENTIONS.md); ``flux`` mean
    per-site signal summed over the PSF: (A_R + 2 A_G + A_B) / 4 for a Bayer frame, A for
    mono (DN); ``amp`` per-channel totals R, G, B (DN); ``rg, bg`` colour ratios (NaN for
    mono); ``cov_xy`` (N, 2, 2) px^2; ``cov_colour`` (N, 2, 2) for (rg, bg); ``snr``
    detection signal-to-noise; ``sigma`` fitted PSF sigma (px); ``reduced_chi2`` fit
    quality; ``flags`` StarFlag bits; ``vectors`` (N, 3) sensor-frame unit vectors when a
    camera model was available, else None. ``timings`` seconds per stage; ``reason`` says
    why the list is empty (or what was dropped)."""

    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    amp: np.ndarray
    rg: np.ndarray
    bg: np.ndarray
    cov_xy: np.ndarray
    cov_colour: np.ndarray
    snr: np.ndarray
    sigma: np.ndarray
    reduced_chi2: np.ndarray
    flags: np.ndarray
    vectors: np.ndarray | None = None
    timings: dict = field(default_factory=dict)
    reason: str = ""
    psf_sigma_px: float = float("nan")  #: PSF sigma detection and fit used (px)
    psf_measured_px: float = float("nan")  #: PSF sigma measured on this frame (px); NaN: too few stars
    psf_source: str = ""  #: "setting" (override), "measured" or "start" (too few stars to measure)
    psf_passes: int = 0  #: detection + fit passes run

    def __len__(self) -> int:
        return len(self.x)

    @property
    def trusted(self) -> np.ndarray:
        """True where no UNTRUSTED flag is set."""
        return (self.flags & int(UNTRUSTED)) == 0

    def to_records(self) -> list[dict]:
        """One JSON-friendly dict per star (NaN becomes None)."""

        def num(v):
            v = float(v)
            return v if np.isfinite(v) else None

        recs = []
        for i in range(len(self)):
            rec = {
                "x": num(self.x[i]),
                "y": num(self.y[i]),
                "flux": num(self.flux[i]),
                "rg": num(self.rg[i]),
                "bg": num(self.bg[i]),
                "sigma_x": num(np.sqrt(self.cov_xy[i, 0, 0])),
                "sigma_y": num(np.sqrt(self.cov_xy[i, 1, 1])),
                "sigma_rg": num(np.sqrt(self.cov_colour[i, 0, 0])),
                "sigma_bg": num(np.sqrt(self.cov_colour[i, 1, 1])),
                "snr": num(self.snr[i]),
                "psf_sigma": num(self.sigma[i]),
                "reduced_chi2": num(self.reduced_chi2[i]),
                "flags": int(self.flags[i]),
                "flag_names": [f.name for f in StarFlag if f and int(self.flags[i]) & int(f)],
            }
            if self.vectors is not None:
                rec["vector"] = [float(c) for c in self.vectors[i]]
            recs.append(rec)
        return recs


def _measurable(fit: FitResults) -> np.ndarray:
    """True where a fitted sigma may enter the PSF measurement (:func:`measure_psf_sigma`)."""
    return np.isfinite(fit.sigma) & ((fit.flags & _PSF_EXCLUDE) == 0) & ~fit.sharp


def measure_psf_sigma(fit: FitResults, snr: np.ndarray) -> float:
    """Median fitted PSF sigma (px) of the :data:`PSF_SAMPLE_STARS` highest-SNR stars whose fit
    converged and is not saturated, clipped, blended or sharp; NaN with fewer than
    :data:`PSF_MIN_STARS` such stars."""
    idx = np.flatnonzero(_measurable(fit))
    if len(idx) < PSF_MIN_STARS:
        return float("nan")
    idx = idx[np.argsort(-snr[idx])][:PSF_SAMPLE_STARS]
    return float(np.median(fit.sigma[idx]))


def failed_fit_fraction(fit: FitResults, snr: np.ndarray) -> float:
    """Share of the :data:`PSF_SAMPLE_STARS` highest-SNR candidates (not saturated, clipped or
    blended) whose fit failed; 0 without such candidates."""
    idx = np.flatnonzero((fit.flags & int(StarFlag.SATURATED | StarFlag.EDGE | StarFlag.BLEND)) == 0)
    if not len(idx):
        return 0.0
    idx = idx[np.argsort(-snr[idx])][:PSF_SAMPLE_STARS]
    return float(np.mean((fit.flags[idx] & int(StarFlag.FIT_FAILED)) != 0))


#: Fitted centres closer than this (px) are one star found twice (two peaks of a defocus ring).
REPEAT_PX = 1.0


def _repeats(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """True for candidates whose fitted centre lies within :data:`REPEAT_PX` of a brighter one's."""
    ok = np.flatnonzero(np.isfinite(x) & np.isfinite(y))
    out = np.zeros(len(x), bool)
    if len(ok) > 1:
        pairs = cKDTree(np.column_stack([x[ok], y[ok]])).query_pairs(REPEAT_PX, output_type="ndarray")
        out[ok[pairs.max(axis=1)]] = True  # candidates come brightest first
    return out


#: Candidates fitted first, as a multiple of the cap: the fit goes on to fainter candidates only
#: while fewer than the cap survive it (fit only where the result needs it).
FIT_FIRST_FACTOR = 1.25
#: Candidates fitted first by a pass that only measures the PSF, as a multiple of
#: :data:`PSF_SAMPLE_STARS`; it fits further ones only while fewer than that many are measurable.
PSF_FIT_FIRST_FACTOR = 1.6


def _take(det: Detections, idx: np.ndarray) -> Detections:
    """Detections restricted to candidates ``idx`` (bad pixels and counts kept)."""
    return replace(
        det,
        x=det.x[idx],
        y=det.y[idx],
        flux=det.flux[idx],
        snr=det.snr[idx],
        flags=det.flags[idx],
        noise=det.noise[idx],
        background=det.background[idx],
    )


class _Pass:
    """One pass at PSF sigma ``sigma_px``: detection with :data:`CAP_MARGIN` times the candidate
    cap, then the fit of its candidates brightest first, only as far as asked (:meth:`fit_for_psf`
    for the PSF measurement, :meth:`fit_to_cap` for the result). A candidate's fate depends only
    on the brighter ones (the repeat test keeps the brighter of two), so fitting further never
    changes the stars already kept. ``fit_s``: seconds in the fit."""

    def __init__(self, frame: Frame, params: ExtractParams, sigma_px: float, prepared) -> None:
        self.frame, self.sigma = frame, sigma_px
        self.cap = params.detect.max_candidates
        dp = replace(params.detect, psf_sigma_px=sigma_px, max_candidates=CAP_MARGIN * self.cap)
        self.det = detect_stars(frame, dp, prepared=prepared)
        self.fp = replace(params.fit, psf_sigma_px=sigma_px)
        self.parts: list[FitResults] = []
        self.stop = 0  # candidates fitted
        self.fit_s = 0.0
        self.fit = fit_stars(frame, _take(self.det, np.arange(0)), self.fp)
        self.keep = np.arange(0)  # fitted candidates neither sharp nor a repeat, brightest first

    def _fit_next(self, stop: int) -> None:
        """Fit candidates up to index ``stop`` and update the kept ones."""
        t0 = time.perf_counter()
        start, self.stop = self.stop, min(len(self.det), stop)
        self.parts.append(fit_stars(self.frame, _take(self.det, np.arange(start, self.stop)), self.fp))
        fit = self.parts[0] if len(self.parts) == 1 else _concat(self.parts)
        keep = np.flatnonzero(~fit.sharp)
        self.fit, self.keep = fit, keep[~_repeats(fit.x[keep], fit.y[keep])]
        self.fit_s += time.perf_counter() - t0

    def _fit_while(self, more) -> None:
        """Fit further candidates while ``more()`` and fewer than the cap are kept: the first chunk
        up to :data:`FIT_FIRST_FACTOR` x the cap, then twice the shortfall, at least 8."""
        first = max(int(np.ceil(FIT_FIRST_FACTOR * self.cap)), 1)
        while self.stop < len(self.det) and len(self.keep) < self.cap and more():
            self._fit_next(first if self.stop < first else self.stop + max(2 * (self.cap - len(self.keep)), 8))

    def fit_to_cap(self) -> None:
        """Fit until the cap's worth of candidates is kept or none is left."""
        self._fit_while(lambda: True)

    def fit_to_keep(self, n: int) -> None:
        """Fit until ``n`` candidates are kept (or the cap's worth, or none is left)."""
        self._fit_while(lambda: len(self.keep) < n)

    def fit_for_psf(self, likely_kept: bool) -> None:
        """Fit until :data:`PSF_SAMPLE_STARS` kept candidates are measurable (or the cap's worth is
        kept, or none is left). The first :data:`PSF_FIT_FIRST_FACTOR` x that many at once, unless
        the pass is ``likely_kept`` or that chunk would leave out fewer candidates than it holds:
        then the first chunk :meth:`fit_to_cap` would fit (each call of the fit has a set-up cost
        of its own)."""
        small = min(int(np.ceil(PSF_FIT_FIRST_FACTOR * PSF_SAMPLE_STARS)), int(np.ceil(FIT_FIRST_FACTOR * self.cap)))
        if self.stop == 0 and len(self.det) >= 2 * small and not likely_kept:
            self._fit_next(small)
        self._fit_while(lambda: np.count_nonzero(_measurable(self.sample()[0])) < PSF_SAMPLE_STARS)

    def kept(self) -> int:
        """Candidates kept so far, at most the cap."""
        return min(len(self.keep), self.cap)

    def _kept(self) -> FitResults:
        keep = self.keep[: self.cap]
        return FitResults(**{k: v[keep] for k, v in vars(self.fit).items()})

    def sample(self) -> tuple[FitResults, np.ndarray]:
        """The kept candidates fitted so far (at most the cap) and their detection SNR."""
        return self._kept(), self.det.snr[self.keep[: self.cap]]

    def result(self) -> tuple[FitResults, np.ndarray, list[str]]:
        """The fit of the cap's worth of kept candidates (:meth:`fit_to_cap` first), their
        detection SNR and notes on what was left out (candidates never fitted count as dropped
        by the cap)."""
        self.fit_to_cap()
        if not len(self.det):
            return self.fit, self.det.snr, [self.det.reason]
        n = len(self.det)
        notes = bound_notes(
            self.det, self.det.n_dropped_cap + max(len(self.keep) - self.cap, 0) + (n - self.stop), self.cap
        )
        n_sharp = int(np.count_nonzero(self.fit.sharp))
        if n_sharp:
            notes.append(f"{n_sharp} candidate(s) sharper than the PSF rejected by the fit (hot pixels / cosmic rays)")
        fit, snr = self.sample()
        return fit, snr, notes


def _lost_most(new: _Pass, old: _Pass) -> bool:
    """True when ``new`` keeps fewer than half as many stars as ``old`` (each at most the cap),
    fitting only as far as that takes."""
    new.fit_to_keep(int(np.ceil(0.5 * new.cap)))
    if new.kept() >= 0.5 * old.cap:
        return False
    old.fit_to_cap()
    return new.kept() < 0.5 * old.kept()


def _concat(parts: list[FitResults]) -> FitResults:
    return FitResults(**{k: np.concatenate([vars(p)[k] for p in parts]) for k in vars(parts[0])})


def extract_stars(frame: Frame, camera: CameraModel | None = None, params: ExtractParams = ExtractParams()) -> StarList:
    """Detect and fit stars in ``frame``; ``camera`` (or ``frame.camera``) adds unit vectors."""
    t0 = time.perf_counter()
    sigma = params.psf_sigma_px if params.psf_sigma_px is not None else params.psf_start_px
    prepared = prepare_detection(frame, params.detect)  # shared by the passes
    passes_run: list[_Pass] = []

    def one_pass(width: float) -> _Pass:
        p = _Pass(frame, params, width, prepared)
        passes_run.append(p)
        if params.psf_sigma_px is None:
            # a pass at a measured width is usually the one kept; the starting guess seldom is
            p.fit_for_psf(likely_kept=len(passes_run) > 1)
        return p

    current, passes = one_pass(sigma), 1
    source, measured = "setting", float("nan")
    if params.psf_sigma_px is None:
        failed = failed_fit_fraction(*current.sample())
        if failed > PSF_FAIL_FRACTION and passes < params.psf_max_passes:
            # most fits failed: either the guess is far too narrow for the PSF, or the few
            # converged fits are right that it is narrower; a wide pass tells which
            m = measure_psf_sigma(*current.sample())
            wide, passes = one_pass(PSF_WIDEN_FACTOR * max(sigma, m if np.isfinite(m) else 0.0)), passes + 1
            if failed_fit_fraction(*wide.sample()) < failed and not _lost_most(wide, current):
                current = wide
        while True:
            measured = measure_psf_sigma(*current.sample())
            source = "measured" if np.isfinite(measured) else "start"
            if (
                not np.isfinite(measured)
                or abs(measured / current.sigma - 1.0) <= params.psf_tolerance
                or passes >= params.psf_max_passes
            ):
                break
            nxt, passes = one_pass(measured), passes + 1
            if _lost_most(nxt, current):
                break  # the measured width lost most of the stars (a PSF far from Gaussian): keep this pass
            current = nxt
    fit, snr, notes = current.result()
    sigma = current.sigma
    fit_s = sum(p.fit_s for p in passes_run)
    t2 = time.perf_counter()
    t1 = t2 - fit_s
    reason = "; ".join(notes)
    if camera is None and frame.camera:
        camera = CameraModel.from_dict(frame.camera)
    if camera is not None and (camera.width, camera.height) != (frame.width, frame.height):
        raise ValueError(
            f"camera model is {camera.width} x {camera.height} but the frame is {frame.width} x {frame.height}"
        )
    if frame.is_mono:
        flux = fit.amp[:, 1]
    else:
        flux = (fit.amp[:, 0] + 2.0 * fit.amp[:, 1] + fit.amp[:, 2]) / 4.0
    vectors = camera.pixel_to_vector(fit.x, fit.y) if camera is not None else None
    t3 = time.perf_counter()
    return StarList(
        x=fit.x,
        y=fit.y,
        flux=flux,
        amp=fit.amp,
        rg=fit.rg,
        bg=fit.bg,
        cov_xy=fit.cov_xy,
        cov_colour=fit.cov_colour,
        snr=snr,
        sigma=fit.sigma,
        reduced_chi2=fit.reduced_chi2,
        flags=fit.flags,
        vectors=vectors,
        timings={"detect_s": t1 - t0, "fit_s": t2 - t1, "vectors_s": t3 - t2, "total_s": t3 - t0},
        reason=reason,
        psf_sigma_px=float(sigma),
        psf_measured_px=measured,
        psf_source=source,
        psf_passes=passes,
    )


def warm_up() -> float:
    """Run the compiled detection and fit kernels once on small synthetic frames (RGGB and mono,
    16-bit raw; 8-bit as read from PNG/JPEG), so that their compilation (numba, cached on disk: after the first run of an install
    only a load) does not land in the first frame's solve. Returns the seconds it took; meant for
    start-up."""
    t0 = time.perf_counter()
    yy, xx = np.mgrid[0:64, 0:64]
    img = 200.0 + 3.0 * np.sin(xx * 1.7 + yy * 0.9)
    for x0, y0, a in ((20.3, 24.6, 4000.0), (44.8, 40.2, 2500.0), (30.1, 50.7, 1500.0)):
        img += a / (2 * np.pi) * np.exp(-0.5 * ((xx - x0) ** 2 + (yy - y0) ** 2))
    img[10, 50] += 3000.0  # a hot pixel
    for pattern, dtype, white in (("RGGB", np.uint16, 4095), ("MONO", np.uint16, 4095), ("RGGB", np.uint8, 255)):
        px = img.round() if dtype is np.uint16 else np.clip(img.round() / 16, 0, 255)
        frame = Frame(
            pixels=px.astype(dtype), pattern=pattern, black_level=4 if dtype is np.uint8 else 64, white_level=white
        )
        extract_stars(frame)
        detect_stars(frame, DetectParams(psf_sigma_px=3.0))  # the wide-kernel path of defocused optics
    return time.perf_counter() - t0
