"""Camera calibration from identified stars over several frames, or one (the device's per-solve
fit of one frame's focal length and k1 is ``frame_fit.fit_frame``, compiled).

Unknowns: the chosen camera parameters (``CameraModel`` fields: f, cx, cy, k1, k2, k3,
p1, p2) shared by all frames, plus one attitude per frame (a rotation vector applied to
an initial attitude from Wahba's problem with the starting camera). Residuals: measured
minus predicted pixel coordinates of each identified star (``camera.vector_to_pixel(A @
v_icrs)``), in pixels. Solved with ``scipy.optimize.least_squares`` (trust-region, sparse
finite-difference Jacobian: each frame's attitude touches only its own stars; for one frame the
analytic dense Jacobian, :func:`projection_jacobian`).

With a narrow field, the principal point is nearly degenerate with the per-frame
attitudes (a shift of (cx, cy) is almost a rotation); its uncertainty is reported and it
can be held fixed (``fit=`` without "cx", "cy").
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from firmware_model.camera import CameraModel
from firmware_model.ident.attitude import svd_attitude

DEFAULT_FIT = ("f", "cx", "cy", "k1", "k2", "p1", "p2")


@dataclass
class StarObservations:
    """One frame: measured pixel coordinates (x, y) of stars and their ICRS unit vectors (N, 3)."""

    x: np.ndarray
    y: np.ndarray
    v_icrs: np.ndarray

    def __post_init__(self):
        self.x = np.asarray(self.x, float).ravel()
        self.y = np.asarray(self.y, float).ravel()
        self.v_icrs = np.asarray(self.v_icrs, float).reshape(-1, 3)
        if not (len(self.x) == len(self.y) == len(self.v_icrs)):
            raise ValueError("x, y and v_icrs must have the same length")


@dataclass
class CalibrationResult:
    camera: CameraModel
    attitudes: list  # per-frame A (v_sensor = A @ v_icrs)
    residual_rms_px: float
    residuals: list  # per frame (N, 2) measured - predicted, px
    sigmas: dict  # 1-sigma uncertainty of each fitted camera parameter
    n_observations: int
    success: bool
    message: str
    #: per frame, the attitude covariance (rad^2, small rotations about the sensor axes) that the
    #: fitted camera parameters' uncertainty adds: the attitude's marginal covariance minus its
    #: covariance with the camera held (a Schur complement, positive semi-definite)
    camera_attitude_covariance: list = field(default_factory=list)


def _wahba(camera: CameraModel, obs: StarObservations) -> np.ndarray:
    return svd_attitude(camera.pixel_to_vector(obs.x, obs.y), obs.v_icrs)


def rotvec_matrix(r: np.ndarray) -> np.ndarray:
    """Rotation matrix of rotation vector ``r`` (rad; Rodrigues' formula, the small-angle series
    below 1e-8 rad): scipy's ``Rotation.from_rotvec`` without its per-call overhead, which
    dominated the fit's residual evaluations."""
    theta = float(np.sqrt(r @ r))
    k = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + k + 0.5 * (k @ k)
    return np.eye(3) + (np.sin(theta) / theta) * k + ((1.0 - np.cos(theta)) / theta**2) * (k @ k)


def projection_jacobian(cam: CameraModel, fit, v: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Jacobian (2N x (len(fit) + 3), rows x0, y0, x1, ...) of the pixel positions of sensor-frame
    directions ``v`` (N, 3) with respect to the camera parameters ``fit`` (px per unit of each) and
    the rotation vector ``theta`` (rad) of ``v = R(theta) v0``: ``dv/dtheta = -[v]x J_l(theta)``
    (``J_l`` the left Jacobian of SO(3)), through the pinhole ``u = v_x / v_z`` and the
    distortion of :meth:`CameraModel.distort`."""
    vz = v[:, 2]
    u, w = v[:, 0] / vz, v[:, 1] / vz
    r2 = u * u + w * w
    ud, wd = cam.distort(u, w)
    f = cam.f
    per_param = {
        "f": (ud, wd),
        "cx": (np.ones_like(u), np.zeros_like(u)),
        "cy": (np.zeros_like(u), np.ones_like(u)),
        "k1": (f * u * r2, f * w * r2),
        "k2": (f * u * r2**2, f * w * r2**2),
        "k3": (f * u * r2**3, f * w * r2**3),
        "p1": (f * 2.0 * u * w, f * (r2 + 2.0 * w * w)),
        "p2": (f * (r2 + 2.0 * u * u), f * 2.0 * u * w),
    }
    jac = np.zeros((2 * len(v), len(fit) + 3))
    for i, k in enumerate(fit):
        jac[0::2, i], jac[1::2, i] = per_param[k]
    j11, j12, j21, j22 = cam._distort_jacobian(u, w)
    zero = np.zeros_like(u)
    du = np.stack([1.0 / vz, zero, -u / vz], axis=1)  # d(u)/d(v)
    dw = np.stack([zero, 1.0 / vz, -w / vz], axis=1)
    dx = f * (j11[:, None] * du + j12[:, None] * dw)  # d(x)/d(v), (N, 3)
    dy = f * (j21[:, None] * du + j22[:, None] * dw)
    skew = np.zeros((len(v), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    dv = -skew @ _left_jacobian(theta)  # (N, 3, 3)
    jac[0::2, len(fit) :] = np.einsum("ni,nij->nj", dx, dv)
    jac[1::2, len(fit) :] = np.einsum("ni,nij->nj", dy, dv)
    return jac


def _left_jacobian(theta: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3) at rotation vector ``theta`` (rad): ``I + (1 - cos t) / t^2 K +
    (t - sin t) / t^3 K^2`` with ``K = [theta]x``, ``t = |theta|`` (series below 1e-6 rad)."""
    t = float(np.sqrt(theta @ theta))
    k = np.array([[0.0, -theta[2], theta[1]], [theta[2], 0.0, -theta[0]], [-theta[1], theta[0], 0.0]])
    if t < 1e-6:
        return np.eye(3) + 0.5 * k + (k @ k) / 6.0
    return np.eye(3) + ((1.0 - np.cos(t)) / t**2) * k + ((t - np.sin(t)) / t**3) * (k @ k)


def calibrate(frames: list[StarObservations], initial: CameraModel, fit=DEFAULT_FIT) -> CalibrationResult:
    """Fit camera parameters ``fit`` and per-frame attitudes to the observations."""
    fit = tuple(fit)
    unknown = set(fit) - {"f", "cx", "cy", "k1", "k2", "k3", "p1", "p2"}
    if unknown:
        raise ValueError(f"cannot fit {sorted(unknown)}")
    if not frames:
        raise ValueError("no frames to calibrate from")
    for i, fr in enumerate(frames):
        if len(fr.x) < 3:
            raise ValueError(f"frame {i} has {len(fr.x)} stars; at least 3 are needed")
    n_obs = sum(len(fr.x) for fr in frames)
    n_par = len(fit) + 3 * len(frames)
    if 2 * n_obs <= n_par:
        raise ValueError(f"{n_obs} stars give {2 * n_obs} residuals for {n_par} unknowns")
    a0 = [_wahba(initial, fr) for fr in frames]
    scale = np.array([initial.f if k == "f" else 1.0 for k in fit])  # f fitted relative to its start

    def unpack(p):
        vals = {k: (p[i] * scale[i]) for i, k in enumerate(fit)}
        cam = replace(initial, **vals)
        atts = [rotvec_matrix(p[len(fit) + 3 * j : len(fit) + 3 * j + 3]) @ a0[j] for j in range(len(frames))]
        return cam, atts

    def residuals(p):
        cam, atts = unpack(p)
        out = []
        for fr, a in zip(frames, atts):
            x, y = cam.vector_to_pixel(fr.v_icrs @ a.T)
            out.append(np.column_stack([x - fr.x, y - fr.y]).ravel())
        return np.concatenate(out)

    def jacobian(p):  # one frame (see below)
        cam, atts = unpack(p)
        return projection_jacobian(cam, fit, frames[0].v_icrs @ atts[0].T, p[len(fit) :]) * np.concatenate(
            [scale, np.ones(3)]
        )

    # one frame: every unknown touches every star, and the analytic dense Jacobian (exact
    # trust-region steps, no finite differences) is several times cheaper than the sparse
    # machinery for a handful of parameters
    sparsity = lil_matrix((2 * n_obs, n_par), dtype=int) if len(frames) > 1 else None
    if sparsity is not None:
        sparsity[:, : len(fit)] = 1
        row = 0
        for j, fr in enumerate(frames):
            sparsity[row : row + 2 * len(fr.x), len(fit) + 3 * j : len(fit) + 3 * j + 3] = 1
            row += 2 * len(fr.x)
    p0 = np.concatenate([[getattr(initial, k) / s for k, s in zip(fit, scale)], np.zeros(3 * len(frames))])
    res = least_squares(
        residuals,
        p0,
        jac=jacobian if sparsity is None else "2-point",
        jac_sparsity=sparsity,
        method="trf" if sparsity is not None else "lm",
        x_scale="jac",
        xtol=1e-8,
        ftol=1e-8,
        gtol=1e-10,
        max_nfev=200,
    )
    cam, atts = unpack(res.x)
    r = res.fun
    dof = max(len(r) - n_par, 1)
    s2 = float(r @ r) / dof
    jac = res.jac.toarray() if hasattr(res.jac, "toarray") else res.jac
    added = []
    try:
        info = jac.T @ jac
        cov = np.linalg.pinv(info) * s2
        sig = np.sqrt(np.maximum(np.diag(cov)[: len(fit)], 0.0)) * scale
        for j in range(len(frames)):
            rot = slice(len(fit) + 3 * j, len(fit) + 3 * j + 3)
            added.append(cov[rot, rot] - np.linalg.pinv(info[rot, rot]) * s2)
    except np.linalg.LinAlgError:
        sig = np.full(len(fit), np.nan)
        added = [np.full((3, 3), np.nan) for _ in frames]
    per_frame, row = [], 0
    for fr in frames:
        per_frame.append(-r[row : row + 2 * len(fr.x)].reshape(-1, 2))  # measured - predicted
        row += 2 * len(fr.x)
    return CalibrationResult(
        camera=cam,
        attitudes=atts,
        residual_rms_px=float(np.sqrt(np.mean(r.reshape(-1, 2) ** 2) * 2)),
        residuals=per_frame,
        sigmas=dict(zip(fit, (float(s) for s in sig))),
        n_observations=n_obs,
        success=bool(res.success),
        message=str(res.message),
        camera_attitude_covariance=added,
    )
