"""Attitude from matched star pairs: Davenport q-method, SVD cross-check, covariance, residuals.

Wahba's problem: find the attitude matrix ``A`` (``v_sensor = A @ v_icrs``, docs/CONVENTIONS.md)
minimising ``sum_i w_i |b_i - A r_i|^2`` for sensor-frame unit vectors ``b_i`` and ICRS catalog
unit vectors ``r_i``. Weights are ``w_i = 1 / sigma_i^2`` with ``sigma_i`` the per-axis direction
noise of detection ``i`` in radians (QUEST measurement model, Shuster & Oh 1981).

* ``davenport_q``: the largest eigenvector of Davenport's 4x4 ``K`` matrix (Enright & McVittie ref. 21),
  returned as the scalar-first quaternion ``q_icrs_to_sensor`` with ``w >= 0``.
* ``svd_attitude``: Markley's SVD solution, an independent algorithm for cross-checks.
* ``attitude_covariance``: ``P0 = [sum_i sigma_i^-2 (I - b_i b_i^T)]^-1`` (rad^2), the a-priori
  covariance of the small rotation error angles about the sensor axes (Shuster & Oh 1981): right
  only when the ``sigma_i`` given are the real noise.
* ``variance_factor``: the a-posteriori variance of unit weight ``s0^2 = chi^2 / (2n - 3)`` with
  ``chi^2 = sum_i (theta_i / sigma_i)^2`` over the residual angles ``theta_i`` of the ``n`` stars
  (2 measured components per star, 3 attitude parameters): the standard least-squares estimate of
  how much larger the real noise is than the one assumed (``E[chi^2] = 2n - 3`` when the
  ``sigma_i`` are right; the same scaling as the QUEST covariance literature's residual-based
  ``sigma`` estimate, Shuster 1990 "Kalman filtering of spacecraft attitude and the QUEST model").
* ``solve_attitude`` reports ``P = max(1, s0^2) P0``: centroid noise larger than the caller
  announced (a defocused or smeared frame, a wrong noise model) shows in the residuals and widens
  the reported covariance, and so the sigma fields and the roll bound of the confidence decision;
  a fit whose residuals are no larger than expected keeps the a-priori ``P0`` (a small ``s0^2``
  from a handful of stars is chance, not evidence that the noise is smaller than assumed). With
  two stars (1 degree of freedom) the factor is the one residual constraint: noisy, but it can
  only widen ``P``. ``AttitudeSolution.covariance_apriori`` keeps ``P0``: verification gates are
  built from the announced noise and use it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit


def attitude_profile(b: np.ndarray, r: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Attitude profile matrix ``B = sum_i w_i b_i r_i^T`` (3x3)."""
    return _profile(_rows(b), _rows(r), np.asarray(w, float).ravel())


def davenport_q(b: np.ndarray, r: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Scalar-first quaternion ICRS -> sensor minimising Wahba's loss (Davenport q-method).

    For ``A(q)`` with ``q = [w, v]`` (scipy / our convention, ``A = R(q)``), the gain
    ``tr(A B^T) = q^T K q`` with ``K = [[sigma, z^T], [z, S - sigma I]]``, ``S = B + B^T``,
    ``sigma = tr B`` and ``z = [B_zy - B_yz, B_xz - B_zx, B_yx - B_xy]`` (B^T's skew part).
    """
    b = _rows(b)
    return _davenport(b, _rows(r), np.ones(len(b)) if w is None else np.asarray(w, float).ravel())


def svd_attitude(b: np.ndarray, r: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Attitude matrix by Markley's SVD method: ``A = U diag(1, 1, det U det V) V^T``, ``B = U S V^T``."""
    b = _rows(b)
    return svd_attitude_kernel(b, _rows(r), np.ones(len(b)) if w is None else np.asarray(w, float).ravel())


def attitude_covariance(b: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Covariance (rad^2, 3x3, sensor axes) of the attitude error angles; inf if unobservable."""
    b = _rows(b)
    return covariance_kernel(b, np.broadcast_to(np.asarray(sigma, float), (len(b),)).copy())


def variance_factor(residuals: np.ndarray, sigma: np.ndarray | float) -> float:
    """A-posteriori variance of unit weight ``chi^2 / (2n - 3)`` of a fit to ``n >= 2`` stars
    (``residuals`` angles in rad, ``sigma`` per-axis noise in rad); NaN below two stars."""
    res = np.asarray(residuals, float).ravel()
    return float(_variance_factor(res, np.broadcast_to(np.asarray(sigma, float), res.shape).copy()))


def residual_angles(b: np.ndarray, r: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Angle in radians between each measured ``b_i`` and its predicted ``A r_i``."""
    b = np.asarray(b, float)
    out = _residual_angles(_rows(b), _rows(r), np.ascontiguousarray(a, float))
    return out.reshape(b.shape[:-1])


def _rows(v) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(v, float).reshape(-1, 3))


# --- compiled kernels (numba, cached on disk): solve_attitude runs several times per hypothesis;
# the ``*_kernel`` ones are also building blocks of other modules' kernels ---


@njit(cache=True, nogil=True)
def _profile(b, r, w):  # pragma: no cover - compiled
    out = np.zeros((3, 3))
    for i in range(b.shape[0]):
        for j in range(3):
            for k in range(3):
                out[j, k] += w[i] * b[i, j] * r[i, k]
    return out


@njit(cache=True, nogil=True)
def _davenport(b, r, w):  # pragma: no cover - compiled
    bm = _profile(b, r, w)
    sigma = bm[0, 0] + bm[1, 1] + bm[2, 2]
    k = np.empty((4, 4))
    k[0, 0] = sigma
    z0, z1, z2 = bm[2, 1] - bm[1, 2], bm[0, 2] - bm[2, 0], bm[1, 0] - bm[0, 1]
    k[0, 1], k[0, 2], k[0, 3] = z0, z1, z2
    k[1, 0], k[2, 0], k[3, 0] = z0, z1, z2
    for i in range(3):
        for j in range(3):
            k[1 + i, 1 + j] = bm[i, j] + bm[j, i] - (sigma if i == j else 0.0)
    _, vecs = np.linalg.eigh(k)
    q = vecs[:, 3] / np.sqrt(np.sum(vecs[:, 3] ** 2))
    return -q if q[0] < 0 else q


@njit(cache=True, nogil=True)
def svd_attitude_kernel(b, r, w):  # pragma: no cover - compiled
    """:func:`svd_attitude`'s matrix (contiguous (N, 3) ``b``, ``r`` and weights ``w``)."""
    u, _, vt = np.linalg.svd(_profile(b, r, w))
    u[:, 2] *= np.linalg.det(u) * np.linalg.det(vt)
    return u @ vt


@njit(cache=True, nogil=True)
def covariance_kernel(b, sigma):  # pragma: no cover - compiled
    """:func:`attitude_covariance`'s matrix (contiguous (N, 3) ``b``, per-star ``sigma``, rad)."""
    info = np.zeros((3, 3))
    for i in range(b.shape[0]):
        iv = 1.0 / sigma[i] ** 2
        for j in range(3):
            for k in range(3):
                info[j, k] += iv * ((1.0 if j == k else 0.0) - b[i, j] * b[i, k])
    vals, vecs = np.linalg.eigh(info)
    if vals[0] <= vals[2] * 1e-12:
        return np.full((3, 3), np.inf)
    return (vecs / vals) @ vecs.T


@njit(cache=True, nogil=True)
def _variance_factor(res, sigma):  # pragma: no cover - compiled
    dof = 2 * len(res) - 3
    if dof < 1:
        return np.nan
    return np.sum((res / sigma) ** 2) / dof


@njit(cache=True, nogil=True)
def _residual_angles(b, r, a):  # pragma: no cover - compiled
    out = np.empty(b.shape[0])
    for i in range(b.shape[0]):
        d2 = 0.0
        for j in range(3):
            d = b[i, j] - (a[j, 0] * r[i, 0] + a[j, 1] * r[i, 1] + a[j, 2] * r[i, 2])
            d2 += d * d
        out[i] = 2.0 * np.arcsin(min(np.sqrt(d2) / 2.0, 1.0))
    return out


@njit(cache=True, nogil=True)
def _quat_matrix(q):  # pragma: no cover - compiled
    w, x, y, z = q[0], q[1], q[2], q[3]
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


@njit(cache=True, nogil=True)
def solve_attitude_kernel(b, r, sig):  # pragma: no cover - compiled
    """solve_attitude's numbers: q, A, P, residuals, RMS, variance factor, P0."""
    q = _davenport(b, r, 1.0 / sig**2)
    a = _quat_matrix(q)
    res = _residual_angles(b, r, a)
    p0 = covariance_kernel(b, sig)
    s0 = _variance_factor(res, sig)
    p = p0 * s0 if s0 > 1.0 else p0
    return q, a, p, res, np.sqrt(np.mean(res**2)), s0, p0


@dataclass(frozen=True)
class AttitudeSolution:
    """q-method solution: quaternion ICRS -> sensor (scalar first), its matrix, covariance (rad^2,
    the a-priori one scaled by ``max(1, variance_factor)``), per-star residual angles (rad), their
    RMS (rad), the a-posteriori variance factor and the a-priori covariance (module docstring)."""

    q: np.ndarray
    a: np.ndarray
    covariance: np.ndarray
    residuals: np.ndarray
    rms: float
    variance_factor: float
    covariance_apriori: np.ndarray


def quat_matrix(q) -> np.ndarray:
    """Attitude matrix of a unit scalar-first quaternion (same as ``frames.quat_to_matrix``, no scipy
    overhead): ``A = (w^2 - v.v) I + 2 v v^T + 2 w [v x]``."""
    return _quat_matrix(np.asarray(q, float))


def solve_attitude(b: np.ndarray, r: np.ndarray, sigma) -> AttitudeSolution:
    """Weighted q-method attitude with covariance and residuals; needs >= 2 non-parallel stars.

    ``sigma`` is the per-axis direction noise in radians, scalar or one per star. The covariance is
    the a-priori one times ``max(1, variance_factor)`` (module docstring).
    """
    b = np.asarray(b, float)
    r = np.asarray(r, float)
    if b.ndim != 2 or b.shape[1] != 3 or r.shape != b.shape or len(b) < 2:
        raise ValueError(f"need matching (N,3) arrays with N >= 2, got {b.shape} and {r.shape}")
    sig = np.broadcast_to(np.asarray(sigma, float), (len(b),)).copy()
    q, a, p, res, rms, s0, p0 = solve_attitude_kernel(np.ascontiguousarray(b), np.ascontiguousarray(r), sig)
    return AttitudeSolution(q, a, p, res, float(rms), float(s0), p0)


__all__ = [
    "AttitudeSolution",
    "attitude_covariance",
    "attitude_profile",
    "davenport_q",
    "quat_matrix",
    "residual_angles",
    "solve_attitude",
    "svd_attitude",
    "variance_factor",
]
