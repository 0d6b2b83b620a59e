"""Triangle fallback of the geometric mode: candidates against brute force, noisy mono frames."""

import numpy as np
import pytest
from ident_sky import random_attitude, random_catalog, scene

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import angle_between
from firmware_model.ident.consensus import Outcome
from firmware_model.ident.solver import SolveParams
from firmware_model.ident.strategy import solve
from firmware_model.ident.triangle import triangles
from firmware_model.ident.verify import FieldOfView
from firmware_model.reference_frames import quat_to_matrix, rotation_angle


def test_triangles_equal_brute_force():
    cat = random_catalog(80, 2, phi_max_deg=50.0, colour=False)
    rng = np.random.default_rng(0)
    eps = np.radians(0.5)
    full = angle_between(cat.vec[:, None, :], cat.vec[None, :, :])
    in_table = (full > cat.phi_min) & (full <= cat.phi_max)
    checked = 0
    for _ in range(20):
        a = random_attitude(rng)
        idx = cat.stars_within(a[2], np.radians(25))
        if len(idx) < 3:
            continue
        v3 = cat.vec[idx[:3]] @ a.T
        got = {tuple(t) for t in triangles(v3, cat, eps).tolist()}
        m01, m02, m12 = (float(angle_between(v3[p], v3[q])) for p, q in ((0, 1), (0, 2), (1, 2)))
        ok01 = in_table & (np.abs(full - m01) <= eps)
        ok02 = in_table & (np.abs(full - m02) <= eps)
        ok12 = in_table & (np.abs(full - m12) <= eps)
        x, y, z = np.nonzero(ok01[:, :, None] & ok02[:, None, :] & ok12[None, :, :])
        keep = (x != y) & (x != z) & (y != z)
        x, y, z = x[keep], y[keep], z[keep]
        hand = np.sign(np.linalg.det(np.stack([cat.vec[x], cat.vec[y], cat.vec[z]], axis=1)))
        sel = hand == np.sign(np.linalg.det(v3))
        ref = set(zip(x[sel].tolist(), y[sel].tolist(), z[sel].tolist()))
        assert got == ref
        assert tuple(idx[:3].tolist()) in got
        checked += 1
    assert checked >= 5


@pytest.fixture(scope="module")
def cat():
    return random_catalog(2800, 1, phi_max_deg=20.0, colour=False)


def test_noisy_mono_frames_solve_through_the_fallback(cat):
    """1 px noise on a 20 deg field: beyond 4-star voting, the verified triangles still solve."""
    camera = CameraModel.from_fov(1024, 1024, 10.0)
    params = SolveParams(mode="geometric", sigma_vec=1.0 / camera.f, fov=FieldOfView.from_camera(camera))
    rng = np.random.default_rng(5)
    high = wrong = 0
    for _ in range(12):
        a = random_attitude(rng)
        v, _, _, truth = scene(cat, a, rng, camera=camera, sigma_vec=1.0 / camera.f)
        res = solve(v, None, None, cat, params)
        if res.status is Outcome.HIGH_CONFIDENCE:
            high += 1
            wrong += int(np.any(truth[res.matched_det] != res.matched_cat))
            err = rotation_angle(quat_to_matrix(res.q_icrs_to_sensor), a)
            assert err < 5 * np.sqrt(np.trace(res.covariance))  # consistent with the reported covariance
    assert high >= 10 and wrong == 0
