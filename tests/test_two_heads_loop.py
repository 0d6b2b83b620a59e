"""The closed loop with two heads (ground/hil/two_heads_scenario.py, docs/hil.md "Two heads in the
loop"): the plan's geometry, the flight side's selection and the answers it turns into the
body's attitude and axes, the pass mark on synthetic logs, and the whole run through the device
with its control (the flight side reading the blinded head alone fails)."""

from __future__ import annotations

import math

import guards
import numpy as np
import pytest

from firmware_model.pipeline.sky_bodies import sky_bodies
from firmware_model.reference_frames import quat_to_matrix
from ground.hil import scenarios, two_heads_scenario
from ground.hil.run import DEFAULT_EPOCH_UTC, parse_epoch
from ground.sim.flight_estimator import covariance_from_upper, upper_in_body_axes
from ground.sim.hil_loop import HilLog, Update, prefer_last
from ground.sim.orbit import utc_iso

START = parse_epoch(DEFAULT_EPOCH_UTC)


def test_the_plan_sweeps_head_a_inside_the_sun_limit_while_head_b_and_the_other_bodies_stay_clear():
    sc = scenarios.plan("two-heads", START)
    sun_a, sun_b, others = [], [], []
    for t in np.arange(0.0, sc.duration_s, 1.0):
        bodies = sky_bodies(utc_iso(START + t), sc.position_at(t))
        a, b = sc.boresights(t).values()
        sun_a.append(math.degrees(bodies["sun"].edge_angle(a)))
        sun_b.append(math.degrees(bodies["sun"].edge_angle(b)))
        others += [math.degrees(bodies[n].edge_angle(v)) - sc.limits_deg[n] for n in ("moon", "earth") for v in (a, b)]
    assert (
        min(sun_a) < sc.limits_deg["sun"] - 15.0 < sc.limits_deg["sun"] < sun_a[0] and sun_a[-1] > sc.limits_deg["sun"]
    )
    assert min(sun_b) > sc.limits_deg["sun"] + 30.0
    assert min(others) > 1.0
    # head B's boresight does not move: the body turns about the axis it looks along
    assert np.allclose(sc.boresights(0.0)[0x0F], sc.boresights(sc.duration_s)[0x0F], atol=1e-9)


def test_a_plan_the_moon_spoils_on_every_side_is_refused_in_one_line():
    with pytest.raises(ValueError, match="two-heads: the Moon or the Earth .* choose another --epoch"):
        two_heads_scenario.plan(START, {"sun": 30.0, "moon": 170.0, "earth": 25.0})


def _answer(address, status, q_body=None, t=0.0):
    return Update(t, t, status, None, t, address=address, q_body=q_body)


def test_the_flight_side_keeps_its_head_while_it_is_ok_and_takes_another_when_it_is_not():
    q = [1.0, 0.0, 0.0, 0.0]
    both = [_answer(0x0E, "OK", q), _answer(0x0F, "OK", q)]
    assert prefer_last(both, None).address == 0x0E
    assert prefer_last(both, 0x0F).address == 0x0F  # no needless switch
    assert prefer_last([_answer(0x0E, "SUN_IN_FOV"), _answer(0x0F, "OK", q)], 0x0E).address == 0x0F
    assert prefer_last([_answer(0x0E, "BLINDED"), _answer(0x0F, "NO_MATCH")], 0x0E) is None


def test_a_mounted_head_s_covariance_is_turned_into_the_body_s_axes():
    mount = quat_to_matrix(dict(two_heads_scenario.HEADS)[0x0F])  # boresight the body's -x
    sensor = [1e-8, 0.0, 0.0, 1e-8, 0.0, 1e-6]  # loose about the boresight (sensor z)
    body = covariance_from_upper(upper_in_body_axes(sensor, mount))
    assert body[0, 0] == pytest.approx(1e-6) and body[2, 2] == pytest.approx(1e-8)  # loose about the body's x


def _synthetic(sc, read_b: bool) -> tuple[HilLog, list[dict]]:
    """A log as the loop writes it on the plan: truth on the target, head 0x0E excluded while the
    Sun is inside its limit; the flight side uses 0x0F then if it reads it."""
    log = HilLog("synthetic", [float(v) for v in sc.slew.target(sc.duration_s)])
    for t in np.arange(0.0, sc.duration_s + 1e-9, 0.1):
        q = [float(v) for v in sc.slew.target(t)]
        log.truth_t.append(START + t)
        log.truth_q.append(q)
        log.target_q.append(q)
        log.truth_r.append([float(v) for v in sc.position_at(t)])
    last = None
    for t in np.arange(0.25, sc.duration_s - 0.5, 0.5):
        q = [float(v) for v in sc.slew.target(t)]
        sun = sky_bodies(utc_iso(START + t), sc.position_at(t))["sun"]
        inside = math.degrees(sun.edge_angle(sc.boresights(t)[0x0E])) < sc.limits_deg["sun"]
        answers = [Update(START + t, START + t + 0.5, "SUN_IN_FOV" if inside else "OK", None, START + t, address=0x0E)]
        answers[0].q_body = None if inside else q
        answers.append(Update(START + t, START + t + 0.5, "OK", None, START + t, address=0x0F, q_body=q))
        chosen = prefer_last(answers if read_b else answers[:1], last)
        if chosen is not None:
            chosen.used, last = True, chosen.address
        log.updates.extend(answers)
    return log, log.rows()


def test_the_pass_mark_holds_with_selection_and_fails_when_the_flight_side_reads_the_blinded_head_alone():
    from ground.hil.run import summarise

    sc = scenarios.plan("two-heads", START)
    for read_b, passes in ((True, True), (False, False)):
        log, rows = _synthetic(sc, read_b)
        summary = summarise(log, rows, sc.duration_s, 0x16) | two_heads_scenario.summarise(sc, log, rows)
        why = sc.failure(summary, 0.05, 5.0)
        assert (why is None) == passes, why
        if not passes:
            assert "without a tracker fix" in why
    assert summary["sun_excluded_updates"] > 0 and summary["used_not_ok"] == 0


@pytest.mark.timeout(20 * guards.HANG_S)  # a hang guard: 466 GOs of two heads, rendered and solved
@pytest.mark.parametrize("read", ["both", "blinded-head-alone"])
def test_the_two_head_loop_through_the_device(tmp_path, read):
    """The whole scenario through ``st16-device --heads --attitude-feed``; the control reads head
    0x0E alone and must fail the pass mark."""
    from ground.cli.hil import FRESH_FIX_S, PASS_MARK_DEG
    from ground.hil.run import run_hil

    summary = run_hil(
        tmp_path,
        None,
        "standin",
        scenario="two-heads",
        progress=False,
        read_heads=None if read == "both" else (0x0E,),
    )
    sc = scenarios.plan("two-heads", START)
    why = sc.failure(summary, PASS_MARK_DEG, FRESH_FIX_S)
    assert summary["sun_excluded_updates"] > 0
    if read == "both":
        assert why is None, why
        assert summary["used_per_head"]["0x0F"] > 0 and summary["head_switches"]
        assert (tmp_path / "hil.png").stat().st_size > 10_000
    else:
        assert why is not None and "without a tracker fix" in why, why
