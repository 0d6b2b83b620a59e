"""Camera calibration recovers known parameters from identified stars over several frames."""

import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.pipeline.camera_fit import StarObservations, calibrate
from firmware_model.reference_frames import attitude_from_radec_roll

TRUE = CameraModel.from_fov(2592, 1944, 7.5, k1=0.12, k2=-0.4, p1=2e-4, p2=-1e-4)
TRUE = CameraModel(**{**TRUE.to_dict(), "cx": 1301.2, "cy": 965.8})


def _observations(n_frames=8, n_stars=40, noise_px=0.0, seed=0):
    rng = np.random.default_rng(seed)
    frames, atts = [], []
    for _ in range(n_frames):
        a = attitude_from_radec_roll(rng.uniform(0, 2 * np.pi), rng.uniform(-1.2, 1.2), rng.uniform(0, 2 * np.pi))
        x = rng.uniform(0, TRUE.width - 1, n_stars)
        y = rng.uniform(0, TRUE.height - 1, n_stars)
        v_icrs = TRUE.pixel_to_vector(x, y) @ a
        frames.append(
            StarObservations(x + rng.normal(0, noise_px, n_stars), y + rng.normal(0, noise_px, n_stars), v_icrs)
        )
        atts.append(a)
    return frames, atts


def test_noise_free_recovery_exact():
    frames, atts = _observations()
    start = CameraModel.from_fov(2592, 1944, 7.3)
    res = calibrate(frames, start)
    assert res.success and res.residual_rms_px < 1e-5
    c = res.camera
    assert c.f == pytest.approx(TRUE.f, rel=1e-7)
    assert c.k1 == pytest.approx(TRUE.k1, abs=1e-5) and c.k2 == pytest.approx(TRUE.k2, abs=1e-4)
    assert c.cx == pytest.approx(TRUE.cx, abs=1e-3) and c.cy == pytest.approx(TRUE.cy, abs=1e-3)
    assert c.p1 == pytest.approx(TRUE.p1, abs=1e-7)
    for a_fit, a_true in zip(res.attitudes, atts):
        assert np.allclose(a_fit, a_true, atol=1e-8)


def test_noisy_recovery_within_reported_uncertainty():
    frames, _ = _observations(n_frames=10, n_stars=40, noise_px=0.1, seed=1)
    res = calibrate(frames, CameraModel.from_fov(2592, 1944, 7.5), fit=("f", "cx", "cy", "k1", "k2", "p1", "p2"))
    assert res.residual_rms_px == pytest.approx(0.1 * np.sqrt(2), rel=0.1)
    for name in ("f", "k1", "cx", "cy"):
        err = getattr(res.camera, name) - getattr(TRUE, name)
        assert abs(err) < 4 * res.sigmas[name], (name, err, res.sigmas[name])
    # pixel-level agreement of the model over the array is what matters
    xs, ys = np.meshgrid(np.linspace(0, 2591, 9), np.linspace(0, 1943, 7))
    v = TRUE.pixel_to_vector(xs, ys)
    # compare after removing the best rotation (principal point ~ attitude degeneracy)
    from scipy.spatial.transform import Rotation

    rot, _ = Rotation.align_vectors(res.camera.pixel_to_vector(xs, ys), v)
    x2, y2 = res.camera.vector_to_pixel(rot.apply(v))
    assert np.max(np.hypot(x2 - xs.ravel(), y2 - ys.ravel())) < 0.1


def test_bad_input():
    frames, _ = _observations(n_frames=2, n_stars=2)
    with pytest.raises(ValueError, match="at least 3"):
        calibrate(frames, TRUE)
    with pytest.raises(ValueError, match="cannot fit"):
        calibrate(_observations(1, 10)[0], TRUE, fit=("f", "zoom"))
    with pytest.raises(ValueError, match="no frames"):
        calibrate([], TRUE)


def test_end_to_end_from_rendered_frames():
    """Render frames through a distorted camera, extract stars, match truth ids, calibrate."""
    from firmware_model.pipeline.extract import extract_stars
    from ground.sim.sensor_sim import random_star_field, render_frame

    true = CameraModel.from_fov(640, 480, 10.0, k1=0.25, p2=5e-4)
    rng = np.random.default_rng(4)
    frames = []
    for k in range(4):
        a = attitude_from_radec_roll(rng.uniform(0, 6.28), rng.uniform(-1, 1), rng.uniform(0, 6.28))
        stars = random_star_field(true, a, 40, vmag_range=(1.5, 3.5), seed=k, margin_px=8, min_separation_px=15)
        res = render_frame(stars, a, true, seed=k)
        out = extract_stars(res.frame)
        ids, xs, ys = [], [], []
        for t in res.truth["stars"]:
            d = np.hypot(out.x - t["x"], out.y - t["y"])
            j = int(np.argmin(d))
            if d[j] < 1.0 and out.trusted[j]:
                ids.append(t["id"] - 1)
                xs.append(out.x[j])
                ys.append(out.y[j])
        frames.append(StarObservations(xs, ys, stars.vectors[ids]))
    res = calibrate(frames, CameraModel.from_fov(640, 480, 10.0), fit=("f", "k1", "p1", "p2"))
    assert res.residual_rms_px < 0.06
    assert res.camera.k1 == pytest.approx(0.25, abs=0.02)
    assert res.camera.f == pytest.approx(true.f, rel=1e-3)


def test_projection_jacobian_matches_finite_differences():
    """The one-frame fit's analytic Jacobian (every camera parameter and the rotation vector)
    against central differences of the projection, on a camera with every distortion term."""
    from dataclasses import replace

    from firmware_model.pipeline.camera_fit import projection_jacobian, rotvec_matrix

    cam = CameraModel(1024, 768, 5100.0, 511.5, 383.5, k1=0.1, k2=-0.05, k3=0.01, p1=1e-3, p2=-2e-3)
    rng = np.random.default_rng(0)
    v0 = np.column_stack([rng.uniform(-0.1, 0.1, 20), rng.uniform(-0.07, 0.07, 20), np.ones(20)])
    v0 /= np.linalg.norm(v0, axis=1, keepdims=True)
    theta = np.array([0.02, -0.01, 0.03])
    fit = ("f", "cx", "cy", "k1", "k2", "k3", "p1", "p2")
    p0 = np.array([getattr(cam, k) for k in fit])

    def pixels(params, th):
        x, y = replace(cam, **dict(zip(fit, params))).vector_to_pixel(v0 @ rotvec_matrix(th).T)
        return np.column_stack([x, y]).ravel()

    jac = projection_jacobian(cam, fit, v0 @ rotvec_matrix(theta).T, theta)
    num = np.zeros_like(jac)
    for i in range(len(fit)):
        d = np.zeros(len(fit))
        d[i] = 1e-6 * max(1.0, abs(p0[i]))
        num[:, i] = (pixels(p0 + d, theta) - pixels(p0 - d, theta)) / (2 * d[i])
    for i in range(3):
        d = np.zeros(3)
        d[i] = 1e-7
        num[:, len(fit) + i] = (pixels(p0, theta + d) - pixels(p0, theta - d)) / 2e-7
    assert np.max(np.abs(jac - num)) < 1e-8 * np.max(np.abs(num))


def test_the_fitted_focal_lengths_uncertainty_tilts_an_off_centre_field_more():
    """``camera_attitude_covariance``: what fitting f adds to the attitude's covariance (marginal
    minus camera-held): positive semi-definite, and larger across the boresight for stars all on
    one side of the array (a focal-length error moves them all one way) than for a centred set."""
    from firmware_model.pipeline.frame_fit import fit_frame

    cam = CameraModel.from_horizontal_fov(1024, 768, 11.4)
    rng = np.random.default_rng(2)
    a = attitude_from_radec_roll(1.0, 0.3, 0.2)

    def added(xmin, xmax):
        x, y = rng.uniform(xmin, xmax, 20), rng.uniform(50, 718, 20)
        v = cam.pixel_to_vector(x, y) @ a  # sensor -> ICRS
        obs = StarObservations(x + rng.normal(0, 0.3, 20), y + rng.normal(0, 0.3, 20), v)
        res = fit_frame(obs, cam, k1_min_stars=100)
        assert res is not None and res.success
        return res.camera_attitude_covariance[0]

    centred, one_side = added(100, 924), added(700, 1000)
    for c in (centred, one_side):
        assert np.all(np.linalg.eigvalsh(0.5 * (c + c.T)) > -1e-18)
    assert one_side[1, 1] > 10 * centred[1, 1]  # tilt about sensor y: the x offset of the stars


@pytest.mark.parametrize("k1_min_stars", [6, 100])
def test_the_compiled_frame_fit_agrees_with_calibrate(k1_min_stars):
    """``frame_fit.fit_frame`` (compiled Levenberg-Marquardt, rotations on the group) against
    ``calibrate`` (scipy's MINPACK) on the same stars: focal length, k1, attitude, residual RMS,
    sigmas and the covariance the fitted camera adds."""
    from dataclasses import replace

    from firmware_model.pipeline.frame_fit import fit_frame

    rng = np.random.default_rng(5)
    for _ in range(20):
        true = CameraModel(1024, 768, 5100.0 * rng.uniform(0.9, 1.1), 511.5, 383.5, k1=rng.uniform(-0.3, 0.3), p1=1e-4)
        start = replace(true, f=true.f * rng.uniform(0.98, 1.02), k1=0.0)
        n = int(rng.integers(8, 50))
        x, y = rng.uniform(0, 1023, n), rng.uniform(0, 767, n)
        a = attitude_from_radec_roll(rng.uniform(0, 6), rng.uniform(-1, 1), rng.uniform(0, 6))
        obs = StarObservations(x + rng.normal(0, 0.5, n), y + rng.normal(0, 0.5, n), true.pixel_to_vector(x, y) @ a)
        fitted = ("f", "k1") if n >= k1_min_stars else ("f",)
        ref, got = calibrate([obs], start, fit=fitted), fit_frame(obs, start, k1_min_stars)
        assert got is not None and got.success and ref.success
        assert got.camera.f == pytest.approx(ref.camera.f, abs=1e-4)
        assert got.camera.k1 == pytest.approx(ref.camera.k1, abs=1e-6)
        turn = got.attitudes[0] @ ref.attitudes[0].T
        assert np.degrees(np.arccos(min(1.0, (np.trace(turn) - 1) / 2))) * 3600 < 0.1  # arcsec
        assert got.residual_rms_px == pytest.approx(ref.residual_rms_px, rel=1e-9)
        assert got.sigmas == pytest.approx(ref.sigmas, rel=1e-4)
        np.testing.assert_allclose(
            got.camera_attitude_covariance[0],
            ref.camera_attitude_covariance[0],
            rtol=0,
            atol=1e-2 * np.max(np.abs(ref.camera_attitude_covariance[0])),
        )


def test_pipeline_warm_up_compiles_every_solve_kernel():
    """``run.warm_up`` (the device's start-up) leaves no kernel of a solve to compile in the first
    GO: in a fresh process, after it, every compiled kernel a solve calls from Python (the camera's
    projections, the attitude solve, the one-frame fit, the verification's and the pattern stage's)
    has its signature (a first solve compiling them took seconds of the optics search's
    1.5 s budget and of an attitude feed's staleness window)."""
    import subprocess
    import sys

    code = (
        "from firmware_model import camera\nfrom firmware_model.pipeline import run, frame_fit, scale_free\n"
        "from firmware_model.ident import attitude, strategy, verify\n"
        "run.warm_up()\n"
        "kernels = (camera.pixel_to_vector_kernel, camera.vector_to_pixel_kernel,\n"
        "    attitude.solve_attitude_kernel, frame_fit.fit_frame_kernel, verify._residual_step,\n"
        "    verify._refine_steps, strategy._free_in_gate, scale_free._assign_kernel, scale_free._refine)\n"
        "print(all(k.signatures for k in kernels))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "True"
