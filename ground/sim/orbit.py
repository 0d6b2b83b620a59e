"""A circular Keplerian orbit: the spacecraft position a rendered sky needs for the Earth's limb,
the Moon's parallax, eclipses and the South Atlantic Anomaly.

Two-body motion on a circle (no J2, no drag: over the minutes of a HIL run the node drifts by
about 0.001 deg per minute at 550 km and the altitude stays put, far below what glare and
exclusion depend on). Written by hand: it is six lines of geometry, and no propagator among the
project's dependencies is lighter (Basilisk is optional).

Positions are GCRS (km, ICRS-aligned axes, origin the geocentre); times POSIX UTC seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from astropy.time import Time

MU_EARTH_KM3_S2 = 398600.4418  #: WGS84 / EGM96 gravitational parameter
EARTH_RADIUS_KM = 6378.137


@dataclass(frozen=True)
class CircularOrbit:
    """``altitude_km`` above the equatorial radius, ``inclination_deg``, ``raan_deg`` (right
    ascension of the ascending node, GCRS), ``arg_latitude_deg`` (angle from the node along the
    orbit) at ``epoch_utc`` (ISO-8601 UTC)."""

    altitude_km: float
    inclination_deg: float = 97.6
    raan_deg: float = 0.0
    arg_latitude_deg: float = 0.0
    epoch_utc: str = "2026-06-01T00:00:00"

    def __post_init__(self):
        if not 100.0 <= self.altitude_km <= 400_000.0:
            raise ValueError(f"orbit altitude {self.altitude_km:g} km is outside 100-400000 km")
        if not 0.0 <= self.inclination_deg <= 180.0:
            raise ValueError(f"orbit inclination {self.inclination_deg:g} deg is outside 0-180 deg")

    @property
    def radius_km(self) -> float:
        return EARTH_RADIUS_KM + self.altitude_km

    @property
    def mean_motion_rad_s(self) -> float:
        return math.sqrt(MU_EARTH_KM3_S2 / self.radius_km**3)

    @property
    def period_s(self) -> float:
        return 2.0 * math.pi / self.mean_motion_rad_s

    @property
    def epoch_posix(self) -> float:
        from astropy.time import Time  # astropy is slow to import: only when a time is converted

        return float(Time(self.epoch_utc, scale="utc").unix)

    def _frame(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit vectors of the ascending node and of the orbit's 90-deg point (GCRS)."""
        i, o = math.radians(self.inclination_deg), math.radians(self.raan_deg)
        node = np.array([math.cos(o), math.sin(o), 0.0])
        quarter = np.array([-math.sin(o) * math.cos(i), math.cos(o) * math.cos(i), math.sin(i)])
        return node, quarter

    def position_gcrs_km(self, t_posix: float) -> np.ndarray:
        """GCRS position (km) at POSIX UTC time ``t_posix``."""
        u = math.radians(self.arg_latitude_deg) + self.mean_motion_rad_s * (t_posix - self.epoch_posix)
        node, quarter = self._frame()
        return self.radius_km * (math.cos(u) * node + math.sin(u) * quarter)

    def velocity_gcrs_km_s(self, t_posix: float) -> np.ndarray:
        """GCRS velocity (km/s) at ``t_posix``."""
        u = math.radians(self.arg_latitude_deg) + self.mean_motion_rad_s * (t_posix - self.epoch_posix)
        node, quarter = self._frame()
        return self.radius_km * self.mean_motion_rad_s * (-math.sin(u) * node + math.cos(u) * quarter)

    @classmethod
    def parse(cls, spec: str) -> CircularOrbit:
        """``ALT_KM[,INC_DEG[,RAAN_DEG[,ARG_LAT_DEG[,EPOCH_UTC]]]]`` (the ``--orbit`` option); ValueError
        with a one-line reason."""
        parts = [p.strip() for p in spec.split(",")]
        if not 1 <= len(parts) <= 5 or not all(parts):
            raise ValueError(f"orbit {spec!r}: expected ALT_KM[,INC_DEG[,RAAN_DEG[,ARG_LAT_DEG[,EPOCH_UTC]]]]")
        try:
            numbers = [float(p) for p in parts[:4]]
        except ValueError:
            raise ValueError(f"orbit {spec!r}: altitude and angles must be numbers") from None
        if not all(math.isfinite(v) for v in numbers):
            raise ValueError(f"orbit {spec!r}: altitude and angles must be finite")
        kwargs: dict[str, float | str] = dict(
            zip(("altitude_km", "inclination_deg", "raan_deg", "arg_latitude_deg"), numbers, strict=False)
        )
        if len(parts) == 5:
            try:
                kwargs["epoch_utc"] = parse_utc(parts[4]).isot
            except ValueError as exc:
                raise ValueError(f"orbit {spec!r}: epoch {parts[4]!r} {exc}") from None
        return cls(**kwargs)  # type: ignore[arg-type]


#: The earliest time a schedule, an orbit or a feed may name: UTC with leap seconds, as it is now,
#: began in 1972 (the Earth orientation table, ``ground.sim.earth_orientation``, starts in 1962).
EARLIEST_UTC = "1972-01-01T00:00:00"


def parse_utc(text: str) -> Time:
    """A UTC time from ISO-8601 text (or another astropy format); ValueError whose text completes
    ``time '...' <reason>``: not a time, before :data:`EARLIEST_UTC`, or one ERFA warns about
    (a second 60 on a day without a leap second, a year beyond the leap-second table's reach)."""
    import warnings

    from astropy.time import Time
    from erfa import ErfaWarning

    early = f"is before {EARLIEST_UTC[:10]}: UTC as it is (with leap seconds) began in 1972"
    with warnings.catch_warnings():
        warnings.simplefilter("error", ErfaWarning)
        try:
            t = Time(text, scale="utc")
            t.tt  # noqa: B018 - the conversion ERFA checks the year in
        except ErfaWarning as exc:
            why = str(exc).split(' of "', 1)[-1].split(" (Note")[0].rstrip('"')
            if "dubious year" in why and str(text).strip()[:4] < EARLIEST_UTC[:4]:
                raise ValueError(early) from None
            if "dubious year" in why:
                why = "a year beyond the leap-second table's reach: ERFA's dubious year"
            elif "end of day" in why:
                why = "second 60 on a day without a leap second"
            raise ValueError(f"is not a valid UTC time ({why})") from None
        except (ValueError, TypeError):
            raise ValueError("is not ISO-8601 UTC (YYYY-MM-DDThh:mm:ss)") from None
    if not t.isscalar:
        raise ValueError("is not one time")
    if t < Time(EARLIEST_UTC, scale="utc"):
        raise ValueError(early)
    return t


def utc_iso(t_posix: float) -> str:
    """ISO-8601 UTC string (ms) of POSIX time ``t_posix`` (s), as astropy writes it."""
    from astropy.time import Time

    return str(Time(t_posix, format="unix", scale="utc").isot)


def in_earth_shadow(position_km: np.ndarray, sun_direction: np.ndarray) -> bool:
    """Whether a spacecraft at ``position_km`` (GCRS) is in the Earth's cylindrical shadow, the Sun
    along the unit vector ``sun_direction`` (penumbra ignored: it lasts about 8 s in LEO)."""
    r = np.asarray(position_km, dtype=float)
    along = float(np.dot(r, sun_direction))
    return along < 0.0 and float(np.linalg.norm(r - along * np.asarray(sun_direction))) < EARTH_RADIUS_KM
