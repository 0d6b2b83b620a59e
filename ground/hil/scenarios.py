"""The closed loop's scenarios (docs/hil.md "Scenarios"): where the spacecraft is and where the
controller points it, so that a bright body crosses the tracker's exclusion angle during a run.

A scenario is planned for the run's start (POSIX UTC s): the device stamps each exposure with its
own clock, so the sky is the real one at the time of the run. Each declares

* the orbit (a :class:`~ground.sim.orbit.CircularOrbit` whose epoch is the start), sent as the
  feed samples' ``r``;
* the initial attitude (the slew's start, at rest) and the controller's target profile
  (:class:`Slew`: hold, turn at a constant rate about a fixed inertial axis, hold);
* the exclusion angles the device is given (slot-2 ``*_exclusion_deg``).

``eclipse-exit``: a noon-midnight orbit phased so the spacecraft leaves the Earth's shadow
(``in_earth_shadow``, searched over the orbit) during the first hold. At sunrise the Sun is at the
Earth's limb, so a boresight within the Sun's limit would be inside the Earth's too; the slew waits
until the Sun has risen far enough, then turns about the Earth's direction (a cone
``limit_earth + 5`` deg outside the bright limb) so that the boresight passes the Sun ``DEPTH_DEG``
inside its limit, from and to ``limit + 6`` deg.
``moon-slew``: the spacecraft above the sub-lunar point (the Earth behind it); a slew through
the Moon's centre, across the Sun-Moon line, from and to ``limit + 6`` deg off the disc.
The Moon's phase is the day's: the run cannot choose its date.

Angles in the code are radians; ``_deg`` names are degrees; times s since the start unless POSIX.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from firmware_model.pipeline.sky_bodies import sky_bodies
from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat, quat_to_matrix
from ground.sim.orbit import CircularOrbit, in_earth_shadow, utc_iso

NAMES = ("none", "eclipse-exit", "moon-slew", "two-heads")  #: two-heads: ground.hil.two_heads_scenario

#: Exclusion angles the scenarios give the device, deg (edge of the disc to the boresight): the
#: device's defaults (``pipeline.exclusion.ExclusionLimits``: Sun 30 and Moon 25 from CryoSat's
#: HE-5AS baffle, the Earth's 25 an assumption), written out so a run states them.
LIMITS_DEG = {"sun": 30.0, "moon": 25.0, "earth": 25.0}
ALTITUDE_KM = 550.0  #: assumption: a typical LEO small satellite
INCLINATION_DEG = 97.6  #: sun-synchronous at 550 km (assumption: the orbit class, not a mission)
#: the target's turn rate: below the ~1.1 deg/s up to which the device still solved every smeared
#: frame of a 1.5 deg/s run (none above 1.4 deg/s; docs/hil.md "Scenarios"), so the tracker keeps
#: its attitude up to the body and the exclusion check has one to judge by
SLEW_RATE_DEG_S = 0.8
HOLD_S = 4.0  #: at the start attitude before the slew (the tracker's first fixes)
SETTLE_S = 26.0  #: after the slew: the controller (omega_n 0.3 rad/s, zeta 0.9) settles
MARGIN_DEG = 6.0  #: the path's ends are this far outside the body's limit
DEPTH_DEG = 4.0  #: eclipse-exit: the Sun's closest approach this far inside its limit
EARTH_CLEAR_DEG = 5.0  #: eclipse-exit: the boresight's cone this far outside the Earth's limit


@dataclass(frozen=True)
class Slew:
    """Target profile: ``q_start`` (q_icrs_to_sensor) until ``t_start`` s, then a turn of
    ``angle`` rad about the ICRS unit vector ``axis`` at ``rate`` rad/s, then held."""

    q_start: np.ndarray
    axis: np.ndarray
    angle: float
    t_start: float
    rate: float

    @property
    def t_end(self) -> float:
        return self.t_start + self.angle / self.rate

    def turned(self, t: float) -> float:
        """Angle (rad) turned by ``t`` s."""
        return float(np.clip((t - self.t_start) * self.rate, 0.0, self.angle))

    def attitude(self, t: float) -> np.ndarray:
        """Target attitude matrix ``A`` (v_sensor = A v_icrs) at ``t`` s: the start attitude's
        sensor turned about ``axis`` (inertial) by :meth:`turned`."""
        return quat_to_matrix(self.q_start) @ Rotation.from_rotvec(self.turned(t) * self.axis).as_matrix().T

    def target(self, t: float) -> np.ndarray:
        """Target quaternion at ``t`` s."""
        return matrix_to_quat(self.attitude(t))

    def boresight(self, t: float) -> np.ndarray:
        """Target boresight (ICRS unit vector) at ``t`` s."""
        return self.attitude(t)[2]


@dataclass(frozen=True)
class Scenario:
    """A planned run: ``body`` the one that crosses its limit, the orbit (epoch = the start), the
    slew, the limits (deg), the run's length (s), and the start (POSIX s) it was planned for."""

    name: str
    body: str
    orbit: CircularOrbit
    slew: Slew
    limits_deg: dict[str, float]
    duration_s: float
    start_posix: float

    def params(self) -> dict[str, float]:
        """The device's slot-2 parameters for the run."""
        return {f"{b}_exclusion_deg": v for b, v in self.limits_deg.items()}

    heads = ()  #: one head: the device's own, mounted at the identity

    def position_km(self, t: float) -> np.ndarray:
        """GCRS position (km) ``t`` s after the start, whenever the run starts."""
        return self.orbit.position_gcrs_km(self.start_posix + t)

    @property
    def position_at(self):
        """What the feed's samples carry as ``r`` (s since the start -> GCRS km)."""
        return self.position_km

    def report(self, log, rows: list[dict], plot_path) -> dict:
        """The summary's scenario figures; the plot written to ``plot_path``."""
        from ground.hil import scenario_report

        tr = scenario_report.track(log)
        scenario_report.plot_scenario(self, log, rows, tr, plot_path)
        return scenario_report.summarise_scenario(self, log, rows, tr)

    def failure(self, summary: dict, pass_mark_deg: float, fresh_fix_s: float) -> str | None:
        """Why the run fails the scenario's pass mark, or None."""
        from ground.hil import scenario_report

        del fresh_fix_s  # one head: the demo's own fresh-fix check applies
        return scenario_report.scenario_failure(summary, pass_mark_deg)


def plan(name: str, start_posix: float, limits_deg: dict[str, float] | None = None):
    """Scenario ``name`` (not ``none``) for a run starting at POSIX ``start_posix``; ValueError
    with a one-line reason when the day's geometry does not allow it."""
    limits = dict(LIMITS_DEG if limits_deg is None else limits_deg)
    if name == "eclipse-exit":
        return _checked(_eclipse_exit(start_posix, limits))
    if name == "moon-slew":
        return _checked(_moon_slew(start_posix, limits))
    if name == "two-heads":
        from ground.hil import two_heads_scenario

        return two_heads_scenario.plan(start_posix, limits)
    raise ValueError(f"unknown scenario {name!r}; known: {', '.join(NAMES)}")


def _checked(sc: Scenario, step_s: float = 1.0) -> Scenario:
    """``sc`` when, along its planned boresight (every ``step_s``), its body goes inside its limit
    and no other body comes within 1 deg of its own (a new Moon beside the Sun spoils both)."""
    closest = _closest(sc.orbit, sc.start_posix, sc.slew, step_s)
    if not closest[sc.body] < sc.limits_deg[sc.body]:
        raise ValueError(f"{sc.name}: the {sc.body} stays {closest[sc.body]:.1f} deg from the boresight")
    for name, edge in closest.items():
        if name != sc.body and edge < sc.limits_deg[name] + 1.0:
            raise ValueError(
                f"{sc.name}: the {name} comes {edge:.1f} deg from the planned boresight at that epoch, "
                f"within its {sc.limits_deg[name]:g} deg limit (+1 deg): choose another --epoch"
            )
    return sc


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _path(centre: np.ndarray, axis: np.ndarray, before: float, after: float, t_start: float, rate: float) -> Slew:
    """A slew about the unit ``axis`` whose boresight passes ``centre``, turning ``before`` rad
    before it and ``after`` rad after."""
    b0 = Rotation.from_rotvec(-before * axis).apply(centre)
    a0 = attitude_from_radec_roll(math.atan2(b0[1], b0[0]), math.asin(float(np.clip(b0[2], -1, 1))), 0.0)
    return Slew(matrix_to_quat(a0), axis, before + after, t_start, rate)


def sunrise_after(orbit: CircularOrbit, t0_posix: float, sun: np.ndarray) -> float:
    """POSIX time of the first exit from the Earth's shadow after ``t0_posix`` (within one period):
    a 10 s scan with ``in_earth_shadow``, then Brent's method on the shadow boundary."""
    t_grid = t0_posix + np.arange(0.0, orbit.period_s + 10.0, 10.0)
    shadow = [in_earth_shadow(orbit.position_gcrs_km(t), sun) for t in t_grid]
    for k in range(len(t_grid) - 1):
        if shadow[k] and not shadow[k + 1]:

            def margin(t: float) -> float:  # > 0 outside the shadow cylinder, on the night side
                r = orbit.position_gcrs_km(t)
                return float(np.linalg.norm(r - np.dot(r, sun) * sun)) - 6378.137

            return float(brentq(margin, t_grid[k], t_grid[k + 1], xtol=1e-3))
    raise ValueError("eclipse-exit: this orbit has no eclipse at that epoch")


def _eclipse_exit(start: float, limits: dict[str, float]) -> Scenario:
    s_lim, rate = math.radians(limits["sun"]), math.radians(SLEW_RATE_DEG_S)
    sun = sky_bodies(utc_iso(start))["sun"].direction
    raan = math.degrees(math.atan2(sun[1], sun[0]))  # noon-midnight plane: the longest eclipse
    probe = CircularOrbit(ALTITUDE_KM, INCLINATION_DEG, raan, 0.0, utc_iso(start))
    t_exit = sunrise_after(probe, start, sun)
    arg_lat = math.degrees(probe.mean_motion_rad_s * (t_exit - start - HOLD_S)) % 360.0  # sunrise at HOLD_S
    orbit = CircularOrbit(ALTITUDE_KM, INCLINATION_DEG, raan, arg_lat, utc_iso(start))
    earth = sky_bodies(utc_iso(start), orbit.position_gcrs_km(start))["earth"]
    cone = earth.angular_radius + math.radians(limits["earth"] + EARTH_CLEAR_DEG)  # boresight to the Earth's centre
    need = cone - (s_lim - math.radians(DEPTH_DEG)) - sky_bodies(utc_iso(start))["sun"].angular_radius
    ends = s_lim + math.radians(MARGIN_DEG)

    def sun_from_earth(t: float) -> float:  # rad, the Sun's angle from the Earth's direction at t s
        return math.acos(float(np.clip(-np.dot(_unit(orbit.position_gcrs_km(start + t)), sun), -1.0, 1.0)))

    t_cross = float(brentq(lambda t: sun_from_earth(t) - need, HOLD_S, HOLD_S + 0.25 * orbit.period_s, xtol=1e-3))
    sigma = sun_from_earth(t_cross)
    cos_half = (math.cos(ends) - math.cos(cone) * math.cos(sigma)) / (math.sin(cone) * math.sin(sigma))
    half = math.acos(float(np.clip(cos_half, -1.0, 1.0)))  # turn about the Earth's direction to each end
    t_cross = max(t_cross, HOLD_S + half / rate)
    e = -_unit(orbit.position_gcrs_km(start + t_cross))
    out = _unit(sun - np.dot(sun, e) * e)  # from the Earth's direction toward the Sun
    centre = math.cos(cone) * e + math.sin(cone) * out
    # from the hold on, the boresight rides the cone about the Earth's direction at the crossing
    # (the Earth turns away from the Sun as the spacecraft climbs), in the sense that keeps the
    # Earth and the Moon further outside their limits
    slews = [_path(centre, sense * e, (t_cross - HOLD_S) * rate, half, HOLD_S, rate) for sense in (1.0, -1.0)]

    def clearance(sl: Slew) -> float:
        closest = _closest(orbit, start, sl)
        return min(closest[b] - limits[b] for b in ("earth", "moon"))

    slew = max(slews, key=clearance)
    return Scenario("eclipse-exit", "sun", orbit, slew, limits, slew.t_end + SETTLE_S, start)


def _closest(orbit: CircularOrbit, start: float, slew: Slew, step_s: float = 1.0) -> dict[str, float]:
    """Each body's closest edge angle (deg) to the planned boresight, every ``step_s`` of the slew."""
    out = {name: math.inf for name in ("sun", "moon", "earth")}
    for t in np.arange(0.0, slew.t_end + step_s, step_s):
        for name, b in sky_bodies(utc_iso(start + t), orbit.position_gcrs_km(start + t)).items():
            out[name] = min(out[name], math.degrees(b.edge_angle(slew.boresight(t))))
    return out


def _moon_slew(start: float, limits: dict[str, float]) -> Scenario:
    m_lim, rate = math.radians(limits["moon"]), math.radians(SLEW_RATE_DEG_S)
    geo = sky_bodies(utc_iso(start))
    m, sun = geo["moon"].direction, geo["sun"].direction
    inc = math.radians(INCLINATION_DEG)
    u = math.asin(float(np.clip(m[2] / math.sin(inc), -1.0, 1.0)))  # the orbit passes over the sub-lunar point
    raan = math.atan2(m[1], m[0]) - math.atan2(math.sin(u) * math.cos(inc), math.cos(u))
    orbit = CircularOrbit(ALTITUDE_KM, INCLINATION_DEG, math.degrees(raan) % 360.0, math.degrees(u), utc_iso(start))
    half = m_lim + geo["moon"].angular_radius + math.radians(MARGIN_DEG)
    t_cross = HOLD_S + half / rate
    moon = sky_bodies(utc_iso(start + t_cross), orbit.position_gcrs_km(start + t_cross))["moon"]
    across = _unit(np.cross(moon.direction, sun))  # the path heads across the Sun-Moon line
    slew = _path(moon.direction, _unit(np.cross(moon.direction, across)), half, half, HOLD_S, rate)
    return Scenario("moon-slew", "moon", orbit, slew, limits, slew.t_end + SETTLE_S, start)
