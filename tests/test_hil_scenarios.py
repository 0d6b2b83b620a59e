"""The closed loop's scenarios (docs/hil.md "Scenarios"): the planned geometry, without a device
(the Sun's angle from the planned boresight crosses its limit after the eclipse exit; the Moon's
disc crosses the boresight path; nothing else comes inside its limit), the report on a synthetic
run, the moving target in both dynamics, the command line's refusal, and one short run through the
paced device (marked ``hil``: it needs the device's bright-body statuses and the feed's ``r``)."""

import functools
import math
import subprocess
import sys

import numpy as np
import pytest
from astropy.time import Time
from conftest import required

from firmware_model.pipeline.sky_bodies import sky_bodies
from firmware_model.reference_frames import quat_to_matrix, rotation_angle
from ground.hil import scenario_report, scenarios
from ground.sim.hil_loop import HilLog, Update
from ground.sim.orbit import in_earth_shadow

#: run starts the plans are checked at: a waning gibbous Moon, a northern summer, a full Moon
STARTS = [Time(t).unix for t in ("2026-11-28T08:00:00", "2026-06-21T03:30:00", "2026-12-24T01:00:00")]
NEW_MOON = Time("2026-12-09T12:00:00").unix


def _along(sc, step=0.5):
    """(t, edge angles deg per body, sunlit) along the planned boresight, every ``step`` s."""
    out = []
    for t in np.arange(0.0, sc.duration_s, step):
        r = sc.position_km(t)
        bodies = sky_bodies(Time(sc.start_posix + t, format="unix").isot, r)
        edges = {n: math.degrees(b.edge_angle(sc.slew.boresight(t))) for n, b in bodies.items()}
        out.append((t, edges, not in_earth_shadow(r, bodies["sun"].direction)))
    return out


@pytest.mark.parametrize("start", STARTS)
def test_eclipse_exit_sunrise_then_the_sun_crosses_its_limit(start):
    sc = scenarios.plan("eclipse-exit", start)
    path = _along(sc)
    limit = sc.limits_deg
    sun = np.array([e["sun"] for _, e, _ in path])
    assert sun[0] > limit["sun"] and sun[-1] > limit["sun"] and sun.min() < limit["sun"] - scenarios.DEPTH_DEG + 0.1
    sunlit = np.array([s for *_, s in path])
    t = np.array([t for t, *_ in path])
    assert not sunlit[0] and sunlit[-1] and np.all(np.diff(sunlit.astype(int)) >= 0)  # one exit, in the run
    assert t[np.argmax(sunlit)] < t[np.argmax(sun < limit["sun"])]  # sunrise before the Sun is inside
    for body in ("earth", "moon"):  # nothing else inside its limit
        assert min(e[body] for _, e, _ in path) > limit[body]


@pytest.mark.parametrize("start", STARTS)
def test_moon_slew_passes_the_boresight_across_the_moons_disc(start):
    sc = scenarios.plan("moon-slew", start)
    path = _along(sc, step=0.1)
    limit = sc.limits_deg
    moon = np.array([e["moon"] for _, e, _ in path])
    assert moon[0] > limit["moon"] and moon[-1] > limit["moon"]
    assert moon.min() < 0.0  # negative: the boresight is inside the disc
    for body in ("sun", "earth"):
        assert min(e[body] for _, e, _ in path) > limit[body]


def test_slew_turns_at_its_rate_about_its_axis_and_holds():
    sc = scenarios.plan("moon-slew", STARTS[0])
    s = sc.slew
    assert np.allclose(s.target(0.0), s.q_start) and np.allclose(s.target(s.t_start), s.q_start)
    a, b = s.attitude(s.t_start + 2.0), s.attitude(s.t_start + 3.0)
    assert math.isclose(rotation_angle(a, b), s.rate, rel_tol=1e-9)
    assert math.isclose(rotation_angle(quat_to_matrix(s.q_start), s.attitude(s.t_end + 5.0)), s.angle, rel_tol=1e-9)
    assert sc.params() == {f"{k}_exclusion_deg": v for k, v in scenarios.LIMITS_DEG.items()}


@pytest.mark.parametrize("name", ["eclipse-exit", "moon-slew"])
def test_a_new_moon_beside_the_sun_is_refused_with_its_reason(name):
    with pytest.raises(ValueError, match=r"comes .* deg from the planned boresight at that epoch"):
        scenarios.plan(name, NEW_MOON)


def test_unknown_scenario_is_refused():
    with pytest.raises(ValueError, match="unknown scenario"):
        scenarios.plan("sun-dive", STARTS[0])
    run = subprocess.run(
        [sys.executable, "-m", "ground.cli", "hil", "demo", "--scenario", "sun-dive"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1 and "sun-dive" in run.stderr


def _synthetic_run(sc, statuses):
    """A log as the loop writes it: the truth on the plan, one update per 0.5 s with ``statuses(t)``."""
    t0 = sc.start_posix
    log = HilLog("synthetic", [float(v) for v in sc.slew.target(sc.duration_s)])
    for t in np.arange(0.0, sc.duration_s + 1e-9, 0.1):
        q = [float(v) for v in sc.slew.target(t)]
        log.truth_t.append(t0 + t)
        log.truth_q.append(q)
        log.target_q.append(q)
        log.truth_r.append([float(v) for v in sc.position_km(t)])
    for t in np.arange(0.25, sc.duration_s - 0.5, 0.5):
        status = statuses(t)
        q = [float(v) for v in sc.slew.target(t)] if status == "OK" else None
        log.updates.append(Update(t0 + t - 0.1, t0 + t + 0.1, status, q, t0 + t, q_body=q, used=q is not None))
    return log


def test_report_of_a_run_that_coasts_through_the_moon(tmp_path):
    from ground.hil.run import summarise

    sc = scenarios.plan("moon-slew", STARTS[0])
    t_in, t_out = sc.slew.t_start + 4.0, sc.slew.t_end - 4.0
    log = _synthetic_run(sc, lambda t: "MOON_IN_FOV" if t_in <= t <= t_out else "OK")
    rows = log.rows()
    tr = scenario_report.track(log)
    summary = summarise(log, rows, sc.duration_s, 0x16) | scenario_report.summarise_scenario(sc, log, rows, tr)
    assert summary["statuses"]["MOON_IN_FOV"] == summary["exclusion_updates"] > 0
    ((lo, hi),) = summary["no_attitude_s"]
    assert t_in <= lo < t_in + 0.5 and t_out < hi <= t_out + 0.5
    assert 0.0 < summary["recovery_s"] <= 0.5 and summary["ok_inside_limit"] == []
    assert summary["moon_closest_edge_deg"] < 0.0 and summary["pointing_error_deg_max_no_attitude"] < 1e-3
    assert scenario_report.scenario_failure(summary, 0.05) is None
    scenario_report.plot_scenario(sc, log, rows, tr, tmp_path / "hil.png")
    assert (tmp_path / "hil.png").stat().st_size > 10_000
    # an attitude reported with the Moon inside its limit fails the pass mark, and so does a run with no exclusion
    bad = _synthetic_run(sc, lambda t: "OK")
    rows = bad.rows()
    tr = scenario_report.track(bad)
    summary = summarise(bad, rows, sc.duration_s, 0x16) | scenario_report.summarise_scenario(sc, bad, rows, tr)
    assert summary["ok_inside_limit"] and "inside its limit" in scenario_report.scenario_failure(summary, 0.05)
    summary["ok_inside_limit"] = []
    assert "no exclusion status" in scenario_report.scenario_failure(summary, 0.05)


def test_both_dynamics_follow_a_moving_target_alike():
    required("Basilisk")
    from ground.sim.hil_dynamics import BasiliskDynamics, StandInDynamics, gains

    sc = scenarios.plan("moon-slew", STARTS[0])
    inertia = np.diag([10.0, 9.0, 8.0])
    k, p = gains(inertia, 0.3, 0.9)
    q0 = sc.slew.target(0.0)
    bsk, ours = (
        BasiliskDynamics(inertia, q0, np.zeros(3), q0, k, p, 0.02),
        StandInDynamics(inertia, q0, np.zeros(3), q0, k, p),
    )
    worst = 0.0
    for n in range(1, 751):  # 15 s: the hold and 11 s of the slew
        for dyn in (bsk, ours):
            dyn.set_target(sc.slew.target(n * 0.02))
        (qb, wb), (qo, wo) = bsk.step(0.02), ours.step(0.02)
        bsk.set_measurement(qb, wb)
        ours.set_measurement(qo, wo)
        worst = max(worst, rotation_angle(quat_to_matrix(qb), quat_to_matrix(qo)))
    turned = rotation_angle(quat_to_matrix(q0), quat_to_matrix(qo))
    assert 0.3 * sc.slew.turned(15.0) < turned < sc.slew.turned(15.0)  # it follows, lagging (no rate fed forward)
    assert math.degrees(worst) < 0.02  # of a 10 deg turn: the same law, Basilisk's step order


def test_short_moon_slew_through_the_paced_device(tmp_path, monkeypatch):
    """A small Moon limit (5 deg) keeps the slew short; the run ends 8 s after the slew."""
    from ground.hil.run import run_hil
    from ground.sim import hil_loop
    from protocol.result import Status

    if not hasattr(Status, "MOON_IN_FOV"):
        pytest.fail("the device has no MOON_IN_FOV status yet (issue 33 part 1)", pytrace=False)
    limits = {"sun": 30.0, "moon": 5.0, "earth": 20.0}
    loop = functools.partial(hil_loop.run_closed_loop, min_ok_updates=5, overrun_s=600, combination_timeout=60)
    monkeypatch.setattr(hil_loop, "run_closed_loop", loop)
    probe = scenarios.plan("moon-slew", STARTS[0], limits)
    s = run_hil(tmp_path, probe.slew.t_end + 8.0, "standin", progress=False, scenario="moon-slew", limits_deg=limits)
    assert s["statuses"].get("MOON_IN_FOV", 0) >= 1 and s["ok_inside_limit"] == []
    assert s["moon_closest_edge_deg"] < 0.0 and s["recovery_s"] is not None and s["recovery_s"] > 0.0
    assert s["no_attitude_s"] and (tmp_path / "hil.png").exists()
