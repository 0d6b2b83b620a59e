"""The closed loop's two-head scenario (``hil demo --scenario two-heads``, docs/hil.md "Two heads
in the loop"): a slew that carries head 0x0E's boresight past the Sun while head 0x0F looks away,
and the flight side's head selection.

The heads are :data:`ground.hil.two_heads.HEADS`: 0x0E at the identity mounting (boresight the
body's +z), 0x0F mounted 90 deg about the body's y axis (boresight the body's -x). The slew turns the
body about an inertial axis ``k`` at ``SLEW_RATE_DEG_S``, with the body's x axis along ``k``: head
0x0F's boresight (``-k``) stays put, 90 deg + ``CLOSEST_DEG`` from the Sun, while head 0x0E's sweeps a
great circle that passes ``CLOSEST_DEG`` from the Sun's centre, from and to ``limit + MARGIN_DEG``
off the disc. The orbit is high (``ALTITUDE_KM``, polar) and phased so that the Earth, 8.7 deg in
radius from there, lies far from both heads' paths (its centre opposite the closest point and the
turn's axis together); the feed's samples carry that position, so the device renders and judges
the bodies as seen from it. Where the Sun's side of the sky is chosen (the turn about the Sun's
direction that places the closest point), the Moon and the Earth must stay 1 deg outside their
limits from both heads' paths; the first such side is taken.

Pass mark (:func:`scenario_failure`): the final pointing error under the demo's mark; head 0x0E
reported the Sun (SUN_IN_FOV or BLINDED) at least once; no answer but an OK one was used; and
the flight side's newest used fix was never older than the demo's ``FRESH_FIX_S`` from its first
fix to the end. A flight side that reads head 0x0E alone coasts through the crossing on its gyro
and fails the last clause (the control, ``tests/test_two_heads_loop.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from firmware_model.pipeline.sky_bodies import sky_bodies
from firmware_model.reference_frames import matrix_to_quat, quat_to_matrix, rotation_angle
from ground.hil.scenario_report import STATUS_COLOURS
from ground.hil.scenarios import HOLD_S, LIMITS_DEG, MARGIN_DEG, SETTLE_S, SLEW_RATE_DEG_S, Slew
from ground.hil.two_heads import CLOSEST_DEG, HEADS
from ground.sim.orbit import CircularOrbit, utc_iso

NAME = "two-heads"
ALTITUDE_KM = 35_786.0  #: ours: the geostationary altitude (the Earth small in the sky), on a polar orbit
SIDES = 12  #: where around the Sun the closest point may go: this many turns of 30 deg, tried in order
EXCLUSION = ("SUN_IN_FOV", "BLINDED")  #: what head 0x0E must report at the crossing


@dataclass(frozen=True)
class TwoHeadPlan:
    """The planned run: the body's slew (``q`` is the body's attitude, ``q_icrs_to_body``), the
    heads (address, mount_q), the limits (deg), the length (s) and the start (POSIX s)."""

    slew: Slew
    orbit: CircularOrbit
    heads: tuple[tuple[int, list[float]], ...]
    limits_deg: dict[str, float]
    duration_s: float
    start_posix: float
    name: str = NAME

    def params(self) -> dict[str, float]:
        """The heads' slot-2 parameters (their exclusion angles)."""
        return {f"{b}_exclusion_deg": v for b, v in self.limits_deg.items()}

    def position_at(self, t: float) -> np.ndarray:
        """GCRS position (km) ``t`` s after the start: the feed samples' ``r``."""
        return self.orbit.position_gcrs_km(self.start_posix + t)

    def report(self, log, rows: list[dict], plot_path) -> dict:
        """The summary's scenario figures (:func:`summarise`); the plot written to ``plot_path``."""
        plot(self, log, rows, plot_path)
        return summarise(self, log, rows)

    def failure(self, summary: dict, pass_mark_deg: float, fresh_fix_s: float) -> str | None:
        """Why the run fails its pass mark (:func:`scenario_failure`), or None."""
        return scenario_failure(summary, pass_mark_deg, fresh_fix_s)

    def boresights(self, t: float) -> dict[int, np.ndarray]:
        """Each head's planned boresight (ICRS unit vector) ``t`` s after the start."""
        a = self.slew.attitude(t)
        return {address: (quat_to_matrix(q) @ a)[2] for address, q in self.heads}


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def plan(start_posix: float, limits_deg: dict[str, float] | None = None) -> TwoHeadPlan:
    """The scenario for a run starting at POSIX ``start_posix``; ValueError (one line) when no
    side of the Sun keeps the Moon outside its limit from both heads."""
    limits = dict(LIMITS_DEG if limits_deg is None else limits_deg)
    bodies = sky_bodies(utc_iso(start_posix))
    sun, rate = bodies["sun"], math.radians(SLEW_RATE_DEG_S)
    closest = math.radians(CLOSEST_DEG)
    ends = sun.angular_radius + math.radians(limits["sun"] + MARGIN_DEG)  # from the Sun's centre
    half = math.acos(math.cos(ends) / math.cos(closest))  # the turn from an end to the closest point
    helper = np.array([0.0, 0.0, 1.0]) if abs(sun.direction[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    first = _unit(np.cross(sun.direction, helper))
    worst = math.inf
    for side in range(SIDES):
        away = Rotation.from_rotvec(side * math.radians(360.0 / SIDES) * sun.direction).apply(first)
        centre = math.cos(closest) * sun.direction + math.sin(closest) * away  # the closest point
        k = _unit(sun.direction - np.dot(sun.direction, centre) * centre)  # the turn's axis, the body's x
        z0 = Rotation.from_rotvec(-half * k).apply(centre)
        a0 = np.vstack([k, np.cross(z0, k), z0])
        slew = Slew(matrix_to_quat(a0), k, 2.0 * half, HOLD_S, rate)
        up = _unit(centre - k)  # the spacecraft's zenith: the Earth's centre at -up
        orbit = CircularOrbit(
            ALTITUDE_KM,
            90.0,
            math.degrees(math.atan2(up[1], up[0])) % 360.0,
            math.degrees(math.asin(float(np.clip(up[2], -1.0, 1.0)))),
            utc_iso(start_posix),
        )
        sc = TwoHeadPlan(slew, orbit, HEADS, limits, slew.t_end + SETTLE_S, start_posix)
        margin = min(_clearance_deg(sc, t) for t in np.arange(0.0, slew.t_end + 1.0, 1.0))
        if margin > 1.0:
            return sc
        worst = min(worst, margin)
    raise ValueError(
        f"{NAME}: the Moon or the Earth comes within {1.0 - worst:.1f} deg of its limit (+1 deg) from a "
        "head's path on every side of the Sun: choose another --epoch"
    )


def _clearance_deg(sc: TwoHeadPlan, t: float) -> float:
    """How far (deg) the Moon and the Earth stay outside their limits from both heads at ``t`` s."""
    bodies = sky_bodies(utc_iso(sc.start_posix + t), sc.position_at(t))
    return min(
        math.degrees(bodies[name].edge_angle(b)) - sc.limits_deg[name]
        for name in ("moon", "earth")
        for b in sc.boresights(t).values()
    )


def sun_edges(sc: TwoHeadPlan, log) -> dict[str, list[float]]:
    """Per logged step: ``t`` (s since the start) and each head's Sun edge angle (deg) from its
    truth boresight (the truth body attitude through its mounting)."""
    t0 = log.truth_t[0]
    out: dict[str, list[float]] = {key: [] for key in ["t", *(f"0x{a:02X}" for a, _ in sc.heads)]}
    mounts = {a: quat_to_matrix(q) for a, q in sc.heads}
    for t, q, r in zip(log.truth_t, log.truth_q, log.truth_r, strict=True):
        sun = sky_bodies(utc_iso(t), np.asarray(r))["sun"]
        out["t"].append(t - t0)
        for a, m in mounts.items():
            out[f"0x{a:02X}"].append(math.degrees(sun.edge_angle((m @ quat_to_matrix(q))[2])))
    return out


def summarise(sc: TwoHeadPlan, log, rows: list[dict]) -> dict:
    """The scenario's figures: each head's statuses, the answers used per head, when the flight
    side switched heads, the oldest its newest used fix got (s), each head's closest Sun edge."""
    heads = [f"0x{a:02X}" for a, _ in sc.heads]
    stamped = [r for r in rows if r.get("address") is not None]
    statuses = {
        h: {s: sum(r["status"] == s for r in stamped if f"0x{r['address']:02X}" == h) for s in _names(stamped)}
        for h in heads
    }
    used = [r for r in stamped if r["used"]]
    switches = [
        [round(b["t"], 3), f"0x{b['address']:02X}"]
        for a, b in zip(used, used[1:], strict=False)
        if a["address"] != b["address"]
    ]
    ages = _fix_ages(log)
    edges = sun_edges(sc, log)
    return {
        "scenario": sc.name,
        "heads": {f"0x{a:02X}": q for a, q in sc.heads},
        "exclusion_deg": sc.limits_deg,
        "head_statuses": {h: {s: n for s, n in v.items() if n} for h, v in statuses.items()},
        "used_per_head": {h: sum(f"0x{r['address']:02X}" == h for r in used) for h in heads},
        "used_not_ok": sum(r["status"] != "OK" for r in used),
        "head_switches": switches,
        "fix_age_s_max": None if ages is None else round(ages, 3),
        "sun_closest_edge_deg": {h: round(min(edges[h]), 3) for h in heads},
        "sun_excluded_updates": sum(r["status"] in EXCLUSION for r in stamped if r["address"] == sc.heads[0][0]),
    }


def _names(rows: list[dict]) -> list[str]:
    return sorted({r["status"] for r in rows})


def _fix_ages(log) -> float | None:
    """The oldest the flight side's newest used fix got (simulated s), from its first fix to the
    run's end; None when it never had one."""
    used = sorted(u.received for u in log.updates if u.used)
    if not used:
        return None
    return max(b - a for a, b in zip(used, [*used[1:], log.truth_t[-1]], strict=True))


def scenario_failure(summary: dict, pass_mark_deg: float, fresh_fix_s: float) -> str | None:
    """Why the two-head run fails its pass mark (module docstring), or None."""
    last = summary["pointing_error_deg_last"]
    if last is None or not last < pass_mark_deg:
        return f"final pointing error {last} deg is not under the {pass_mark_deg} deg pass mark"
    if not summary["sun_excluded_updates"]:
        return "head 0x0E never reported the Sun: the two-heads scenario did not exercise the selection"
    if summary["used_not_ok"]:
        return f"the flight side used {summary['used_not_ok']} answers that were not OK"
    age = summary["fix_age_s_max"]
    if age is None or age > fresh_fix_s:
        return f"the flight side went {age} s without a tracker fix (over {fresh_fix_s:g} s): the selection did not hold it"
    return None


def plot(sc: TwoHeadPlan, log, rows: list[dict], path) -> None:
    """Three panels over time: each head's status per answer (the used ones ringed), the pointing
    error (truth to target, deg, log), each head's Sun edge angle with the limit."""
    import logging

    from ground.optional import MissingExtra, pyplot

    try:
        plt = pyplot()
    except MissingExtra as exc:
        logging.getLogger(__name__).warning("no plot: %s", exc)
        return
    stamped = [r for r in rows if "t_mid" in r and r.get("address") is not None]
    names = [s for s in STATUS_COLOURS if any(r["status"] == s for r in stamped)]
    names += sorted({r["status"] for r in stamped} - set(names))
    heads = [a for a, _ in sc.heads]
    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, figsize=(8, 8), sharex=True, height_ratios=(2, 2, 2))
    for j, address in enumerate(heads):
        for k, name in enumerate(names):
            mine = [r for r in stamped if r["address"] == address and r["status"] == name]
            y = j * (len(names) + 1) + k
            ax1.plot([r["t_mid"] for r in mine], [y] * len(mine), "|", ms=8, color=STATUS_COLOURS.get(name, "tab:gray"))
            used = [r["t_mid"] for r in mine if r["used"]]
            ax1.plot(used, [y] * len(used), "o", ms=3, mfc="none", color="k")
    ticks = [j * (len(names) + 1) + k for j in range(len(heads)) for k in range(len(names))]
    labels = [f"0x{a:02X} {n}" for a in heads for n in names]
    ax1.set_yticks(ticks, labels, fontsize=7)
    ax1.set_title(f"HIL scenario {sc.name}: {log.dynamics} (o: the answer the flight side used)", fontsize=9)
    t0 = log.truth_t[0]
    target = [quat_to_matrix(q) for q in log.target_q]
    pointing = [math.degrees(rotation_angle(quat_to_matrix(q), a)) for q, a in zip(log.truth_q, target, strict=True)]
    ax2.semilogy([t - t0 for t in log.truth_t], pointing, "-", color="k", lw=1, label="truth to target")
    ax2.set_ylabel("pointing error (deg)")
    ax2.legend(fontsize=7, loc="upper right")
    edges = sun_edges(sc, log)
    for address, colour in zip(heads, ("tab:orange", "tab:purple"), strict=False):
        ax3.plot(edges["t"], edges[f"0x{address:02X}"], "-", color=colour, label=f"head 0x{address:02X} Sun edge")
    ax3.axhline(
        sc.limits_deg["sun"], color="tab:orange", dashes=(6, 2), lw=1.2, label=f"Sun limit {sc.limits_deg['sun']:g}"
    )
    ax3.set_ylabel("Sun edge from boresight (deg)")
    ax3.set_xlabel("exposure mid-time since start (s)")
    ax3.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
