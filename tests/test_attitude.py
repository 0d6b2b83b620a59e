"""q-method against known rotations, the SVD cross-check, weights, covariance and residuals."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from firmware_model.ident.attitude import (
    attitude_covariance,
    davenport_q,
    quat_matrix,
    residual_angles,
    solve_attitude,
    svd_attitude,
    variance_factor,
)
from firmware_model.reference_frames import matrix_to_quat, quat_to_matrix


def star_set(rng, n, radius=0.12):
    """``n`` ICRS unit vectors within ``radius`` rad of a random direction."""
    c = rng.normal(size=3)
    c /= np.linalg.norm(c)
    v = c + radius * rng.normal(size=(n, 3)) / np.sqrt(3)
    return v / np.linalg.norm(v, axis=1)[:, None]


@pytest.mark.parametrize("seed", range(5))
def test_q_method_recovers_known_rotation_exactly(seed):
    rng = np.random.default_rng(seed)
    a = Rotation.random(random_state=seed).as_matrix()
    r = star_set(rng, 2 + seed)
    b = r @ a.T
    q = davenport_q(b, r)
    assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    np.testing.assert_allclose(quat_to_matrix(q), a, atol=1e-10)
    np.testing.assert_allclose(q, matrix_to_quat(a), atol=1e-10)


def test_q_method_agrees_with_svd_under_noise_and_weights():
    rng = np.random.default_rng(7)
    for _ in range(20):
        a = Rotation.random(random_state=rng).as_matrix()
        r = star_set(rng, 6)
        b = r @ a.T + rng.normal(scale=1e-4, size=(6, 3))
        b /= np.linalg.norm(b, axis=1)[:, None]
        w = rng.uniform(0.1, 10.0, 6)
        np.testing.assert_allclose(quat_to_matrix(davenport_q(b, r, w)), svd_attitude(b, r, w), atol=1e-9)


def test_weights_pull_the_solution_toward_the_trusted_star():
    rng = np.random.default_rng(3)
    a = Rotation.random(random_state=3).as_matrix()
    r = star_set(rng, 3)
    b = r @ a.T
    b[2] = b[2] + np.array([1e-3, 0, 0])
    b /= np.linalg.norm(b, axis=1)[:, None]
    even = residual_angles(b, r, quat_to_matrix(davenport_q(b, r)))
    trusted = residual_angles(b, r, quat_to_matrix(davenport_q(b, r, np.array([1.0, 1.0, 1e4]))))
    assert trusted[2] < 0.05 * even[2]


def test_quat_matrix_matches_frames():
    q = np.random.default_rng(1).normal(size=4)
    q /= np.linalg.norm(q)
    np.testing.assert_allclose(quat_matrix(q), quat_to_matrix(q), atol=1e-14)


def test_covariance_matches_monte_carlo():
    rng = np.random.default_rng(11)
    a = Rotation.random(random_state=11).as_matrix()
    r = star_set(rng, 5)
    sigma = 3e-5
    truth_b = r @ a.T
    errs = []
    for _ in range(3000):
        b = truth_b + rng.normal(scale=sigma, size=truth_b.shape)
        b /= np.linalg.norm(b, axis=1)[:, None]
        d = quat_to_matrix(davenport_q(b, r)) @ a.T  # = exp([-theta x]) for small error angles
        errs.append([d[1, 2] - d[2, 1], d[2, 0] - d[0, 2], d[0, 1] - d[1, 0]])
    emp = np.cov(np.array(errs).T / 2.0)
    pred = attitude_covariance(truth_b, np.full(5, sigma))
    # per-axis variances within 10 % (3000 samples: ~2.6 % standard error)
    np.testing.assert_allclose(np.diag(emp), np.diag(pred), rtol=0.1)


def test_solve_attitude_residuals_and_errors():
    rng = np.random.default_rng(5)
    a = Rotation.random(random_state=5).as_matrix()
    r = star_set(rng, 4)
    sol = solve_attitude(r @ a.T, r, 1e-5)
    assert sol.rms < 1e-12 and sol.residuals.shape == (4,)
    np.testing.assert_allclose(sol.a, a, atol=1e-10)
    with pytest.raises(ValueError, match="N >= 2"):
        solve_attitude(r[:1] @ a.T, r[:1], 1e-5)
    assert np.all(np.isinf(attitude_covariance(np.array([[0, 0, 1.0], [0, 0, 1.0]]), np.ones(2))))


def _error_angles(a_est, a_true):
    d = a_est @ a_true.T  # = exp([-theta x]) for small error angles
    return np.array([d[1, 2] - d[2, 1], d[2, 0] - d[0, 2], d[0, 1] - d[1, 0]]) / 2.0


def test_clean_fit_keeps_the_a_priori_covariance():
    """Noise as announced: s0^2 near 1 on average, and a fit with s0^2 <= 1 reports P0 exactly."""
    rng = np.random.default_rng(21)
    a = Rotation.random(random_state=21).as_matrix()
    r = star_set(rng, 8)
    sigma = 3e-5
    factors = []
    for _ in range(400):
        b = r @ a.T + rng.normal(scale=sigma, size=r.shape)
        b /= np.linalg.norm(b, axis=1)[:, None]
        sol = solve_attitude(b, r, sigma)
        factors.append(sol.variance_factor)
        np.testing.assert_allclose(sol.covariance, max(1.0, sol.variance_factor) * sol.covariance_apriori)
        if sol.variance_factor <= 1.0:
            np.testing.assert_array_equal(sol.covariance, sol.covariance_apriori)
    assert abs(np.mean(factors) - 1.0) < 0.1  # E[chi^2 / (2n - 3)] = 1 (~2 % standard error)
    exact = solve_attitude(r @ a.T, r, sigma)
    np.testing.assert_array_equal(exact.covariance, attitude_covariance(r @ a.T, np.full(8, sigma)))
    assert variance_factor(np.array([1e-5, 2e-5]), 1e-5) == pytest.approx(5.0)  # 2 stars: 1 dof
    assert np.isnan(variance_factor(np.array([1e-5]), 1e-5))


@pytest.mark.parametrize("n", [4, 8, 20])
def test_scaled_covariance_covers_unannounced_noise(n):
    """Real noise 5x the announced one: the a-priori sigma misses the error, the scaled one covers it."""
    rng = np.random.default_rng(100 + n)
    sigma = 3e-5
    z_prior, z_post = [], []
    for _ in range(600):
        a = Rotation.random(random_state=rng).as_matrix()
        r = star_set(rng, n)
        b = r @ a.T + rng.normal(scale=5 * sigma, size=r.shape)
        b /= np.linalg.norm(b, axis=1)[:, None]
        sol = solve_attitude(b, r, sigma)
        e = _error_angles(sol.a, a)
        z_prior.append(np.abs(e) / np.sqrt(np.diag(sol.covariance_apriori)))
        z_post.append(np.abs(e) / np.sqrt(np.diag(sol.covariance)))
    zp, zq = np.array(z_prior), np.array(z_post)
    assert np.mean(zp > 3) > 0.3  # the a-priori covariance is far too small
    # scaled: error/sigma is Student-t with 2n - 3 dof (4 stars, 5 dof: RMS 1.29, 3 % beyond 3 sigma;
    # 8 stars: RMS 1.08, 1 %; many stars: the Gaussian's 1 and 0.27 %)
    few = n == 4
    assert 0.8 < np.sqrt(np.mean(zq**2)) < (1.5 if few else 1.25)
    assert np.mean(zq > 3) < (0.05 if few else 0.025)
    assert np.max(zq) < (15 if few else 6)
