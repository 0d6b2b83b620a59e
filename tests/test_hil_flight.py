"""The HIL flight side (ground.sim.gyro, ground.sim.flight_estimator; docs/hil.md "The flight side"): the
gyro's noise terms, the estimator lost until its first fix, converging on answers with their
covariance, and drifting on the gyro alone; bad parameters refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ground.sim.flight_estimator import Mekf
from ground.sim.gyro import DEFAULT, DEG_PER_H, Gyro, GyroSpec


def _angle_deg(a, b) -> float:
    return math.degrees(np.linalg.norm(Rotation.from_matrix(a @ b.T).as_rotvec()))


def test_gyro_bias_and_noise_are_seeded_and_of_the_stated_size():
    g1, g2 = Gyro(DEFAULT, 3), Gyro(DEFAULT, 3)
    assert np.array_equal(g1.measure(np.zeros(3), 0.02), g2.measure(np.zeros(3), 0.02))
    g = Gyro(GyroSpec(bias_deg_h=0.0, arw_deg_rt_h=0.07, rrw_deg_h_rt_h=0.0, sf_ppm=0.0), 1)
    dt, n = 0.02, 20000
    angle = np.sum([g.measure(np.zeros(3), dt) * dt for _ in range(n)], axis=0)  # n dt = 400 s
    # the angle random walk: sigma = ARW sqrt(t); three axes, a loose bound on one draw
    sigma = DEFAULT.arw * math.sqrt(n * dt)
    assert np.all(np.abs(angle) < 5 * sigma) and np.any(np.abs(angle) > 0.1 * sigma)
    biased = Gyro(GyroSpec(bias_deg_h=1.0, arw_deg_rt_h=0.0, rrw_deg_h_rt_h=0.0, sf_ppm=0.0), 2)
    assert 0 < np.linalg.norm(biased.measure(np.zeros(3), dt)) < 10 * DEG_PER_H


@pytest.mark.parametrize(
    "spec",
    [
        GyroSpec(bias_deg_h=-1.0),
        GyroSpec(arw_deg_rt_h=math.nan),
        GyroSpec(sf_ppm=1e9),
        GyroSpec(rrw_deg_h_rt_h=math.inf),
    ],
)
def test_a_gyro_out_of_range_is_refused(spec):
    assert spec.problems()
    with pytest.raises(ValueError):
        Gyro(spec)


def _run(fix_until: float, seconds: float = 120.0, seed: int = 4):
    """A body turning at 0.1 deg/s; answers every 0.5 s (20 arcsec, valid 0.05 s after the GO, used
    0.5 s after it) until ``fix_until``; returns (estimator, truth matrix, errors in arcsec per s)."""
    dt, w = 0.02, np.radians([0.1, -0.05, 0.02])
    gyro = Gyro(DEFAULT, seed)
    rng = np.random.default_rng(seed)
    a = Rotation.from_rotvec([0.3, -1.0, 2.0]).as_matrix()
    est = Mekf(0.0, DEFAULT)
    hist: dict[int, np.ndarray] = {}
    sigma = math.radians(20 / 3600)
    cov = [sigma**2, 0, 0, sigma**2, 0, sigma**2]
    err = {}
    for k in range(int(seconds / dt)):
        t = k * dt
        hist[k] = a
        if k % 25 == 0 and k >= 25 and (k - 25) * dt < fix_until:  # the answer of the GO at (k - 25) dt
            mid = k - 25 + 2  # 0.04 s after the GO: on a step
            meas = Rotation.from_rotvec(rng.normal(0, sigma, 3)).as_matrix() @ hist[mid]
            assert est.lost == (est.fixes == 0)
            est.update(meas, mid * dt, cov)
        a = Rotation.from_rotvec(-w * dt).as_matrix() @ a
        est.propagate(gyro.measure(w, dt), t + dt)
        if k % 50 == 49 and not est.lost:
            err[round(t + dt)] = _angle_deg(est.a, a) * 3600
    return est, a, err


def test_lost_until_the_first_fix_then_tracks_within_the_answers_noise():
    est = Mekf(0.0, DEFAULT)
    assert est.lost and math.isinf(est.sigma_deg())
    est, a, err = _run(fix_until=1e9)
    assert not est.lost and est.fixes > 200
    assert max(v for t, v in err.items() if t >= 10) < 30.0  # arcsec; the answers are 20 arcsec 1-sigma per axis


def test_without_answers_the_error_grows_on_the_gyro():
    _, _, tracked = _run(fix_until=1e9, seconds=200)
    _, _, coasting = _run(fix_until=20.0, seconds=200)
    assert coasting[200] > 3 * tracked[200] and coasting[200] > coasting[30]


def test_the_default_epoch_is_fixed_and_plans_both_scenarios():
    from ground.hil import scenarios
    from ground.hil.run import DEFAULT_EPOCH_UTC, parse_epoch

    start = parse_epoch(DEFAULT_EPOCH_UTC)
    assert start == parse_epoch("2026-12-01T00:00:00Z") == 1796083200.0
    for name in ("eclipse-exit", "moon-slew"):
        assert scenarios.plan(name, start).duration_s > 60


@pytest.mark.parametrize("text", ["2026-13-01", "yesterday", "2026-12-01T00:00:00+02:00", "1900-01-01", "nan"])
def test_an_epoch_that_does_not_parse_is_refused(text):
    from ground.arg_types import InputError
    from ground.hil.run import parse_epoch

    with pytest.raises(InputError, match="--epoch"):
        parse_epoch(text)


def test_the_feed_clock_is_the_newest_kept_sample():
    from ground.sim.feed_clock import FeedClock

    c = FeedClock()
    assert c.posix() == 0.0 and c.elapsed() == 0.0
    c.offering(100.0)
    assert c.posix() == 100.0 and c.elapsed() == 0.0  # a first sample is checked against itself
    c.accepted(100.0)
    c.accepted(100.5)
    c.accepted(100.2)  # never back
    assert c.posix() == 100.5 and c.elapsed() == pytest.approx(0.5)


@pytest.mark.hil
def test_lockstep_gives_the_same_run_at_any_speed(tmp_path):
    """The closed loop through the device in simulated time: unpaced and at 2x real time, the same
    statuses, attitudes and time tags (docs/hil.md "Lockstep")."""
    import json

    from ground.hil.run import run_hil

    logs = []
    for speed in (0.0, 2.0):
        out = tmp_path / f"speed-{speed:g}"
        summary = run_hil(out, 3.0, dynamics_kind="standin", progress=False, speed=speed)
        assert summary["ok_updates"] >= 4 and summary["acquisition_s"] == 0.5
        logs.append([json.loads(x) for x in (out / "hil_log.jsonl").read_text().splitlines()])
    keys = ("status", "sent", "received", "t_mid", "epoch", "q")
    assert len(logs[0]) == len(logs[1]) >= 5
    assert [[r[k] for k in keys] for r in logs[0]] == [[r[k] for k in keys] for r in logs[1]]
