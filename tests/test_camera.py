"""Camera model: reference design numbers, projection conventions, exact inverse."""

import numpy as np
import pytest

from firmware_model.camera import CameraModel


def test_reference_design_focal_and_fov():
    cam = CameraModel.reference_design()
    assert (cam.width, cam.height) == (2592, 1944)
    assert cam.f == pytest.approx(972.0 / np.tan(np.radians(7.5)), rel=1e-12)
    assert (cam.cx, cam.cy) == (1295.5, 971.5)
    assert np.degrees(cam.fov_half_angle_minor) == pytest.approx(7.5, abs=1e-9)
    assert np.degrees(cam.fov_half_angle_major) > 9.9
    assert cam.fov_half_angle_diagonal > cam.fov_half_angle_major


def test_from_focal_matches_pixel_pitch():
    cam = CameraModel.from_focal(2592, 1944, focal_mm=16.0, pixel_um=2.2)
    assert cam.f == pytest.approx(16000.0 / 2.2)


def test_axis_conventions():
    cam = CameraModel.reference_design()
    x, y = cam.vector_to_pixel([0.0, 0.0, 1.0])
    assert (x[0], y[0]) == (cam.cx, cam.cy)
    x, y = cam.vector_to_pixel([0.01, 0.0, 1.0])  # +x -> increasing column
    assert x[0] == pytest.approx(cam.cx + 0.01 * cam.f) and y[0] == cam.cy
    x, y = cam.vector_to_pixel([0.0, 0.01, 1.0])  # +y -> increasing row
    assert y[0] == pytest.approx(cam.cy + 0.01 * cam.f)
    x, y = cam.vector_to_pixel([0.0, 0.0, -1.0])
    assert np.isnan(x[0]) and np.isnan(y[0])


@pytest.mark.parametrize(
    "dist",
    [{}, {"k1": -0.3, "k2": 0.1, "k3": -0.05, "p1": 1e-3, "p2": -2e-3}, {"k1": 0.2, "p1": -5e-4}],
)
def test_inverse_exact_over_array(dist):
    cam = CameraModel.from_fov(2592, 1944, 7.5, **dist)
    xs, ys = np.meshgrid(np.linspace(-0.5, 2591.5, 41), np.linspace(-0.5, 1943.5, 31))
    v = cam.pixel_to_vector(xs, ys)
    assert np.allclose(np.linalg.norm(v, axis=1), 1.0)
    x2, y2 = cam.vector_to_pixel(v)
    assert np.max(np.hypot(x2 - xs.ravel(), y2 - ys.ravel())) < 1e-6


def test_distortion_moves_corners():
    plain = CameraModel.reference_design()
    barrel = CameraModel.from_fov(2592, 1944, 7.5, k1=-0.5)
    v = plain.pixel_to_vector([0.0], [0.0])
    x, y = barrel.vector_to_pixel(v)
    assert np.hypot(x[0] - plain.cx, y[0] - plain.cy) < np.hypot(plain.cx, plain.cy) - 5


def test_dict_round_trip_and_errors():
    cam = CameraModel.from_fov(640, 480, 10.0, k1=0.01, p2=1e-4)
    assert CameraModel.from_dict(cam.to_dict()) == cam
    with pytest.raises(ValueError, match="unknown"):
        CameraModel.from_dict({**cam.to_dict(), "bogus": 1})
    with pytest.raises(ValueError, match="lacks"):
        CameraModel.from_dict({"width": 10})
    with pytest.raises(ValueError):
        CameraModel(10, 10, -1.0, 5, 5)
    with pytest.raises(ValueError):
        CameraModel.from_fov(10, 10, 95.0)
    with pytest.raises(ValueError, match="same length"):
        cam.pixel_to_vector([1.0, 2.0], [1.0])


def test_no_inverse_beyond_a_fold_gives_nan():
    cam = CameraModel.from_fov(2592, 1944, 7.5, k1=-8.0)  # r (1 - 8 r^2) peaks at r_d = 0.136
    v = cam.pixel_to_vector([cam.cx, 0.0], [cam.cy, 0.0])
    assert np.allclose(v[0], [0, 0, 1]) and np.all(np.isnan(v[1]))


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=60, deadline=None)
@given(
    k1=st.floats(-0.5, 0.5),
    k2=st.floats(-1.0, 1.0),
    p1=st.floats(-2e-3, 2e-3),
    p2=st.floats(-2e-3, 2e-3),
    x=st.floats(-0.5, 2591.5),
    y=st.floats(-0.5, 1943.5),
)
def test_inverse_property(k1, k2, p1, p2, x, y):
    cam = CameraModel.from_fov(2592, 1944, 7.5, k1=k1, k2=k2, p1=p1, p2=p2)
    x2, y2 = cam.vector_to_pixel(cam.pixel_to_vector([x], [y]))
    assert np.hypot(x2[0] - x, y2[0] - y) < 1e-6
