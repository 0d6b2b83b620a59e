"""Planets and the Moon in the field of view: predicted positions and detection labels.

Positions come from astropy's built-in ephemeris (ERFA ``epv00`` for the Earth,
``plan94`` for the planets, ``moon98`` for the Moon; ``ephemeris="builtin"``, the
setting ``solar_system_ephemeris.set("builtin")`` selects). Nothing is downloaded:
the time-scale conversions (UTC -> TT, TDB) run with ``iers.conf.auto_download`` off, so
even an expired leap-second table never triggers a network fetch, and the optional
site rotation uses UT1 = UTC instead of IERS tables.

Direction convention: **astrometric** ICRS directions, the same kind as the star
catalog's (barycentric ICRS star positions propagated for proper motion, without
aberration or light deflection; ``ground/catalog/sources.py`` ``at_epoch``). For a body
this is ``p_body(t - tau) - p_observer(t)`` with the light time ``tau`` included and
stellar aberration excluded. Stars and planets seen in the same direction share the
same annual (20.5 arcsec) and orbital (<= 27 arcsec in LEO) aberration, so an attitude solved from
catalog stars maps these directions onto the detector without further correction.
Error budget (angle on the sky, geocentric):

* aberration left out of both stars and planets: cancels, except its variation across
  the field, <= 20.5 arcsec x sin(field radius), about 3 arcsec for a 9 deg radius;
* light deflection by the Sun: < 0.01 arcsec more than 45 deg from the Sun;
* ``plan94`` (ERFA documentation: max heliocentric errors over 1800-2100, scaled to
  the geocentric angle at the closest approach; RMS 1960-2025 at a typical distance):
  Mercury <= 6 arcsec, Venus <= 20, Mars <= 110 (RMS ~30), Jupiter <= 100 (RMS 25),
  Saturn <= 105 (RMS 35), Uranus <= 90 (RMS 45), Neptune <= 12; no worse than 1.5
  times these over 1000-3000;
* ``moon98``: 2.9 arcsec RMS, 18 arcsec worst (1950-2100);
* geocentric instead of topocentric (no ``site``): the Moon up to 1 deg (more from orbit),
  Venus up to 34 arcsec, Mars 24 arcsec, the others < 10 arcsec; with a ``site``, UT1 = UTC leaves
  < 0.3 arcsec on the Moon.

So a predicted centre is good to <= 2 arcmin (worst case) and ~30 arcsec typically,
i.e. 0.5-12 px worst for pixels of 10-70 arcsec.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from functools import lru_cache

import erfa
import numpy as np
from astropy import units as u
from astropy.coordinates import get_body_barycentric, get_body_barycentric_posvel
from astropy.time import Time
from astropy.utils import iers

from firmware_model.reference_frames import quat_to_matrix
from protocol.result import BODIES

#: Bodies predicted for each frame (``protocol.result.BODIES``: the planets, then the Moon, the
#: only extended one; their order gives the body codes of the result's star flags).
PLANETS = BODIES[:-1]
EXTENDED = frozenset({"moon"})

#: Equatorial radii (km, IAU WGCCRE); Saturn's globe, its rings reach 2.3 times further.
RADIUS_KM = {
    "mercury": 2440.5,
    "venus": 6051.8,
    "mars": 3396.2,
    "jupiter": 71492.0,
    "saturn": 60268.0,
    "uranus": 25559.0,
    "neptune": 24764.0,
    "moon": 1737.4,
    "sun": 695700.0,
}

#: Angular tolerance (rad) of the default planet match: the worst ephemeris error
#: (110 arcsec, module docstring) plus the attitude and centroid errors.
DEFAULT_TOL = np.radians(2.5 / 60.0)
#: Smallest default match radius in pixels (centroid of a bright, possibly saturated blob).
MIN_TOL_PX = 3.0
#: Margin (rad) beyond the Moon's limb inside which detections are glare, not stars.
DEFAULT_MOON_MARGIN = np.radians(0.25)

_C_KM_S = 299792.458
_EPHEMERIS = "builtin"


@dataclass(frozen=True)
class BodyPosition:
    """A body at an epoch: ``direction`` unit vector (ICRS axes, astrometric, from the
    observer), ``distance_km``, ``angular_radius`` (rad) and whether it is ``extended``."""

    name: str
    direction: np.ndarray
    distance_km: float
    angular_radius: float
    extended: bool


@dataclass(frozen=True)
class BodyInView:
    """A body whose centre (or, for the Moon, whose disk) falls on the array: predicted
    pixel ``(x, y)`` of its centre (px, may be off the array for the Moon) and its disk
    radius ``radius_px``."""

    name: str
    x: float
    y: float
    radius_px: float


@dataclass(frozen=True)
class PlanetLabel:
    """Detection ``index`` lies ``distance_px`` from the predicted centre of ``body``."""

    index: int
    body: str
    distance_px: float


@lru_cache(maxsize=64)
def _parse_utc(epoch: str) -> Time:
    """ISO-8601 time; an explicit UTC offset (``Z``, ``+00:00``, ``+02:00``) is applied, none means UTC."""
    try:
        when = datetime.fromisoformat(epoch)
    except ValueError:
        return Time(epoch, scale="utc")  # astropy's own formats (e.g. year-day)
    if when.tzinfo is not None:
        when = when.astimezone(UTC).replace(tzinfo=None)
    return Time(when, scale="utc")


def _as_time(epoch) -> Time:
    return epoch if isinstance(epoch, Time) else _parse_utc(epoch)


def _site_gcrs_km(site, t: Time) -> np.ndarray:
    """GCRS position (km) of a geodetic WGS84 site ``(lat_deg, lon_deg, height_m)``;
    UT1 = UTC and no polar motion (errors of tens of metres)."""
    lat_deg, lon_deg, height_m = site
    itrs_m = erfa.gd2gc(1, np.radians(lon_deg), np.radians(lat_deg), float(height_m))
    tt = t.tt
    utc = t.utc
    c2t = erfa.c2t06a(tt.jd1, tt.jd2, utc.jd1, utc.jd2, 0.0, 0.0)
    return c2t.T @ itrs_m / 1000.0


def astrometric_positions(epoch, bodies=BODIES, site=None, observer_gcrs_km=None) -> dict[str, np.ndarray]:
    """Astrometric positions (km, ICRS axes) of ``bodies`` (names of the built-in
    ephemeris, e.g. "jupiter", "moon", "sun") from the geocentre, from ``site``
    ``(lat_deg, lon_deg, height_m)``, or from a spacecraft at ``observer_gcrs_km`` (GCRS
    position, km): ``p_body(t - tau) - p_observer(t)``, light time ``tau`` included, no
    aberration. ``epoch``: ISO-8601 UTC string or astropy Time."""
    t = _as_time(epoch)
    out = {}
    with iers.conf.set_temp("auto_download", False):
        observer = get_body_barycentric("earth", t, ephemeris=_EPHEMERIS).xyz.to_value(u.km)
        if site is not None:
            observer = observer + _site_gcrs_km(site, t)
        if observer_gcrs_km is not None:
            observer = observer + np.asarray(observer_gcrs_km, dtype=float)
        for name in bodies:
            pos, vel = get_body_barycentric_posvel(name, t, ephemeris=_EPHEMERIS)
            p = pos.xyz.to_value(u.km)
            v = vel.xyz.to_value(u.km / u.s)
            rel = p - observer
            # light time by fixed point on a linear path: the curvature over tau (<~ 1 h)
            # is < 1 km, far below the ephemeris error
            for _ in range(3):
                rel = p - v * (np.linalg.norm(rel) / _C_KM_S) - observer
            out[name] = rel
    return out


@lru_cache(maxsize=64)
def _positions_cached(scale: str, jd1: float, jd2: float, site) -> dict[str, BodyPosition]:
    t = Time(jd1, jd2, format="jd", scale=scale)
    out = {}
    for name, rel in astrometric_positions(t, BODIES, site).items():
        dist = float(np.linalg.norm(rel))
        out[name] = BodyPosition(name, rel / dist, dist, float(np.arcsin(RADIUS_KM[name] / dist)), name in EXTENDED)
    return out


def body_positions(epoch, site=None) -> dict[str, BodyPosition]:
    """``BodyPosition`` of every body in ``BODIES`` at ``epoch`` (ISO-8601 UTC string or
    astropy Time), geocentric or from ``site`` ``(lat_deg, lon_deg, height_m)``.
    Cached per (epoch, site): a frame replay pays the ephemeris once per frame."""
    t = _as_time(epoch)
    site = None if site is None else tuple(map(float, site))
    return _positions_cached(t.scale, float(t.jd1), float(t.jd2), site)


def planet_directions(epoch, site=None) -> dict[str, np.ndarray]:
    """Astrometric unit vectors (ICRS axes) of the seven planets and the Moon at
    ``epoch``; see ``body_positions`` for the arguments and the module docstring for
    the convention and its error budget."""
    return {name: b.direction for name, b in body_positions(epoch, site).items()}


def _project(bodies, a: np.ndarray, camera):
    """Pixel centres and disk radii (px) of ``bodies`` under attitude matrix ``a``; NaN
    centres for bodies behind the camera."""
    d = np.array([b.direction for b in bodies])
    ds = d @ a.T
    x, y = camera.vector_to_pixel(ds)
    # a point one angular radius off the centre gives the local disk radius in pixels
    perp = np.cross(ds, np.array([0.0, 0.0, 1.0]))
    perp[np.linalg.norm(perp, axis=1) < 1e-12] = [1.0, 0.0, 0.0]
    perp /= np.linalg.norm(perp, axis=1, keepdims=True)
    rad = np.array([b.angular_radius for b in bodies])[:, None]
    xe, ye = camera.vector_to_pixel(np.cos(rad) * ds + np.sin(rad) * perp)
    return x, y, np.hypot(xe - x, ye - y)


def default_tol_px(camera) -> float:
    """Default match radius (px): ``DEFAULT_TOL`` at the camera's focal length, at least
    ``MIN_TOL_PX``."""
    return max(MIN_TOL_PX, DEFAULT_TOL * camera.f)


def planets_in_view(
    q_icrs_to_sensor, camera, epoch, site=None, moon_margin: float = DEFAULT_MOON_MARGIN
) -> list[BodyInView]:
    """Bodies whose predicted centre falls inside the array, plus the Moon when its disk
    widened by ``moon_margin`` (rad) reaches the array; ordered as ``BODIES``."""
    bodies = list(body_positions(epoch, site).values())
    x, y, r = _project(bodies, quat_to_matrix(q_icrs_to_sensor), camera)
    out = []
    for b, xi, yi, ri in zip(bodies, x, y, r):
        if not np.isfinite(xi):
            continue
        reach = ri + moon_margin * camera.f if b.extended else 0.0
        # distance from the centre to the nearest point of the array rectangle
        dx = max(-0.5 - xi, 0.0, xi - (camera.width - 0.5))
        dy = max(-0.5 - yi, 0.0, yi - (camera.height - 0.5))
        if bool(camera.in_frame(xi, yi)) or np.hypot(dx, dy) < reach:
            out.append(BodyInView(b.name, float(xi), float(yi), float(ri)))
    return out


def label_planets(
    x,
    y,
    q_icrs_to_sensor,
    camera,
    epoch,
    tol_px: float | None = None,
    site=None,
    moon_margin: float = DEFAULT_MOON_MARGIN,
) -> list[PlanetLabel]:
    """Detections (pixel coordinates ``x``, ``y``) that sit on a predicted body, for a
    frame at ``epoch`` with attitude ``q_icrs_to_sensor``: within ``tol_px`` (default
    ``default_tol_px(camera)``) plus the body's disk radius of its centre, and for the
    Moon within its disk plus ``moon_margin`` (rad) plus ``tol_px``. One label per
    detection (the nearest body, by distance beyond its disk edge), sorted by index."""
    x = np.atleast_1d(np.asarray(x, dtype=float))
    y = np.atleast_1d(np.asarray(y, dtype=float))
    if x.shape != y.shape:
        raise ValueError(f"x and y must have the same length, got {x.shape} and {y.shape}")
    tol = default_tol_px(camera) if tol_px is None else float(tol_px)
    bodies = list(body_positions(epoch, site).values())
    bx, by, br = _project(bodies, quat_to_matrix(q_icrs_to_sensor), camera)
    reach = br + tol + np.array([moon_margin * camera.f if b.extended else 0.0 for b in bodies])
    dist = np.hypot(x[:, None] - bx[None, :], y[:, None] - by[None, :])  # (n_det, n_body), NaN behind
    excess = np.where(dist <= reach[None, :], dist - br[None, :], np.inf)
    labels = []
    for i in np.flatnonzero(np.isfinite(excess).any(axis=1)):
        j = int(np.argmin(excess[i]))
        labels.append(PlanetLabel(int(i), bodies[j].name, float(dist[i, j])))
    return labels
