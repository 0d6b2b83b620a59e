"""Tracking: star identification and attitude from the last fix, predicted in small windows.

After a confident lost-in-space fix, a frame's stars are identified by predicting where the
catalog stars are, matching detections inside small windows around the predictions, and
updating the attitude and body rate with a constant-rate Kalman filter (docs/tracking.md).

Conventions (docs/CONVENTIONS.md): ``q`` is the scalar-first ``q_icrs_to_sensor`` with matrix
``A`` (``v_sensor = A v_icrs``); ``omega`` (rad/s, sensor axes) is the rate of the sensor frame
with respect to ICRS, so a sensor turning at a constant ``omega`` has ``A(t + dt) = R(-omega dt)
A(t)`` with ``R(v)`` the rotation by the rotation vector ``v`` (the kinematics of
``ground/sim/smear.py``). Times are seconds on any clock the caller keeps, the frame's
mid-exposure time (a smeared star's flux-weighted centroid is its mid-exposure position).

**Estimator.** Error state ``x = [theta, dw]`` (6): ``theta`` the small rotation (rad, sensor
axes) with ``A_true = R(theta) A``, ``dw`` the rate error (rad/s). Prediction over ``dt``:
``F = [[R(-omega dt), -dt I], [0, I]]``, ``P <- F P F^T + Q`` with the process noise of a white
angular acceleration of spectral density ``q_w`` (``TrackParams.rate_noise``, rad^2/s^3) and a
white attitude jitter ``q_a`` (``TrackParams.attitude_noise``, rad^2/s)::

    Q = q_w [[dt^3/3 I, -dt^2/2 I], [-dt^2/2 I, dt I]] + q_a [[dt I, 0], [0, 0]]

The measurement is the q-method attitude of the matched stars (``attitude.solve_attitude``, its
covariance ``R``): innovation ``z = rotvec(A_meas A_pred^T)``, ``H = [I 0]``, ``S = P_aa + R``;
the usual Kalman update (Joseph form). The rate is thus the filtered finite difference of
successive attitudes.

**Gates.** A catalog star predicted at ``p`` (px) takes the nearest free detection within
``gate_k * sqrt(sigma_pred^2 + sigma_meas^2)`` px, with ``sigma_pred`` the predicted attitude
uncertainty seen at that star (``f sqrt((tr P_aa - b^T P_aa b) / 2)``, as ``verify``'s gate) and
``sigma_meas`` the centroid noise and, in quadrature, ``smear_sigma_coeff L^2`` for a star whose
smear track over the exposure is ``L`` px long (``L = f |omega x b| t_exp``): the along-track
scatter of the extractor's centroids on smeared stars grows faster than the track
(``docs/tracking.md``). The matched stars are solved, stars beyond ``gate_k`` sigma of their own noise
dropped, and the stars matched again around the solved attitude. The update is refused (the
caller falls back to lost in space) when fewer than ``min_stars`` stars match, when the
normalised RMS residual exceeds ``max_normalised_rms``, or when the innovation's chi-square
``z^T S^-1 z`` exceeds ``innovation_chi2``: "disagrees with the prediction beyond its gate".
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.ident.attitude import quat_matrix, solve_attitude
from firmware_model.reference_frames import matrix_to_quat


@dataclass(frozen=True)
class TrackParams:
    """Tracking settings (defaults in brackets; module docstring for their roles).

    ``gate_k`` [5]: match window and residual gate in sigmas; ``min_stars`` [4]: matched stars
    needed for an update; ``max_normalised_rms`` [3]: largest RMS residual over the stars' own
    noise; ``innovation_chi2`` [30.7]: largest ``z^T S^-1 z`` (3 degrees of freedom, chance
    1e-6); ``centroid_sigma_px`` [0.25]: per-axis centroid noise when the caller gives none;
    ``smear_sigma_coeff`` [0.008 px^-1]: extra per-axis noise ``coeff L^2`` (px) for a smear track
    of ``L`` px;
    ``rate_noise`` [1e-7 rad^2/s^3]: angular-acceleration spectral density (1-sigma rate drift
    0.018 deg/s over 1 s); ``attitude_noise`` [1e-10 rad^2/s]: attitude jitter;
    ``initial_rate_sigma`` [0.0175 rad/s = 1 deg/s]: per-axis rate uncertainty after a
    lost-in-space fix (rate unknown, zero assumed); ``max_dt_s`` [2]: longest prediction;
    ``edge_margin_px`` [2]: predicted stars this close to the array edge are not looked for."""

    gate_k: float = 5.0
    min_stars: int = 4
    max_normalised_rms: float = 3.0
    innovation_chi2: float = 30.7
    centroid_sigma_px: float = 0.25
    smear_sigma_coeff: float = 0.008
    rate_noise: float = 1e-7
    attitude_noise: float = 1e-10
    initial_rate_sigma: float = np.radians(1.0)
    max_dt_s: float = 2.0
    edge_margin_px: float = 2.0


@dataclass(frozen=True)
class TrackState:
    """Attitude ``q`` (scalar-first ``q_icrs_to_sensor``), body rate ``omega`` (rad/s, sensor
    axes), the 6x6 covariance of ``[attitude error (rad, sensor axes), rate error (rad/s)]`` and
    the time ``t`` (s) they refer to."""

    q: np.ndarray
    omega: np.ndarray
    covariance: np.ndarray
    t: float

    @classmethod
    def from_fix(
        cls, q, attitude_covariance, t: float, params: TrackParams = TrackParams(), omega=(0.0, 0.0, 0.0)
    ) -> TrackState:
        """The state after a lost-in-space fix: its attitude and covariance (rad^2), a rate
        ``omega`` (default unknown: zero with ``params.initial_rate_sigma``)."""
        p = np.zeros((6, 6))
        p[:3, :3] = np.asarray(attitude_covariance, float)
        p[3:, 3:] = np.eye(3) * params.initial_rate_sigma**2
        return cls(np.asarray(q, float), np.asarray(omega, float), p, float(t))

    @property
    def attitude_covariance(self) -> np.ndarray:
        """3x3 (rad^2, sensor axes)."""
        return self.covariance[:3, :3]

    @property
    def rate_covariance(self) -> np.ndarray:
        """3x3 ((rad/s)^2, sensor axes)."""
        return self.covariance[3:, 3:]

    @property
    def rate_sigma(self) -> np.ndarray:
        """1-sigma of each rate component (rad/s)."""
        return np.sqrt(np.diag(self.rate_covariance))


class TrackStatus(StrEnum):
    OK = "ok"
    LOST = "lost"


@dataclass(frozen=True)
class TrackResult:
    """One tracking step: ``status``; ``reason`` (why lost, "" when ok); ``state`` (updated when
    ok, the prediction when lost); ``matched_det`` rows of the detections given, ``matched_cat``
    catalog indices, ``residuals`` (rad); ``innovation_chi2``; ``n_predicted`` catalog stars
    looked for."""

    status: TrackStatus
    reason: str
    state: TrackState
    matched_det: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    matched_cat: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    residuals: np.ndarray = field(default_factory=lambda: np.empty(0))
    innovation_chi2: float = float("nan")
    n_predicted: int = 0

    @property
    def ok(self) -> bool:
        return self.status is TrackStatus.OK


def predict(state: TrackState, t: float, params: TrackParams = TrackParams()) -> TrackState:
    """``state`` propagated to ``t`` (s) at its constant rate; covariance grown by the process
    noise (module docstring)."""
    dt = float(t) - state.t
    turn = Rotation.from_rotvec(-state.omega * dt).as_matrix()
    f = np.eye(6)
    f[:3, :3] = turn
    f[:3, 3:] = -dt * np.eye(3)
    adt = abs(dt)
    eye = np.eye(3)
    q = np.zeros((6, 6))
    q[:3, :3] = (params.rate_noise * adt**3 / 3 + params.attitude_noise * adt) * eye
    q[:3, 3:] = q[3:, :3] = -params.rate_noise * dt * adt / 2 * eye
    q[3:, 3:] = params.rate_noise * adt * eye
    p = f @ state.covariance @ f.T + q
    return TrackState(matrix_to_quat(turn @ quat_matrix(state.q)), state.omega.copy(), 0.5 * (p + p.T), float(t))


def _predicted_stars(a: np.ndarray, catalog: OnboardCatalog, camera: CameraModel, margin_px: float):
    """Catalog indices, sensor vectors and pixel positions of the stars ``a`` puts on the array."""
    idx = catalog.stars_within(a[2], camera.fov_half_angle_diagonal + 1e-3, deep=True)
    s = catalog.vec[idx] @ a.T
    x, y = camera.vector_to_pixel(s)
    on = np.isfinite(x) & camera.in_frame(x, y, margin=margin_px)
    return idx[on], s[on], np.column_stack([x[on], y[on]])


def _match(pred_px, gate_px, tree: cKDTree) -> tuple[np.ndarray, np.ndarray]:
    """(predicted rows, detection rows): each prediction's nearest detection within its gate,
    each detection given to the closest prediction that wants it."""
    if len(pred_px) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    dist, det = tree.query(pred_px, k=1, distance_upper_bound=float(np.max(gate_px)))
    ok = np.flatnonzero(dist <= gate_px)
    ok = ok[np.argsort(dist[ok], kind="stable")]
    _, first = np.unique(det[ok], return_index=True)
    keep = np.sort(ok[first])
    return keep, det[keep].astype(np.int64)


def _solve(b_det, cat_vec, sigma_rad, k: float):
    """q-method on the pairs, then again without stars beyond ``k`` sigma; (solution, kept rows)."""
    rows = np.arange(len(b_det))
    sol = solve_attitude(b_det, cat_vec, sigma_rad)
    keep = sol.residuals <= k * sigma_rad
    if not keep.all() and keep.sum() >= 2:
        rows = rows[keep]
        sol = solve_attitude(b_det[rows], cat_vec[rows], sigma_rad[rows])
    return sol, rows


def track(
    pixels,
    state: TrackState,
    t: float,
    catalog: OnboardCatalog,
    camera: CameraModel,
    params: TrackParams = TrackParams(),
    sigma_px=None,
    exposure_s: float = 0.0,
) -> TrackResult:
    """One tracking step on a frame's detections ``pixels`` ((N, 2): x = column, y = row, px) taken
    at mid-exposure time ``t`` (s) over ``exposure_s`` (s, for the smear term); ``sigma_px`` the
    per-axis centroid noise (px, scalar or per detection; default ``params.centroid_sigma_px``).
    Non-finite rows are ignored. Lost answers say why (module docstring)."""
    px = np.asarray(pixels, dtype=float)
    if px.ndim != 2 or px.shape[1] != 2:
        raise ValueError(f"pixels must have shape (N, 2), got {px.shape}")
    sig = np.asarray(params.centroid_sigma_px if sigma_px is None else sigma_px, float)
    if sig.shape not in ((), (len(px),)) or not np.all(sig > 0):
        raise ValueError(
            f"sigma_px must be positive, one number or one per detection ({len(px)}), got shape {sig.shape}"
        )
    sig_det = np.broadcast_to(sig, len(px))
    dt = float(t) - state.t
    pred = predict(state, t, params)
    if not 0.0 <= dt <= params.max_dt_s:
        return TrackResult(TrackStatus.LOST, f"prediction over {dt:.3f} s outside 0..{params.max_dt_s} s", pred)
    finite = np.flatnonzero(np.isfinite(px).all(axis=1))
    a_pred = quat_matrix(pred.q)
    cat, s_pred, p_pred = _predicted_stars(a_pred, catalog, camera, params.edge_margin_px)
    n_pred = len(cat)

    def lost(why: str, chi2: float = float("nan")) -> TrackResult:
        return TrackResult(TrackStatus.LOST, why, pred, innovation_chi2=chi2, n_predicted=n_pred)

    if len(finite) < params.min_stars or n_pred < params.min_stars:
        return lost(f"too few stars to track: {len(finite)} detections, {n_pred} catalog stars predicted")
    tree = cKDTree(px[finite])
    smear = (
        params.smear_sigma_coeff * (camera.f * exposure_s * np.linalg.norm(np.cross(pred.omega, s_pred), axis=1)) ** 2
    )
    b_all = camera.pixel_to_vector(px[finite, 0], px[finite, 1])
    sig_gate = float(np.median(sig_det[finite]))  # a window's centroid noise, before it knows its detection

    def meas_px(rows: np.ndarray, det: np.ndarray) -> np.ndarray:
        """Per-axis noise (px) of detections ``det`` matched to predicted stars ``rows``: centroid and smear."""
        return np.sqrt(sig_det[finite[det]] ** 2 + smear[rows] ** 2)

    def attempt(p_att: np.ndarray, s: np.ndarray, p: np.ndarray):
        """Match in windows around ``p`` (px) of stars ``s`` with attitude covariance ``p_att`` and solve."""
        spread = camera.f * np.sqrt(np.clip((np.trace(p_att) - np.einsum("ij,jk,ik->i", s, p_att, s)) / 2, 0, None))
        rows, det = _match(p, params.gate_k * np.sqrt(spread**2 + sig_gate**2 + smear**2), tree)
        if len(rows) < max(params.min_stars, 2):
            return None, rows, det
        sol, kept = _solve(b_all[det], catalog.vec[cat[rows]], meas_px(rows, det) / camera.f, params.gate_k)
        return sol, rows[kept], det[kept]

    sol, rows, det = attempt(pred.attitude_covariance, s_pred, p_pred)
    if sol is not None:  # again around the solved attitude: tight windows, every predicted star
        s_sol = catalog.vec[cat] @ sol.a.T
        x, y = camera.vector_to_pixel(s_sol)
        sol2, rows2, det2 = attempt(sol.covariance, s_sol, np.column_stack([x, y]))
        if sol2 is not None:
            sol, rows, det = sol2, rows2, det2
    if sol is None or len(rows) < params.min_stars:
        return lost(f"too few matched stars: {len(rows)} of {n_pred} predicted (need {params.min_stars})")
    meas_rad = meas_px(rows, det) / camera.f
    nrms = float(np.sqrt(np.mean((sol.residuals / meas_rad) ** 2)))
    if nrms > params.max_normalised_rms:
        return lost(f"residuals beyond the gate: normalised RMS {nrms:.2f} > {params.max_normalised_rms}")
    z = Rotation.from_matrix(sol.a @ a_pred.T).as_rotvec()
    s_inn = pred.attitude_covariance + sol.covariance
    chi2 = float(z @ np.linalg.solve(s_inn, z))
    if not chi2 <= params.innovation_chi2:
        return lost(
            f"disagrees with the prediction beyond its gate: innovation chi2 {chi2:.1f} > {params.innovation_chi2}"
            f" ({np.degrees(np.linalg.norm(z)) * 3600:.1f} arcsec)",
            chi2,
        )
    state = _update(pred, z, sol.covariance)
    return TrackResult(TrackStatus.OK, "", state, finite[det], cat[rows], sol.residuals, chi2, n_pred)


def _update(pred: TrackState, z: np.ndarray, r: np.ndarray) -> TrackState:
    """Kalman update of ``pred`` with the attitude innovation ``z`` (rad) of covariance ``r``."""
    p = pred.covariance
    h = np.zeros((3, 6))
    h[:, :3] = np.eye(3)
    gain = np.linalg.solve(p[:3, :3] + r, p[:3, :]).T  # P H^T S^-1 (S symmetric)
    dx = gain @ z
    ikh = np.eye(6) - gain @ h
    p_new = ikh @ p @ ikh.T + gain @ r @ gain.T
    a = Rotation.from_rotvec(dx[:3]).as_matrix() @ quat_matrix(pred.q)
    return replace(pred, q=matrix_to_quat(a), omega=pred.omega + dx[3:], covariance=0.5 * (p_new + p_new.T))


__all__ = ["TrackParams", "TrackResult", "TrackState", "TrackStatus", "predict", "track"]
