"""Single entry point from a raw frame to star measurements: detection, centroid and
colour fit, and (with a camera model) sensor-frame unit vectors.

``extract_stars(frame, camera=None, params=ExtractParams()) -> StarList``. Pure: no I/O,
no global state. Times per stage are measured with ``time.perf_counter`` (seconds).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.centroid import FitParams, FitResults, fit_stars
from firmware_model.detect import DetectParams, detect_stars
from firmware_model.frame import Frame
from firmware_model.star_flags import StarFlag, UNTRUSTED


@dataclass(frozen=True)
class ExtractParams:
    detect: DetectParams = DetectParams()
    fit: FitParams = FitParams()


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
                "x": num(self.x[i]), "y": num(self.y[i]), "flux": num(self.flux[i]),
                "rg": num(self.rg[i]), "bg": num(self.bg[i]),
                "sigma_x": num(np.sqrt(self.cov_xy[i, 0, 0])), "sigma_y": num(np.sqrt(self.cov_xy[i, 1, 1])),
                "sigma_rg": num(np.sqrt(self.cov_colour[i, 0, 0])), "sigma_bg": num(np.sqrt(self.cov_colour[i, 1, 1])),
                "snr": num(self.snr[i]), "psf_sigma": num(self.sigma[i]), "reduced_chi2": num(self.reduced_chi2[i]),
                "flags": int(self.flags[i]),
                "flag_names": [f.name for f in StarFlag if f and int(self.flags[i]) & int(f)],
            }
            if self.vectors is not None:
                rec["vector"] = [float(c) for c in self.vectors[i]]
            recs.append(rec)
        return recs


def extract_stars(frame: Frame, camera: CameraModel | None = None, params: ExtractParams = ExtractParams()) -> StarList:
    """Detect and fit stars in ``frame``; ``camera`` (or ``frame.camera``) adds unit vectors."""
    t0 = time.perf_counter()
    det = detect_stars(frame, params.detect)
    t1 = time.perf_counter()
    fit = fit_stars(frame, det, params.fit)
    keep = ~fit.sharp
    reason = det.reason
    if not keep.all():
        n_sharp = int(np.count_nonzero(~keep))
        note = f"{n_sharp} candidate(s) sharper than the PSF rejected by the fit (hot pixels / cosmic rays)"
        reason = f"{reason}; {note}" if reason else note
        fit = FitResults(**{k: v[keep] for k, v in vars(fit).items()})
        snr = det.snr[keep]
    else:
        snr = det.snr
    t2 = time.perf_counter()
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
        x=fit.x, y=fit.y, flux=flux, amp=fit.amp, rg=fit.rg, bg=fit.bg, cov_xy=fit.cov_xy,
        cov_colour=fit.cov_colour, snr=snr, sigma=fit.sigma, reduced_chi2=fit.reduced_chi2,
        flags=fit.flags, vectors=vectors,
        timings={"detect_s": t1 - t0, "fit_s": t2 - t1, "vectors_s": t3 - t2, "total_s": t3 - t0},
        reason=reason,
    )
