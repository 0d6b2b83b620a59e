"""The Sun, the Moon and the Earth as a spacecraft's star tracker sees them: where they are and
how large, for the bright-body exclusion check (``pipeline.exclusion``) and for rendering glare
(``ground.sim.glare``).

Directions are astrometric ICRS unit vectors from the observer (``planets``' convention and
ephemeris: astropy's built-in ``epv00``/``moon98``, nothing downloaded): from the spacecraft when
its GCRS position is known (km; a frame's ``metadata["sc_position_km"]``), else from the geocentre,
where the Earth has no direction and is left out. The Moon's parallax between the geocentre and a
spacecraft in LEO is up to 1 deg, so a check near the Moon wants the position.

The Earth's apparent disc is taken out to :data:`ATMOSPHERE_KM` above the surface, where the
daylit limb stops scattering enough light to matter to a star tracker (an assumption: the
airglow and twilight layers reach about 100 km).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

EARTH_RADIUS_KM = 6378.137  #: WGS84 equatorial radius
ATMOSPHERE_KM = 100.0  #: height of the bright limb above the surface (assumption, module docstring)
NAMES = ("sun", "moon", "earth")


@dataclass(frozen=True)
class SkyBody:
    """A bright body seen from the observer: ``direction`` unit vector (ICRS axes) to its centre,
    ``distance_km``, ``angular_radius`` (rad) of its disc (the Earth's to the bright limb)."""

    name: str
    direction: np.ndarray
    distance_km: float
    angular_radius: float

    def edge_angle(self, boresight: np.ndarray) -> float:
        """Angle (rad) from the unit vector ``boresight`` (ICRS axes) to the nearest point of the
        disc; negative when the boresight is inside it."""
        c = float(np.clip(np.dot(self.direction, boresight), -1.0, 1.0))
        return math.acos(c) - self.angular_radius


def sky_bodies(epoch, sc_position_km=None) -> dict[str, SkyBody]:
    """The Sun and the Moon (and the Earth when ``sc_position_km``, the observer's GCRS position
    in km, is given) at ``epoch`` (ISO-8601 UTC string or astropy Time)."""
    # the ephemerides import astropy, slow: only when bodies are placed
    from firmware_model.pipeline.planets import RADIUS_KM, _as_time, astrometric_positions

    t = _as_time(epoch)
    observer = None if sc_position_km is None else np.asarray(sc_position_km, dtype=float).reshape(3)
    out = {}
    for name, rel in astrometric_positions(t, ("sun", "moon"), observer_gcrs_km=observer).items():
        dist = float(np.linalg.norm(rel))
        out[name] = SkyBody(name, rel / dist, dist, math.asin(min(1.0, RADIUS_KM[name] / dist)))
    if observer is not None:
        r = float(np.linalg.norm(observer))
        limb = EARTH_RADIUS_KM + ATMOSPHERE_KM
        if r <= limb:
            raise ValueError(f"spacecraft position {r:.0f} km from the geocentre is inside the atmosphere")
        out["earth"] = SkyBody("earth", -observer / r, r, math.asin(limb / r))
    return out
