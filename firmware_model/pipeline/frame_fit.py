"""One frame's focal length (and k1) fitted with its attitude: the device's per-solve optics fit.

The model and residuals are :func:`camera_fit.calibrate`'s for one frame with the principal point
and the other distortion terms held (pixel residuals predicted minus measured of
``camera.vector_to_pixel(A @ v_icrs)``). The solver is a compiled Levenberg-Marquardt (numba,
cached on disk) with the analytic Jacobian and the attitude updated on the rotation group (a small
rotation about the sensor axes per step): the search calls this fit once or twice per hypothesis,
and scipy's ``least_squares`` spent most of each call in its own and our Python-level callbacks
on a handful of parameters (docs/identification.md). Its answers agree with ``calibrate``'s (tested).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numba import njit

from firmware_model.camera import CameraModel, distort_point, pixel_to_vector_kernel
from firmware_model.ident.attitude import svd_attitude_kernel
from firmware_model.pipeline.camera_fit import CalibrationResult, StarObservations

#: Iteration cap, and the relative step and cost-reduction tolerances of the compiled fit.
MAX_ITER = 100
XTOL = 1e-10
FTOL = 1e-14


def fit_frame(obs: StarObservations, camera: CameraModel, k1_min_stars: int) -> CalibrationResult | None:
    """One frame's focal length, and k1 when at least ``k1_min_stars`` stars are given, fitted with
    its attitude (principal point held); None when the stars cannot constrain it."""
    c = camera
    dist = np.array([c.k1, c.k2, c.k3, c.p1, c.p2])
    x, y, v_icrs = np.asarray(obs.x, float), np.asarray(obs.y, float), np.ascontiguousarray(obs.v_icrs, float)
    try:
        fitted = fit_frame_kernel(x, y, v_icrs, c.f, c.cx, c.cy, dist, k1_min_stars)
    except np.linalg.LinAlgError:  # a parameter no star constrains
        return None
    return fit_result(camera, fitted)


def fit_result(camera: CameraModel, fitted: tuple) -> CalibrationResult | None:
    """The :class:`CalibrationResult` of a compiled fit's numbers (:func:`fit_frame_kernel`) from
    ``camera``; None when it did not fit."""
    done, f, k1, att, r, sig, added, rms, nit = fitted
    if not done:
        return None
    return CalibrationResult(
        camera=replace(camera, f=float(f), k1=float(k1)),
        attitudes=[att],
        residual_rms_px=float(rms),
        residuals=[-r.reshape(-1, 2)],
        sigmas=dict(zip(("f", "k1"), (float(x) for x in sig))),  # k1's only when it was fitted
        n_observations=len(r) // 2,
        success=nit < MAX_ITER,
        message=f"converged in {nit} iterations" if nit < MAX_ITER else "iteration limit",
        camera_attitude_covariance=[added],
    )


@njit(cache=True, nogil=True)
def fit_frame_kernel(x, y, v_icrs, f0, cx, cy, dist, k1_min_stars):  # pragma: no cover - compiled
    """:func:`fit_frame`'s numbers: (fitted, f, k1, attitude, residuals predicted - measured,
    1-sigma of f [and k1, when at least ``k1_min_stars`` stars are given], the attitude covariance
    the camera's uncertainty adds, RMS residual (px), iterations); not fitted with fewer than
    three stars or no more residuals than parameters. The start: Wahba's attitude of the pinhole
    directions (the fit takes the distortion from there)."""
    n = len(x)
    fit_k1 = n >= k1_min_stars
    nk = 2 if fit_k1 else 1
    none = (False, 0.0, 0.0, np.eye(3), np.empty(0), np.empty(0), np.empty((3, 3)), 0.0, 0)
    if n < 3 or 2 * n <= nk + 3:
        return none
    pinhole = pixel_to_vector_kernel(x, y, f0, cx, cy, 0.0, 0.0, 0.0, 0.0, 0.0)
    a0 = svd_attitude_kernel(pinhole, v_icrs, np.ones(n))
    if not np.all(np.isfinite(a0)):
        return none
    f, k1, att, r, jac, nit = _levenberg_marquardt(v_icrs @ a0.T, x, y, f0, cx, cy, dist, fit_k1)
    if not (np.isfinite(f) and np.all(np.isfinite(r)) and np.all(np.isfinite(jac))):
        return none
    s2 = (r @ r) / max(len(r) - nk - 3, 1)
    info = jac.T @ jac
    cov = np.linalg.inv(info) * s2
    sig = np.sqrt(np.maximum(np.diag(cov)[:nk], 0.0))
    added = cov[nk:, nk:] - np.linalg.inv(np.ascontiguousarray(info[nk:, nk:])) * s2
    return True, f, k1, att @ a0, r, sig, added, np.sqrt(np.mean(r * r) * 2.0), nit


@njit(cache=True, nogil=True)
def _project(v, f, cx, cy, k1, dist, fit_k1, r, jac):  # pragma: no cover - compiled
    """Residuals (predicted - measured are formed by the caller) as predicted pixels into ``r``
    (x0, y0, x1, ...), and their Jacobian into ``jac``: columns f, [k1], then small rotations about
    the sensor axes (``v -> v + delta x v``)."""
    k2, k3, p1, p2 = dist[1], dist[2], dist[3], dist[4]
    nk = 2 if fit_k1 else 1
    for i in range(v.shape[0]):
        vx, vy, vz = v[i, 0], v[i, 1], v[i, 2]
        u, w = vx / vz, vy / vz
        r2 = u * u + w * w
        ud, wd, _radial, j11, j12, j22 = distort_point(u, w, k1, k2, k3, p1, p2)
        j21 = j12
        r[2 * i] = cx + f * ud
        r[2 * i + 1] = cy + f * wd
        jac[2 * i, 0] = ud
        jac[2 * i + 1, 0] = wd
        if fit_k1:
            jac[2 * i, 1] = f * u * r2
            jac[2 * i + 1, 1] = f * w * r2
        # d(u, w)/dv, then dv/d(delta) = -[v]x
        iz = 1.0 / vz
        dxv0, dxv1, dxv2 = f * j11 * iz, f * j12 * iz, -f * (j11 * u + j12 * w) * iz
        dyv0, dyv1, dyv2 = f * j21 * iz, f * j22 * iz, -f * (j21 * u + j22 * w) * iz
        # dv/d(delta) columns (delta x v): (0, -vz, vy), (vz, 0, -vx), (-vy, vx, 0)
        jac[2 * i, nk] = -dxv1 * vz + dxv2 * vy
        jac[2 * i, nk + 1] = dxv0 * vz - dxv2 * vx
        jac[2 * i, nk + 2] = -dxv0 * vy + dxv1 * vx
        jac[2 * i + 1, nk] = -dyv1 * vz + dyv2 * vy
        jac[2 * i + 1, nk + 1] = dyv0 * vz - dyv2 * vx
        jac[2 * i + 1, nk + 2] = -dyv0 * vy + dyv1 * vx


@njit(cache=True, nogil=True)
def _rotation(d):  # pragma: no cover - compiled
    """Rotation matrix of rotation vector ``d`` (rad; Rodrigues)."""
    t = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    k = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    if t < 1e-8:
        return np.eye(3) + k + 0.5 * (k @ k)
    return np.eye(3) + (math.sin(t) / t) * k + ((1.0 - math.cos(t)) / (t * t)) * (k @ k)


@njit(cache=True, nogil=True)
def _levenberg_marquardt(v0, xm, ym, f0, cx, cy, dist, fit_k1):  # pragma: no cover - compiled
    """Levenberg-Marquardt with Marquardt's scaling (the largest diagonal of J^T J seen, as
    MINPACK) on (f, [k1], rotation). ``v0``: the stars' sensor-frame directions at the starting
    attitude (N, 3). Returns f, k1, the rotation from the start, residuals (predicted - measured),
    Jacobian at the answer and the iterations used (``MAX_ITER`` when not converged)."""
    n = v0.shape[0]
    nk = 2 if fit_k1 else 1
    m = nk + 3
    meas = np.empty(2 * n)
    for i in range(n):
        meas[2 * i] = xm[i]
        meas[2 * i + 1] = ym[i]
    f, k1 = f0, dist[0]
    att = np.eye(3)
    v = v0.copy()
    r = np.empty(2 * n)
    jac = np.zeros((2 * n, m))
    _project(v, f, cx, cy, k1, dist, fit_k1, r, jac)
    r -= meas
    cost = r @ r
    scale = np.zeros(m)
    lam = 1e-3
    r_new = np.empty(2 * n)
    jac_new = np.zeros((2 * n, m))
    it = 0
    while it < MAX_ITER:
        it += 1
        a = jac.T @ jac
        g = jac.T @ r
        for j in range(m):
            scale[j] = max(scale[j], a[j, j])
        lhs = a.copy()
        for j in range(m):
            lhs[j, j] += lam * scale[j]
        h = -np.linalg.solve(lhs, g)
        f_new = f + h[0]
        k1_new = k1 + h[1] if fit_k1 else k1
        turn = _rotation(h[nk:])
        v_new = v @ turn.T
        _project(v_new, f_new, cx, cy, k1_new, dist, fit_k1, r_new, jac_new)
        r_new -= meas
        cost_new = r_new @ r_new
        predicted = -(2.0 * (g @ h) + h @ (a @ h))
        step = math.sqrt(np.sum(scale * h * h))
        size = math.sqrt(scale[0] * f * f + (scale[1] * k1 * k1 if fit_k1 else 0.0))
        if cost_new <= cost:
            drop = cost - cost_new
            f, k1, v, att = f_new, k1_new, v_new, turn @ att
            r, r_new = r_new, r
            jac, jac_new = jac_new, jac
            cost = cost_new
            rho = drop / predicted if predicted > 0 else 0.0
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            if drop <= FTOL * cost or step <= XTOL * (size + XTOL):
                return f, k1, att, r, jac, it
        else:
            lam *= 4.0
            if step <= XTOL * (size + XTOL):
                return f, k1, att, r, jac, it
    return f, k1, att, r, jac, MAX_ITER
