"""The flight side's attitude estimator (docs/hil.md "The flight side"): a multiplicative extended
Kalman filter (Lefferts, Markley and Shuster 1982; Markley and Crassidis 2014, section 6.2) on
the gyro of ``ground.sim.gyro``, updated with the tracker's answers and their reported covariance.

* **Lost at start.** Until the first OK answer the estimator has no attitude (``lost``): it still
  integrates the gyro from an arbitrary attitude, which gives the relative rotation between any two
  times. The first answer, valid at its exposure mid-time, is carried to the present by that
  relative rotation and becomes the estimate; its covariance the attitude block of P, the gyro's
  turn-on bias sigma the bias block.
* **Propagation** with the gyro's rate less the estimated bias: ``A <- exp(-[w dt x]) A``
  (``v_body = A v_icrs``, docs/CONVENTIONS.md); the error state ``e`` (rad, body axes, ``A_true =
  exp([e x]) A``) and the bias error ``db`` obey ``e' = -w x e + db + n_arw``, ``db' = n_rrw``.
* **Update** with an answer valid at ``t_mid`` (in the past: the answer comes after the exposure):
  the innovation is taken against the estimate at ``t_mid`` (kept per step), rotated to the
  present by the estimate's own rotation since, and applied to the present estimate (the delay is
  a few tenths of a second: the error rotated, the covariance not re-propagated; our
  simplification). ``R`` is the answer's ``attitude_covariance`` (rad^2, sensor axes; a head mounted
  at ``M`` gives ``M.T R M`` in the body's, :func:`upper_in_body_axes`); an answer without one (all zero) is given :data:`FALLBACK_SIGMA_RAD`.
"""

from __future__ import annotations

import bisect
import math

import numpy as np
from scipy.spatial.transform import Rotation

from ground.sim.gyro import DEG_PER_H, GyroSpec

FALLBACK_SIGMA_RAD = math.radians(20.0 / 3600.0)  #: an answer without a covariance: 20 arcsec, our assumption
HISTORY_S = 5.0  #: how far back an answer's mid-time may lie


def rotvec_of(a: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of the rotation matrix ``a`` (``exp([v x]) = a``)."""
    return Rotation.from_matrix(a).as_rotvec()


def exp_rot(v) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(v, dtype=float)).as_matrix()


def covariance_from_upper(six) -> np.ndarray:
    """3x3 covariance from the result's upper triangle, row by row (xx, xy, xz, yy, yz, zz)."""
    xx, xy, xz, yy, yz, zz = (float(v) for v in six)
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


def upper_in_body_axes(six, mount: np.ndarray) -> list[float]:
    """A head's attitude covariance (the result's six numbers, sensor axes) in the body's axes,
    ``mount`` the head's body-to-sensor matrix: ``P_body = M.T P M`` (the error ``e_body = M.T e``)."""
    p = mount.T @ covariance_from_upper(six) @ mount
    return [float(p[i, j]) for i in range(3) for j in range(i, 3)]


class Mekf:
    """The estimator of the module docstring: ``t`` s (the flight software's time), ``spec`` the
    gyro class it was told (its noise), ``lost`` until the first answer."""

    def __init__(self, t: float, spec: GyroSpec):
        self.spec = spec
        self.t = t
        self.a = np.eye(3)  #: lost: an arbitrary attitude integrated with the gyro
        self.b = np.zeros(3)
        self.w = np.zeros(3)  #: the last bias-corrected rate
        self.p = np.zeros((6, 6))
        self.lost = True
        self.fixes = 0
        self._hist_t: list[float] = [t]
        self._hist_a: list[np.ndarray] = [self.a.copy()]

    def propagate(self, w_meas, t: float) -> None:
        """Carry the estimate to ``t`` with the gyro's mean rate ``w_meas`` over the step."""
        dt = t - self.t
        if dt <= 0:
            return
        w = np.asarray(w_meas, dtype=float) - self.b
        self.a = exp_rot(-w * dt) @ self.a
        self.w = w
        if not self.lost:
            f = np.zeros((6, 6))
            f[:3, :3] = -np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
            f[:3, 3:] = np.eye(3)
            phi = np.eye(6) + f * dt
            q = np.zeros((6, 6))
            q[:3, :3] = np.eye(3) * self.spec.arw**2 * dt
            q[3:, 3:] = np.eye(3) * self.spec.rrw**2 * dt
            self.p = phi @ self.p @ phi.T + q
        self.t = t
        self._hist_t.append(t)
        self._hist_a.append(self.a.copy())
        while self._hist_t[0] < t - HISTORY_S:
            del self._hist_t[0], self._hist_a[0]

    def _at(self, t: float) -> np.ndarray:
        """The estimate (or the lost integration) at ``t`` inside the history, between steps by the
        rotation's geodesic."""
        k = bisect.bisect_left(self._hist_t, t)
        if k <= 0:
            return self._hist_a[0]
        if k >= len(self._hist_t):
            return self._hist_a[-1]
        t0, t1 = self._hist_t[k - 1], self._hist_t[k]
        a0, a1 = self._hist_a[k - 1], self._hist_a[k]
        f = (t - t0) / (t1 - t0)
        return exp_rot(f * rotvec_of(a1 @ a0.T)) @ a0

    def update(self, a_meas: np.ndarray, t_mid: float, cov6) -> float:
        """An answer: the attitude matrix ``a_meas`` valid at ``t_mid`` with its covariance (the
        result's six numbers). Returns the innovation's size (rad; 0 for the first fix)."""
        r = covariance_from_upper(cov6)
        if not (np.all(np.isfinite(r)) and np.all(np.linalg.eigvalsh(r) > 0)):
            r = np.eye(3) * FALLBACK_SIGMA_RAD**2
        then = self._at(t_mid)
        since = self.a @ then.T  #: the body's rotation from t_mid to now, by the gyro
        if self.lost:
            self.a = since @ a_meas
            self.p = np.zeros((6, 6))
            self.p[:3, :3] = since @ r @ since.T
            self.p[3:, 3:] = np.eye(3) * (self.spec.bias_deg_h * DEG_PER_H) ** 2
            self.lost = False
            self.fixes = 1
            self._hist_t, self._hist_a = [self.t], [self.a.copy()]  # the lost integration is dropped
            return 0.0
        y = since @ rotvec_of(a_meas @ then.T)
        r_now = since @ r @ since.T
        h = np.hstack([np.eye(3), np.zeros((3, 3))])
        s = h @ self.p @ h.T + r_now
        k = self.p @ h.T @ np.linalg.inv(s)
        dx = k @ y
        self.a = exp_rot(dx[:3]) @ self.a
        self.b = self.b + dx[3:]
        ikh = np.eye(6) - k @ h
        self.p = ikh @ self.p @ ikh.T + k @ r_now @ k.T
        self.fixes += 1
        return float(np.linalg.norm(y))

    def sigma_deg(self) -> float:
        """1-sigma attitude uncertainty (deg, root of the trace's mean); inf while lost."""
        return math.inf if self.lost else math.degrees(math.sqrt(max(np.trace(self.p[:3, :3]) / 3.0, 0.0)))
