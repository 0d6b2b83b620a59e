"""What a scenario run of the closed loop did (docs/hil.md "Scenarios"): the truth geometry of the
bright bodies along the run, the summary's scenario figures, the pass mark and the plot.

The geometry is the truth's: ``sky_bodies`` at each step's time from the logged GCRS position,
against the truth boresight; a body is inside its limit when the edge of its disc is nearer the
boresight than the limit (``SkyBody.edge_angle``). Times are s since the run's start.
"""

from __future__ import annotations

import math

import numpy as np

from firmware_model.pipeline.sky_bodies import sky_bodies
from firmware_model.reference_frames import quat_to_matrix, rotation_angle
from ground.sim.orbit import in_earth_shadow, utc_iso

#: statuses that say a body is inside its exclusion angle or the image is blinded: no attitude
EXCLUSION = ("SUN_IN_FOV", "MOON_IN_FOV", "EARTH_IN_FOV", "BLINDED")
#: the plot's colour of each status (others grey) and of each body's angle
STATUS_COLOURS = {
    "OK": "tab:green",
    "LOW_CONFIDENCE": "tab:olive",
    "SUN_IN_FOV": "tab:orange",
    "MOON_IN_FOV": "tab:blue",
    "EARTH_IN_FOV": "tab:brown",
    "BLINDED": "tab:red",
}
BODY_COLOURS = {"sun": "tab:orange", "moon": "tab:blue", "earth": "tab:brown"}


def geometry_at(log, t_posix: float) -> tuple[dict[str, float], bool]:
    """(edge angle in deg of each body from the truth boresight, sunlit) at POSIX ``t_posix``."""
    r = np.array([np.interp(t_posix, log.truth_t, [p[k] for p in log.truth_r]) for k in range(3)])
    bodies = sky_bodies(utc_iso(t_posix), r)
    boresight = quat_to_matrix(log.truth_at(t_posix))[2]
    edges = {name: math.degrees(b.edge_angle(boresight)) for name, b in bodies.items()}
    return edges, not in_earth_shadow(r, bodies["sun"].direction)


def track(log) -> dict:
    """Per logged step: ``t``, each body's edge angle (deg), ``sunlit``, ``pointing_deg`` (truth to target)."""
    t0 = log.truth_t[0]
    out: dict = {"t": [], "sunlit": [], "pointing_deg": [], **{b: [] for b in BODY_COLOURS}}
    for t, q, q_target in zip(log.truth_t, log.truth_q, log.target_q, strict=False):
        edges, sunlit = geometry_at(log, t)
        out["t"].append(t - t0)
        out["sunlit"].append(sunlit)
        out["pointing_deg"].append(math.degrees(rotation_angle(quat_to_matrix(q), quat_to_matrix(q_target))))
        for b in BODY_COLOURS:
            out[b].append(edges[b])
    return {k: np.array(v) for k, v in out.items()}


def _intervals(t: np.ndarray, flag: np.ndarray) -> list[list[float]]:
    """[start, end] (s) of each run of True in ``flag`` along ``t``."""
    out, begin = [], None
    for ti, f in zip(t, flag, strict=True):
        if f and begin is None:
            begin = ti
        elif not f and begin is not None:
            out.append([round(float(begin), 3), round(float(ti), 3)])
            begin = None
    if begin is not None:
        out.append([round(float(begin), 3), round(float(t[-1]), 3)])
    return out


def summarise_scenario(scenario, log, rows: list[dict], tr: dict) -> dict:
    """The summary's scenario figures (module docstring; docs/hil.md "Scenarios")."""
    from ground.sim.orbit import CircularOrbit

    o = scenario.orbit
    orbit = CircularOrbit(o.altitude_km, o.inclination_deg, o.raan_deg, o.arg_latitude_deg, utc_iso(log.truth_t[0]))
    limits = scenario.limits_deg
    stamped = [r for r in rows if "t_mid" in r]
    t_up = np.array([r["t_mid"] for r in stamped])
    ok_up = np.array([r["status"] == "OK" for r in stamped])
    ok_inside = []
    for r in stamped:
        if r["status"] == "OK":
            edges, _ = geometry_at(log, log.truth_t[0] + r["t_mid"])
            if any(edges[b] < limits[b] for b in limits):
                ok_inside.append(round(r["t_mid"], 3))
    blind = _intervals(np.append(t_up, tr["t"][-1]), np.append(~ok_up, False)) if len(t_up) else []
    in_blind = np.zeros(len(tr["t"]), dtype=bool)
    for a, b in blind:
        in_blind |= (tr["t"] >= a) & (tr["t"] <= b)
    excl = [r["t_mid"] for r in stamped if r["status"] in EXCLUSION]
    after = [r["t_mid"] for r in stamped if excl and r["status"] == "OK" and r["t_mid"] > excl[-1]]
    sunrise = np.flatnonzero(~tr["sunlit"][:-1] & tr["sunlit"][1:])
    body = tr[scenario.body]
    return {
        "scenario": scenario.name,
        "orbit": f"{orbit.altitude_km:g},{orbit.inclination_deg:g},{orbit.raan_deg:.3f},"
        f"{orbit.arg_latitude_deg:.3f},{orbit.epoch_utc}",
        "exclusion_deg": limits,
        "moon_illuminated": _moon_illuminated(log.truth_t[0]),
        "sunrise_s": float(tr["t"][sunrise[0] + 1]) if len(sunrise) else None,
        f"{scenario.body}_closest_edge_deg": float(body.min()),
        f"{scenario.body}_inside_limit_s": _intervals(tr["t"], body < limits[scenario.body]),
        "exclusion_updates": len(excl),
        "no_attitude_s": blind,
        "pointing_error_deg_max_no_attitude": float(tr["pointing_deg"][in_blind].max()) if in_blind.any() else None,
        "recovery_s": round(after[0] - excl[-1], 3) if after else None,
        "ok_inside_limit": ok_inside,
    }


def _moon_illuminated(t_posix: float) -> float:
    """Illuminated fraction of the Moon's disc seen from the geocentre at ``t_posix``: the phase
    angle from the elongation and the distances, ``k = (1 + cos i) / 2`` (Meeus, Astronomical
    Algorithms, 2nd ed., eqs. 48.1 and 48.3)."""
    b = sky_bodies(utc_iso(t_posix))
    elongation = math.acos(float(np.clip(np.dot(b["sun"].direction, b["moon"].direction), -1.0, 1.0)))
    phase = math.atan2(
        b["sun"].distance_km * math.sin(elongation), b["moon"].distance_km - b["sun"].distance_km * math.cos(elongation)
    )
    return round((1.0 + math.cos(phase)) / 2.0, 3)


def scenario_failure(summary: dict, pass_mark_deg: float) -> str | None:
    """Why a scenario run fails its pass mark (docs/hil.md "Scenarios"), or None."""
    last = summary["pointing_error_deg_last"]
    if last is None or not last < pass_mark_deg:
        return f"final pointing error {last} deg is not under the {pass_mark_deg} deg pass mark"
    if summary["ok_inside_limit"]:
        t = summary["ok_inside_limit"]
        return f"{len(t)} high-confidence attitudes reported with a body inside its limit (first at {t[0]} s)"
    if not summary["exclusion_updates"]:
        return f"no exclusion status reported: the {summary['scenario']} scenario did not exercise the check"
    return None


def plot_scenario(scenario, log, rows: list[dict], tr: dict, path) -> None:
    """Three panels over time: the tracker's status per update, the pointing error (truth and
    tracker to the target, deg, log), each body's edge angle from the boresight with its limit."""
    import logging

    from ground.optional import MissingExtra, pyplot

    try:
        plt = pyplot()
    except MissingExtra as exc:
        logging.getLogger(__name__).warning("no plot: %s", exc)
        return
    stamped = [r for r in rows if "t_mid" in r]
    names = [s for s in STATUS_COLOURS if any(r["status"] == s for r in stamped)]
    names += sorted({r["status"] for r in stamped} - set(names))
    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, figsize=(8, 8), sharex=True, height_ratios=(1, 2, 2))
    for k, name in enumerate(names):
        t = [r["t_mid"] for r in stamped if r["status"] == name]
        ax1.plot(t, [k] * len(t), "|", ms=10, color=STATUS_COLOURS.get(name, "tab:gray"))
    ax1.set_yticks(range(len(names)), names, fontsize=7)
    ax1.set_ylim(-0.7, len(names) - 0.3)
    ax1.set_title(f"HIL scenario {scenario.name}: {log.dynamics}", fontsize=9)
    ok = [r for r in stamped if "q_measured" in r]
    ax2.semilogy(tr["t"], tr["pointing_deg"], "-", color="k", lw=1, label="truth to target")
    measured = [
        math.degrees(
            rotation_angle(quat_to_matrix(r["q_measured"]), quat_to_matrix(log.target_at(log.truth_t[0] + r["t_mid"])))
        )
        for r in ok
    ]
    ax2.semilogy([r["t_mid"] for r in ok], measured, ".", ms=3, color="tab:green", label="tracker to target")
    ax2.set_ylabel("pointing error (deg)")
    for (b, colour), dashes in zip(BODY_COLOURS.items(), ((6, 2), (1, 2), (4, 2, 1, 2)), strict=True):
        ax3.plot(tr["t"], tr[b], "-", color=colour, label=f"{b} edge")
        limit = scenario.limits_deg[b]
        ax3.axhline(limit, lw=1.2, color=colour, dashes=dashes, label=f"{b} limit {limit:g}")
    ax3.set_ylim(-5.0, 95.0)  # the crossing's detail; a body further than 95 deg is off the panel
    ax3.set_ylabel("edge from boresight (deg, to 95)")
    ax3.set_xlabel("exposure mid-time since start (s)")
    for k, (lo, hi) in enumerate(_intervals(tr["t"], ~tr["sunlit"])):
        ax3.axvspan(lo, hi, color="0.85", zorder=0, label="eclipse" if k == 0 else None)
    for ax in (ax1, ax2):
        for lo, hi in _intervals(
            np.array([r["t_mid"] for r in stamped] + [tr["t"][-1]]),
            np.array([r["status"] != "OK" for r in stamped] + [False]),
        ):
            ax.axvspan(lo, hi, color="0.9", zorder=0)  # no attitude
    for ax in (ax2, ax3):
        ax.legend(fontsize=7, loc="upper right", ncol=2 if ax is ax3 else 1)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
