"""One exposure of the device's sky-rendering capture sources (``--sky``, ``--attitude-feed``).

``sensor_sim.render_frame`` at the exposure's attitude with two savings that keep the frame's
content (docs/hil.md has the timings):

* only the stars in view: the real sky (``sky_model.sky_stars``, cached) is cut to the cone of
  the field (``camera.fov_half_angle_diagonal`` plus the PSF stamp and smear margin) by one dot
  product of its unit vectors with the boresight, about 100 of 8 867 stars at V 6.5;
* the detector noise from a :class:`~ground.sim.noise_bank.NoiseBank` per detector, drawn once.

With the exposure's mid-time (``epoch_utc``) the Sun's and the Moon's light is rendered too
(``ground.sim.glare``), and the Earth's with the spacecraft's GCRS position (``sc_position_km``);
the frame carries ``timestamp`` = the mid-time and ``metadata["sc_position_km"]`` (the device's
bright-body check reads them) and ``metadata["glare"]`` (each body's angle from the boresight, in
view or not, its peak e-). A glare map with nothing above ``glare.FLOOR_E`` leaves the frame as
without it.
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.pipeline.raw_frame import Frame
from ground.sim.glare import Glare
from ground.sim.noise_bank import NoiseBank
from ground.sim.openloop import stars_in_cone as stars_in_view
from ground.sim.sensor_sim import DetectorModel, Stars, render_frame, stamp_half_width
from ground.sim.sky_model import sky_stars


class ExposureRenderer:
    """Renders exposures of ``camera`` from ``stars`` (default: the real sky to V 6.5)."""

    def __init__(self, camera: CameraModel, stars: Stars | None = None):
        self.camera = camera
        self.stars = sky_stars() if stars is None else stars
        self._banks: dict[DetectorModel, NoiseBank] = {}
        self._lock = threading.Lock()

    def draw_bank(self, det: DetectorModel) -> threading.Thread:
        """Start drawing the noise bank of ``det`` in a thread (numpy draws large arrays without the
        GIL, so a device's kernel loading goes on beside it) and return the thread; a render that
        comes first waits for it (:meth:`bank`'s lock). Capture sources call it at start-up and
        join it in ``ready`` before the device says it is listening."""
        thread = threading.Thread(target=self.bank, args=(det,), name="noise-bank", daemon=True)
        thread.start()
        return thread

    def bank(self, det: DetectorModel) -> NoiseBank:
        """The noise bank of ``det`` (drawn on first use: ~1 s for the reference design)."""
        key = dataclasses.replace(det, pattern="MONO")  # the noise does not depend on the CFA
        with self._lock:
            if key not in self._banks:
                self._banks[key] = NoiseBank(det, (self.camera.height, self.camera.width))
            return self._banks[key]

    def render(
        self,
        attitude: np.ndarray,
        det: DetectorModel,
        seed: int,
        psf=None,
        epoch_utc: str | None = None,
        sc_position_km: np.ndarray | None = None,
    ) -> Frame:
        """The raw frame at ``attitude`` (A), noise from ``seed``; ``psf`` as ``render_frame``'s;
        with ``epoch_utc`` (ISO-8601 UTC, the exposure's mid-time) the bright bodies' light, the
        Earth's too with ``sc_position_km`` (GCRS, km) (module docstring)."""
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
        frame = render_frame(
            near, attitude, self.camera, det, seed=seed, psf=psf, noise=self.bank(det), background_e=background
        ).frame
        if epoch_utc is not None:
            frame.timestamp = epoch_utc
            frame.metadata["glare"] = truth
        if sc_position_km is not None:
            frame.metadata["sc_position_km"] = [float(v) for v in sc_position_km]
        return frame
