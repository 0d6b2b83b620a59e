"""A detector's temporal noise drawn once and served shifted: exposures at a device's cadence.

Fresh full-frame draws (Poisson background and Gaussian read noise over the reference design's
5 Mpx) cost about 220 ms a frame, most of the device's GO -> result budget (docs/hil.md). A
:class:`NoiseBank` draws ``n`` padded frames of background shot noise plus read noise once, at
start-up, and gives each exposure a window of one of them at a seed-chosen offset and flip; the
star signal (Poisson in the pixels it covers) and the hot pixels (Poisson) are drawn per exposure.
Means and distributions are those of ``sensor_sim.render_frame`` (the bank's shot noise uses the
mean background rate, off by the PRNU's 1 % in variance); values differ from it for the same seed,
and exposures share noise fields moved by random offsets (nothing correlates inside one frame).
A saturated pixel reads exactly full well (``render_frame`` adds read noise after clipping; the
DN clip hides the difference for the default detector).
"""

from __future__ import annotations

import numpy as np

from ground.sim.sensor_sim import DetectorModel, fixed_pattern

PAD_PX = 128  #: the bank's margin: offsets 0..PAD_PX in rows and columns


class NoiseBank:
    """Noise of ``det`` for frames of ``shape`` (rows, cols); ``n`` bank frames from ``seed``."""

    def __init__(self, det: DetectorModel, shape: tuple[int, int], n: int = 2, seed: int = 0):
        self.det = det
        self.shape = shape
        prnu, dsnu, hot = fixed_pattern(det, shape)
        self.prnu = prnu
        self.hot = hot
        t = det.exposure_s
        sky, dark = det.sky_e_per_s * t, det.dark_e_per_s * t
        base = sky * prnu + dark + dsnu
        base.ravel()[hot] += det.hot_pixel_e_per_s * t
        self.base = base.astype(np.float32)
        lam = sky * float(np.mean(prnu)) + dark
        rng = np.random.default_rng(seed)
        h, w = shape
        self.banks = []
        for _ in range(n):
            b = rng.poisson(lam, (h + PAD_PX, w + PAD_PX)).astype(np.float32) - np.float32(lam)
            b += np.float32(det.read_noise_e) * rng.standard_normal(b.shape, dtype=np.float32)
            self.banks.append(b)

    def electrons(self, signal: np.ndarray, seed: int) -> np.ndarray:
        """e- per pixel (float32) for the noise-free star ``signal`` (e-, ``shape``), clipped to full well."""
        if signal.shape != self.shape:
            raise ValueError(f"signal is {signal.shape}, the bank's frames are {self.shape}")
        det, (h, w) = self.det, self.shape
        rng = np.random.default_rng(seed)
        bank = self.banks[int(rng.integers(len(self.banks)))]
        r0, c0 = (int(v) for v in rng.integers(0, PAD_PX + 1, size=2))
        window = bank[r0 : r0 + h, c0 : c0 + w]
        flip_rows, flip_cols = rng.integers(0, 2, size=2)
        window = window[:: -1 if flip_rows else 1, :: -1 if flip_cols else 1]
        out = self.base + window
        flat = out.ravel()
        lit = np.flatnonzero(signal)
        flat[lit] += rng.poisson(signal.ravel()[lit] * self.prnu.ravel()[lit])
        hot_mean = det.hot_pixel_e_per_s * det.exposure_s
        flat[self.hot] += rng.poisson(hot_mean, len(self.hot)) - hot_mean
        return np.minimum(out, np.float32(det.full_well_e), out=out)
