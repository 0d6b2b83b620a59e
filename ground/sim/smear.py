"""Motion smear: the PSF of a star over an exposure while the sensor turns at a constant rate.

A star fixed in ICRS seen by a sensor turning at ``omega`` (rad/s, sensor axes, the rate of the
sensor frame with respect to ICRS) moves as ``dv/dt = -omega x v`` in sensor axes. Its image over
an exposure of ``exposure_s`` centred on the mid-time is the detector's pixel-integrated Gaussian
averaged over the mid-times of equal sub-intervals (at most :data:`STEP_PX` of track each), projected through the
camera, so roll smears arcs and cross-boresight rates smear lines. The object has the ``psf``
interface of ``sensor_sim.render_frame`` (``half_width``, ``max_half_width``, ``stamp``,
``to_dict``); positions are mid-exposure positions.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import erf

from ground.sim.sensor_sim import DetectorModel, stamp_half_width

STEP_PX = 0.25  #: largest step between sub-samples along a track
#: Longest track rendered (px): the work grows with the track's length squared (stamp area times
#: sub-steps), so a faster turn is refused (:class:`TooFast`) before anything is allocated.
MAX_TRACK_PX = 100.0


class TooFast(ValueError):
    """A rate that smears stars over more than :data:`MAX_TRACK_PX` in the exposure."""


class SmearPSF:
    """Gaussian PSF of ``det`` smeared by the rate ``omega`` (rad/s) over ``exposure_s`` on ``camera``."""

    def __init__(self, camera, det: DetectorModel, omega, exposure_s: float):
        if det.defocus_radius_px > 0:
            raise ValueError("smear renders the Gaussian PSF only (defocus_radius_px must be 0)")
        self.camera = camera
        self.sigma = det.psf_sigma_px
        self.omega = np.asarray(omega, dtype=float)
        self.exposure_s = float(exposure_s)
        corners_x = np.array([-0.5, camera.width - 0.5, -0.5, camera.width - 0.5, camera.cx])
        corners_y = np.array([-0.5, -0.5, camera.height - 0.5, camera.height - 0.5, camera.cy])
        self.max_track_px = float(np.max(self._track_length(corners_x, corners_y)))
        # the arc, too: a turn of a whole revolution in the exposure ends where it began
        arc_px = (
            float(np.linalg.norm(self.omega)) * self.exposure_s * max(camera.f, np.hypot(camera.width, camera.height))
        )
        if not (self.max_track_px <= MAX_TRACK_PX and arc_px <= 2.0 * MAX_TRACK_PX):
            rate = np.degrees(np.linalg.norm(self.omega))
            raise TooFast(
                f"a rate of {rate:.3g} deg/s smears stars over {self.max_track_px:.3g} px in the "
                f"{self.exposure_s:g} s exposure, beyond the {MAX_TRACK_PX:g} px the renderer draws"
            )
        self.steps = max(2, int(np.ceil(self.max_track_px / STEP_PX)))
        taus = ((np.arange(self.steps) + 0.5) / self.steps - 0.5) * self.exposure_s  # sub-interval mid-times
        self._rotations = Rotation.from_rotvec(-taus[:, None] * self.omega[None, :]).as_matrix()
        self.max_half_width = stamp_half_width(det) + int(np.ceil(self.max_track_px / 2.0)) + 1

    def _track_length(self, x, y) -> np.ndarray:
        """Pixel distance between the start and the end of the tracks through mid-exposure (x, y)."""
        v = self.camera.pixel_to_vector(np.atleast_1d(x), np.atleast_1d(y))
        ends = []
        for tau in (-0.5 * self.exposure_s, 0.5 * self.exposure_s):
            px, py = self.camera.vector_to_pixel(Rotation.from_rotvec(-tau * self.omega).apply(v))
            ends.append(np.stack([px, py]))
        return np.hypot(*(ends[1] - ends[0]))

    def half_width(self, x0: float, y0: float) -> int:
        return self.max_half_width

    def track(self, x0: float, y0: float) -> tuple[np.ndarray, np.ndarray]:
        """Pixel positions (x, y) of the sub-steps of the track through mid-exposure (x0, y0)."""
        v0 = self.camera.pixel_to_vector(np.array([x0]), np.array([y0]))[0]
        return self.camera.vector_to_pixel(self._rotations @ v0)

    def stamp(self, x0: float, y0: float, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
        xs, ys = self.track(x0, y0)
        s = np.sqrt(2.0) * self.sigma
        ex = 0.5 * (erf((cols[None, :] + 0.5 - xs[:, None]) / s) - erf((cols[None, :] - 0.5 - xs[:, None]) / s))
        ey = 0.5 * (erf((rows[None, :] + 0.5 - ys[:, None]) / s) - erf((rows[None, :] - 0.5 - ys[:, None]) / s))
        return ey.T @ ex / self.steps

    def to_dict(self) -> dict:
        return {
            "kind": "smear",
            "omega_rad_s": [float(v) for v in self.omega],
            "exposure_s": self.exposure_s,
            "sigma_px": self.sigma,
            "steps": self.steps,
        }
