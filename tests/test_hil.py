"""The HIL closed loop (docs/hil.md): attitude conversions to Basilisk's, the two dynamics
back-ends agreeing, and a short loop through a device paced at 115200 baud. Basilisk parts are
skipped when ``bsk`` (the ``[hil]`` extra) is not installed; no timings are asserted: the loop
runs on until it has the OK answers the test checks (however few solves a loaded machine
manages in the 4 s), within a hang guard."""

import functools

import numpy as np
import pytest
from conftest import required
from scipy.spatial.transform import Rotation

from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat, quat_to_matrix, rotation_angle
from ground.sim.hil_dynamics import StandInDynamics, gains, mrp_to_quat, quat_to_mrp

I = np.diag([10.0, 9.0, 8.0])
Q_TARGET = matrix_to_quat(attitude_from_radec_roll(1.0, 0.3, 0.2))
Q0 = matrix_to_quat(Rotation.from_rotvec(np.radians([3.0, -2.0, 1.0])).as_matrix() @ quat_to_matrix(Q_TARGET))
W0 = np.radians([0.05, -0.05, 0.02])


def _settle(dyn, steps=1500, dt=0.02):
    for _ in range(steps):
        q, w = dyn.step(dt)
        dyn.set_measurement(q, w)  # a perfect sensor
    return np.degrees(rotation_angle(quat_to_matrix(q), quat_to_matrix(Q_TARGET)))


def test_mrp_round_trip_and_short_rotation():
    for q in (Q0, Q_TARGET, -Q0):
        back = mrp_to_quat(quat_to_mrp(q))
        assert np.linalg.norm(quat_to_mrp(q)) <= 1.0 and abs(abs(back @ q) - 1.0) < 1e-12


def test_stand_in_converges_on_a_perfect_measurement():
    k, p = gains(I, 0.3, 0.9)
    assert _settle(StandInDynamics(I, Q0, W0, Q_TARGET, k, p)) < 0.01


def test_conventions_and_dynamics_match_basilisk():
    required("Basilisk")
    from Basilisk.utilities import RigidBodyKinematics as rbk

    from ground.sim.hil_dynamics import BasiliskDynamics

    a = quat_to_matrix(Q0)
    assert np.allclose(rbk.C2MRP(a), quat_to_mrp(Q0))  # our q of C_BN -> Basilisk's sigma_BN
    k, p = gains(I, 0.3, 0.9)
    bsk, ours = BasiliskDynamics(I, Q0, W0, Q_TARGET, k, p, 0.02), StandInDynamics(I, Q0, W0, Q_TARGET, k, p)
    for _ in range(200):
        qb, wb = bsk.step(0.02)
        qo, wo = ours.step(0.02)
        bsk.set_measurement(qb, wb)
        ours.set_measurement(qo, wo)
    assert np.degrees(rotation_angle(quat_to_matrix(qb), quat_to_matrix(qo))) < 1e-3
    assert np.allclose(wb, wo, atol=2e-5)  # rad/s, of ~6e-3: the same law, Basilisk's step order


MIN_OK = 5  #: OK answers the loop runs on for


@pytest.mark.parametrize("kind", ["basilisk", "standin"])
def test_short_closed_loop_through_the_paced_device(tmp_path, kind, monkeypatch):
    if kind == "basilisk":
        required("Basilisk")
    from ground.hil.run import run_hil
    from ground.sim import hil_loop

    # the demo's loop, told to run on until MIN_OK answers (hang guards: 10 min, 60 s a COMBINATION)
    loop = functools.partial(hil_loop.run_closed_loop, min_ok_updates=MIN_OK, overrun_s=600, combination_timeout=60)
    monkeypatch.setattr(hil_loop, "run_closed_loop", loop)
    summary = run_hil(tmp_path, duration_s=4.0, dynamics_kind=kind, progress=False)
    assert ("stand-in" in summary["dynamics"]) == (kind == "standin") and summary["ok_updates"] >= MIN_OK
    assert summary["measured_error_arcsec_p50"] < 30.0
    assert summary["pointing_error_deg_last"] < summary["pointing_error_deg_first"]  # converging
    assert (tmp_path / "hil_log.jsonl").stat().st_size > 0 and (tmp_path / "summary.json").exists()
