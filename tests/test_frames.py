import numpy as np
import pytest

from firmware_model import reference_frames as frames


def test_quaternion_round_trip_and_canonical_sign():
    rng = np.random.default_rng(1)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        a = frames.quat_to_matrix(q)
        q2 = frames.matrix_to_quat(a)
        assert q2[0] >= 0
        assert np.allclose(q2, q if q[0] >= 0 else -q, atol=1e-12)


def test_boresight_is_sensor_z_and_north_is_up():
    ra, dec = np.radians(30.0), np.radians(20.0)
    a = frames.attitude_from_radec_roll(ra, dec, 0.0)
    bore = frames.radec_to_vec(ra, dec)
    assert np.allclose(a @ bore, [0, 0, 1])
    # a star slightly north of the boresight lands at negative sensor y (image up)
    north = frames.radec_to_vec(ra, dec + 0.01)
    assert (a @ north)[1] < 0
    # a star slightly east lands at negative sensor x (image left)
    east = frames.radec_to_vec(ra + 0.01, dec)
    assert (a @ east)[0] < 0


@pytest.mark.parametrize("ra,dec,roll", [(10, 80, 45), (200, -30, 300), (359, 0, 1), (0, 89.999, 90)])
def test_radec_roll_inverse(ra, dec, roll):
    a = frames.attitude_from_radec_roll(np.radians(ra), np.radians(dec), np.radians(roll))
    assert np.allclose(a @ a.T, np.eye(3), atol=1e-12)
    r2, d2, l2 = frames.radec_roll_from_attitude(a)
    a2 = frames.attitude_from_radec_roll(r2, d2, l2)
    assert frames.rotation_angle(a, a2) < 1e-9


def test_vec_radec_round_trip():
    rng = np.random.default_rng(2)
    v = rng.normal(size=(100, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    ra, dec = frames.vec_to_radec(v)
    assert np.allclose(frames.radec_to_vec(ra, dec), v, atol=1e-12)
