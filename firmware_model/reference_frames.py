"""Reference frames and attitude conventions (see docs/CONVENTIONS.md).

* Quaternions are scalar first, ``q = [w, x, y, z]``, unit norm, canonical ``w >= 0``.
* ``q_icrs_to_sensor`` (matrix ``A``) maps ICRS components to sensor components:
  ``v_sensor = A @ v_icrs``.
* Sensor frame: +z along the boresight (out of the lens, toward the sky), +x along
  increasing pixel column, +y along increasing pixel row.
* Boresight angles: RA/Dec of +z; roll 0 puts celestial north toward decreasing row
  (image "up"), so east is toward decreasing column as on a sky chart. Positive roll
  rotates the sensor frame about +z (x toward y).
* Angles in radians unless a name ends in ``_deg``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def radec_to_vec(ra, dec):
    """Unit vector(s) from right ascension and declination in radians; shape (..., 3)."""
    ra = np.asarray(ra, dtype=float)
    dec = np.asarray(dec, dtype=float)
    cd = np.cos(dec)
    return np.stack([cd * np.cos(ra), cd * np.sin(ra), np.sin(dec)], axis=-1)


def vec_to_radec(v):
    """(ra, dec) in radians, ra in [0, 2 pi), for vector(s) of shape (..., 3)."""
    v = np.asarray(v, dtype=float)
    n = np.linalg.norm(v, axis=-1)
    ra = np.mod(np.arctan2(v[..., 1], v[..., 0]), 2 * np.pi)
    dec = np.arcsin(np.clip(v[..., 2] / n, -1.0, 1.0))
    return ra, dec


def quat_to_matrix(q) -> np.ndarray:
    """Attitude matrix A (v_sensor = A @ v_icrs) of a scalar-first quaternion."""
    return Rotation.from_quat(np.asarray(q, dtype=float), scalar_first=True).as_matrix()


def matrix_to_quat(a) -> np.ndarray:
    """Scalar-first unit quaternion with w >= 0 for attitude matrix ``a``."""
    q = Rotation.from_matrix(np.asarray(a, dtype=float)).as_quat(scalar_first=True)
    return np.where(q[..., :1] < 0, -q, q)


def attitude_from_radec_roll(ra, dec, roll) -> np.ndarray:
    """Attitude matrix A for boresight (ra, dec) and roll, radians (module docstring)."""
    z = radec_to_vec(ra, dec)
    north = np.array([0.0, 0.0, 1.0])
    east = np.cross(north, z)
    ne = np.linalg.norm(east)
    if ne < 1e-12:  # boresight at a pole: take RA direction as the reference meridian
        east = np.array([-np.sin(ra), np.cos(ra), 0.0])
    else:
        east = east / ne
    up = np.cross(z, east)  # local north in the tangent plane
    y0 = -up
    x0 = np.cross(y0, z)  # = -east (west): image right points west
    a0 = np.vstack([x0, y0, z])
    c, s = np.cos(roll), np.sin(roll)
    rz = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return rz @ a0


def radec_roll_from_attitude(a):
    """(ra, dec, roll) in radians of attitude matrix ``a``; inverse of attitude_from_radec_roll."""
    a = np.asarray(a, dtype=float)
    ra, dec = vec_to_radec(a[2])
    a0 = attitude_from_radec_roll(ra, dec, 0.0)
    rz = a @ a0.T
    roll = np.arctan2(rz[0, 1], rz[0, 0])
    return float(ra), float(dec), float(np.mod(roll, 2 * np.pi))


def rotation_angle(a1, a2) -> float:
    """Angle in radians of the rotation between two attitude matrices."""
    r = np.asarray(a1) @ np.asarray(a2).T
    return float(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))
