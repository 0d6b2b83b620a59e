"""Tracking mode (firmware_model/ident/tracking.py) and smeared stars through extraction."""

import numpy as np
import pytest
from ident_sky import random_catalog
from scipy.spatial.transform import Rotation

from firmware_model.camera import CameraModel
from firmware_model.ident.attitude import quat_matrix
from firmware_model.ident.tracking import TrackParams, TrackState, TrackStatus, predict, track
from firmware_model.pipeline.extract import extract_stars
from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat, rotation_angle
from ground.sim.sensor_sim import DetectorModel, Stars, render_frame
from ground.sim.smear import SmearPSF

CAM = CameraModel.reference_design()
A0 = attitude_from_radec_roll(1.0, 0.4, 0.3)
OMEGA = np.radians([0.3, -0.4, 0.1])  # rad/s, sensor axes


@pytest.fixture(scope="module")
def catalog():
    return random_catalog(n=4000, seed=1)


def attitude(t):
    """True attitude of the slew: A(t) = R(-omega t) A0."""
    return Rotation.from_rotvec(-OMEGA * t).as_matrix() @ A0


def detections(catalog, a, rng, sigma_px=0.2, n_false=0):
    """Pixels of the catalog stars on the array at attitude ``a`` plus ``n_false`` false stars; truth indices."""
    s = catalog.vec @ a.T
    x, y = CAM.vector_to_pixel(s)
    on = np.flatnonzero(np.isfinite(x) & CAM.in_frame(x, y))
    px = np.column_stack([x[on], y[on]]) + rng.normal(scale=sigma_px, size=(len(on), 2))
    false = rng.uniform([0, 0], [CAM.width - 1, CAM.height - 1], size=(n_false, 2))
    return np.vstack([px, false]), on


def fix(t, sigma_rad=2e-5, omega=(0.0, 0.0, 0.0)):
    return TrackState.from_fix(matrix_to_quat(attitude(t)), np.eye(3) * sigma_rad**2, t, omega=omega)


def test_predict_follows_a_known_slew():
    p = TrackParams()
    state = TrackState.from_fix(matrix_to_quat(A0), np.eye(3) * 1e-10, 0.0, p, omega=OMEGA)
    pred = predict(state, 0.7, p)
    assert np.allclose(quat_matrix(pred.q), attitude(0.7), rtol=0, atol=1e-12)
    assert pred.t == 0.7 and np.array_equal(pred.omega, OMEGA)
    # attitude variance grows by dt^2 of the rate variance plus the process noise
    expected = 1e-10 + 0.7**2 * p.initial_rate_sigma**2 + p.rate_noise * 0.7**3 / 3 + p.attitude_noise * 0.7
    assert np.allclose(np.diag(pred.attitude_covariance), expected, rtol=1e-9)
    assert np.allclose(np.diag(pred.rate_covariance), p.initial_rate_sigma**2 + p.rate_noise * 0.7)


def test_matching_in_windows_with_false_stars(catalog):
    rng = np.random.default_rng(2)
    px, truth = detections(catalog, attitude(0.2), rng, n_false=200)
    res = track(px, fix(0.0, omega=OMEGA), 0.2, catalog, CAM)
    assert res.ok, res.reason
    n_true = len(truth)
    assert np.all(res.matched_det < n_true)  # no false star taken
    assert np.array_equal(res.matched_cat, truth[res.matched_det])
    assert len(res.matched_det) >= n_true - 1
    assert rotation_angle(quat_matrix(res.state.q), attitude(0.2)) < np.radians(5 / 3600)


def test_rate_estimate_converges_to_the_true_rate_within_its_sigma(catalog):
    rng = np.random.default_rng(3)
    state = fix(0.0)  # rate unknown: zero with 1 deg/s sigma
    for k in range(1, 31):
        t = 0.2 * k
        res = track(detections(catalog, attitude(t), rng)[0], state, t, catalog, CAM)
        assert res.ok, (k, res.reason)
        state = res.state
    err = state.omega - OMEGA
    assert np.all(np.abs(err) < 3 * state.rate_sigma)
    assert np.all(state.rate_sigma < np.radians(0.01))
    assert np.linalg.norm(err) < np.radians(0.01)


def test_gate_violation_returns_lost_with_the_reason(catalog):
    rng = np.random.default_rng(4)
    # a settled track: attitude known to 0.02 px, rate (zero) to 1e-6 rad/s
    state = TrackState(matrix_to_quat(A0), np.zeros(3), np.diag([(0.02 / CAM.f) ** 2] * 3 + [1e-12] * 3), 0.0)
    shift = Rotation.from_rotvec([1.0 / CAM.f, 0.0, 0.0]).as_matrix()  # every star 1 px off the prediction
    px, _ = detections(catalog, shift @ A0, rng, sigma_px=0.05)
    res = track(px, state, 0.0, catalog, CAM)
    assert res.status is TrackStatus.LOST
    assert "disagrees with the prediction beyond its gate" in res.reason
    assert res.innovation_chi2 > TrackParams().innovation_chi2
    far = Rotation.from_rotvec([40.0 / CAM.f, 0.0, 0.0]).as_matrix()  # beyond every window
    res = track(detections(catalog, far @ A0, rng)[0], state, 0.0, catalog, CAM)
    assert not res.ok and res.reason.startswith("too few matched stars")


def test_bad_input_and_stale_prediction(catalog):
    with pytest.raises(ValueError, match=r"pixels must have shape \(N, 2\)"):
        track(np.zeros(5), fix(0.0), 0.2, catalog, CAM)
    with pytest.raises(ValueError, match="sigma_px must be positive"):
        track(np.zeros((10, 2)), fix(0.0), 0.2, catalog, CAM, sigma_px=np.ones(3))
    res = track(np.zeros((10, 2)), fix(0.0), 5.0, catalog, CAM)
    assert not res.ok and "outside 0..2.0 s" in res.reason


def test_smeared_star_is_detected_and_centroided_near_mid_exposure():
    det = DetectorModel()
    omega = np.radians([0.0, 1.0, 0.0])  # 1 deg/s across the boresight: ~13 px over 100 ms
    psf = SmearPSF(CAM, det, omega, det.exposure_s)
    xs, ys = np.array([600.0, 1300.0, 2000.0]), np.array([500.0, 970.0, 1500.0])
    stars = Stars(np.arange(1, 4), CAM.pixel_to_vector(xs, ys) @ A0, [3.0, 3.5, 4.0], [0.8] * 3, [0.6] * 3)
    frame = render_frame(stars, A0, CAM, det, seed=3, psf=psf).frame
    found = extract_stars(frame, CAM)
    for x, y in zip(xs, ys, strict=True):
        tx, ty = psf.track(x, y)
        assert np.hypot(tx[-1] - tx[0], ty[-1] - ty[0]) > 12  # really smeared
        d = np.hypot(found.x - x, found.y - y)
        assert np.sum(d < 15) == 1  # one detection, not split along the streak
        assert d.min() < 1.5  # near the mid-exposure position (the ends are 6.5 px away)
