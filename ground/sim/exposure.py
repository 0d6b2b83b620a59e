"""One exposure of the device's sky-rendering capture sources (``--sky``, ``--attitude-feed``).

``sensor_sim.render_frame`` at the exposure's attitude with two savings that keep the frame's
content (docs/hil.md has the timings):

* only the stars in view: the real sky (``sky_model.sky_stars``, cached) is cut to the cone of
  the field (``camera.fov_half_angle_diagonal`` plus the PSF stamp and smear margin) by one dot
  product of its unit vectors with the boresight, about 100 of 8 867 stars at V 6.5;
* the detector noise from a :class:`~ground.sim.noise_bank.NoiseBank` per detector, drawn once.

With the exposure's mid-time (``epoch_utc``) the Sun's and the Moon's light is rendered too
(``ground.sim.glare``), and the Earth's with the spacecraft's GCRS position (``sc_position_km``);
the frame carries ``timestamp`` = the exposure's start (the mid-time less half the exposure,
docs/CONVENTIONS.md) and ``metadata["sc_position_km"]`` (the device's
bright-body check reads them) and ``metadata["glare"]`` (each body's angle from the boresight, in
view or not, its peak e-). A glare map with nothing above ``glare.FLOOR_E`` leaves the frame as
without it; otherwise its shot noise is drawn by :class:`GlareNoise`.
"""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.pipeline.raw_frame import Frame
from ground.sim.glare import Glare, exposure_start
from ground.sim.noise_bank import PAD_PX, NoiseBank
from ground.sim.openloop import stars_in_cone as stars_in_view
from ground.sim.sensor_sim import DetectorModel, Stars, render_frame, stamp_half_width
from ground.sim.sky_model import sky_stars

#: The glare's shot noise is drawn only inside the box of pixels where its mean exceeds this
#: fraction of the bank's own noise variance (sky, dark, read): below it, it adds under 0.5 % to
#: the noise's standard deviation, and its mean alone is added.
NOISE_FRACTION = 0.01
#: A pixel whose glare mean exceeds full well by this many of its own sigmas is full whatever its
#: noise; when fewer than :data:`SPARSE_FRACTION` of the box's pixels need a draw, only they get one.
SATURATED_SIGMAS = 5.0
SPARSE_FRACTION = 0.5


class GlareNoise:
    """A noise bank's exposure with the glare on it: ``background`` (e- per pixel, noise-free) times
    the PRNU (``prnu32``, float32) as its mean and its shot noise a Gaussian of the same variance:
    a window of ``unit`` (unit-normal draws made once, as the NoiseBank makes its noise) scaled by
    the mean's square root, only where the glare matters and the pixel is not full whatever its
    noise; clipped to full well. Poisson draws over every pixel of the reference design took
    ~0.4 s of the device's 300 ms budget (docs/hil.md), a fresh Gaussian 60-125 ms; the mean and
    variance are Poisson's, the shape differs only below a few e- per pixel, where the bank's own
    noise dominates."""

    def __init__(self, bank: NoiseBank, background: np.ndarray, prnu32: np.ndarray, unit: np.ndarray):
        self.bank = bank
        self.unit = unit  #: unit-normal float32 draws of (rows + PAD_PX, cols + PAD_PX), drawn once
        self.mean = background.astype(np.float32, copy=False) * prnu32
        det = bank.det
        floor = NOISE_FRACTION * ((det.sky_e_per_s + det.dark_e_per_s) * det.exposure_s + det.read_noise_e**2)
        rows = np.flatnonzero(self.mean.max(axis=1) > floor)
        cols = np.flatnonzero(self.mean.max(axis=0) > floor) if len(rows) else rows
        self.box = (rows[0], rows[-1] + 1, cols[0], cols[-1] + 1) if len(rows) else None
        self.at: np.ndarray | None = None  #: flat indices to draw at instead of the box
        if self.box is not None:
            # pixels whose mean is SATURATED_SIGMAS above full well clip to it whatever the noise: a
            # glare that fills the frame (the Sun, the Earth) needs the noise only where it is not
            r0, r1, c0, c1 = self.box
            cap = det.full_well_e + SATURATED_SIGMAS * np.sqrt(det.full_well_e)
            box = self.mean[r0:r1, c0:c1]
            need = (box > floor) & (box < cap)
            n_need = int(np.count_nonzero(need))
            if n_need < SPARSE_FRACTION * need.size:
                rr, cc = np.nonzero(need)
                self.at = np.stack((rr + r0, cc + c0))

    def electrons(self, signal: np.ndarray, seed: int) -> np.ndarray:
        """As ``NoiseBank.electrons``, plus the glare (its noise from ``seed`` too)."""
        out = self.bank.electrons(signal, seed)
        out += self.mean
        if self.box is not None:
            # the shot noise: a window of the unit-normal bank at an offset drawn from ``seed`` (the
            # NoiseBank's way: the same distribution, other values per frame, no full-frame draw)
            h, w = self.mean.shape
            r, c = (int(v) for v in np.random.default_rng([seed, 33]).integers(0, PAD_PX + 1, size=2))
            window = self.unit[r : r + h, c : c + w]
            if self.at is not None:
                rr, cc = self.at
                out[rr, cc] += window[rr, cc] * np.sqrt(self.mean[rr, cc])
            else:
                r0, r1, c0, c1 = self.box
                out[r0:r1, c0:c1] += window[r0:r1, c0:c1] * np.sqrt(self.mean[r0:r1, c0:c1])
        return np.minimum(out, np.float32(self.bank.det.full_well_e), out=out)


def noise_cache_dir() -> Path:
    """Where the capture sources keep their noise banks: the user's cache directory."""
    from firmware_model import user_cache_dir

    return user_cache_dir() / "noise-bank"


class ExposureRenderer:
    """Renders exposures of ``camera`` from ``stars`` (default: the real sky to V 6.5, read on first
    use or by :meth:`draw_bank`'s thread); noise banks kept in ``cache_dir`` when given
    (:class:`~ground.sim.noise_bank.NoiseBank`)."""

    def __init__(self, camera: CameraModel, stars: Stars | None = None, cache_dir: Path | None = None):
        self.camera = camera
        self.cache_dir = cache_dir
        self._stars = stars
        self._stars_lock = threading.Lock()
        self._banks: dict[DetectorModel, NoiseBank] = {}
        self._prnu: dict[int, np.ndarray] = {}
        self._unit: np.ndarray | None = None
        self._lock = threading.Lock()

    @property
    def stars(self) -> Stars:
        """The stars rendered."""
        with self._stars_lock:
            if self._stars is None:
                self._stars = sky_stars()
            return self._stars

    def draw_bank(self, det: DetectorModel, glare: bool = False) -> threading.Thread:
        """Start reading the stars and drawing (or loading) the noise bank of ``det`` in a thread
        (numpy draws large arrays without the GIL, so a device's kernel loading goes on beside it)
        and return the thread; a render that comes first waits for it (:meth:`bank`'s lock).
        Capture sources call it at start-up and join it in ``ready`` before the device says it is
        listening; one exposure is rendered and dropped, and with ``glare`` (a source that may
        render bright bodies) one glare map is made too, so the first GO pays no first-use cost."""

        def draw() -> None:
            self.stars  # noqa: B018 - the real sky read here, beside the device's kernel loading
            self.bank(det)
            self._unit_normal()
            if glare:  # the ephemerides' and the camera's first-use costs (~0.35 s), not in a GO
                Glare("2026-01-01T00:00:00", np.array([7000.0, 0.0, 0.0])).background_e(np.eye(3), self.camera, det)
            self.render(np.eye(3), det, 0)  # a render's own first-use costs (memory, kernels), not in a GO

        thread = threading.Thread(target=draw, name="noise-bank", daemon=True)
        thread.start()
        return thread

    def bank(self, det: DetectorModel) -> NoiseBank:
        """The noise bank of ``det`` (drawn, or loaded from ``cache_dir``, on first use)."""
        key = dataclasses.replace(det, pattern="MONO")  # the noise does not depend on the CFA
        with self._lock:
            if key not in self._banks:
                self._banks[key] = NoiseBank(det, (self.camera.height, self.camera.width), cache_dir=self.cache_dir)
            return self._banks[key]

    def _unit_normal(self) -> np.ndarray:
        """Unit-normal float32 draws of the frame plus the bank's margin (:class:`GlareNoise`'s),
        drawn once (with the first noise bank, at start-up)."""
        with self._lock:
            if self._unit is None:
                shape = (self.camera.height + PAD_PX, self.camera.width + PAD_PX)
                self._unit = np.random.default_rng(33).standard_normal(shape, dtype=np.float32)
            return self._unit

    def _prnu32(self, bank: NoiseBank) -> np.ndarray:
        """The bank's PRNU map as float32 (kept: the glare's mean is scaled by it every frame)."""
        with self._lock:
            if id(bank) not in self._prnu:
                self._prnu[id(bank)] = bank.prnu.astype(np.float32)
            return self._prnu[id(bank)]

    def render(
        self,
        attitude: np.ndarray,
        det: DetectorModel,
        seed: int,
        psf=None,
        epoch_utc: str | None = None,
        sc_position_km: np.ndarray | None = None,
        effects=None,
    ) -> Frame:
        """The raw frame at ``attitude`` (A), noise from ``seed``; ``psf`` as ``render_frame``'s;
        with ``epoch_utc`` (ISO-8601 UTC, the exposure's mid-time) the bright bodies' light, the
        Earth's too with ``sc_position_km`` (GCRS, km) (module docstring); ``effects`` a
        ``detector_effects.MissionEffects`` (radiation tracks, dose hot pixels, the detector at its
        temperature: the noise bank of :meth:`effective_detector`, drawn by the source at start-up),
        its draws seeded by ``seed``."""
        objs: list = []
        extra = None
        effects_truth = None
        if effects is not None:
            inputs = effects.render_inputs(attitude, self.camera, det, np.random.default_rng([seed, 35]))
            det, objs, extra, effects_truth = inputs.detector, inputs.false_objects, inputs.extra_e, inputs.truth
        margin_px = stamp_half_width(det) if psf is None else psf.max_half_width
        radius = self.camera.fov_half_angle_diagonal + (margin_px + 2.0) / self.camera.f
        near = stars_in_view(self.stars, attitude, radius)
        background, truth = None, None
        if epoch_utc is not None:
            glare = Glare(epoch_utc, sc_position_km)
            background = glare.background_e(attitude, self.camera, det)
            truth = glare.truth(attitude, self.camera, det)
            if not background.any():
                background = None
        bank = self.bank(det)
        noise = bank if background is None else GlareNoise(bank, background, self._prnu32(bank), self._unit_normal())
        # the dose's new hot pixels go in with the star signal: a few thousand pixels, whose Poisson
        # draw the bank makes at the lit pixels only (the glare's dense map has its own path)
        frame = render_frame(
            near, attitude, self.camera, det, seed=seed, psf=psf, noise=noise, false_objects=objs, background_e=extra
        ).frame
        if epoch_utc is not None:
            frame.timestamp = exposure_start(epoch_utc, det.exposure_s)
            frame.metadata["glare"] = truth
        if sc_position_km is not None:
            frame.metadata["sc_position_km"] = [float(v) for v in sc_position_km]
        if effects_truth is not None:
            frame.metadata["effects"] = effects_truth
        return frame

    @staticmethod
    def effective_detector(det: DetectorModel, effects=None) -> DetectorModel:
        """The detector an exposure with ``effects`` renders with (its dark current at the
        effects' temperature): the noise bank a source draws at start-up."""
        return det if effects is None else effects.detector_for(det)
