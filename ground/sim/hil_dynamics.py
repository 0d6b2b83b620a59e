"""Attitude dynamics of the HIL closed loop (``st16-ground hil demo``, docs/hil.md): a rigid
spacecraft whose body frame is the tracker's sensor frame, held at a target attitude by an MRP
feedback controller that sees the attitude the flight loop measures.

Two back-ends with one interface (``set_measurement(q, w)``, ``set_target(q)`` (a target that
moves: the scenarios' slews, docs/hil.md "Scenarios"; held between calls, no rate fed forward),
``step(dt) -> (q, w)`` truth, ``label``); quaternions scalar-first ``q_icrs_to_body``, rates rad/s in body axes:

* :class:`BasiliskDynamics`: Basilisk (``bsk``, the ``[hil]`` extra): ``spacecraft.Spacecraft``
  with an ``extForceTorque`` effector commanded by ``mrpFeedback`` through ``attTrackingError``
  against an ``inertial3D`` reference; the measurement enters as the ``NavAttMsg`` the tracking
  error reads.
* :class:`StandInDynamics`: **not Basilisk**, a small numpy stand-in: Euler's equations (RK4)
  with the same control law, for machines without ``bsk``.

Control law (both): ``L = -K sigma_BR - P omega_BR + omega x (I omega)`` (mrpFeedback without
the integral term); gains from a natural frequency and damping about each axis.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from firmware_model.reference_frames import matrix_to_quat, quat_to_matrix


def quat_to_mrp(q) -> np.ndarray:
    """Basilisk's MRP ``sigma_BN`` (|sigma| <= 1) of our ``q_icrs_to_body``: the Euler parameters
    of Basilisk's DCM ``C_BN`` (Schaub) are the conjugate of our quaternion of the same matrix."""
    q = np.asarray(q, dtype=float)
    q = q if q[0] >= 0 else -q
    return -q[1:] / (1.0 + q[0])


def mrp_to_quat(s) -> np.ndarray:
    """Our scalar-first ``q_icrs_to_body`` (w >= 0) of Basilisk's ``sigma_BN``."""
    s = np.asarray(s, dtype=float)
    n2 = float(s @ s)
    q = np.concatenate([[1.0 - n2], -2.0 * s]) / (1.0 + n2)
    return q if q[0] >= 0 else -q


def gains(inertia: np.ndarray, omega_n: float, zeta: float) -> tuple[float, float]:
    """(K, P) for natural frequency ``omega_n`` (rad/s) and damping ``zeta`` about the largest
    axis (small angles: sigma ~ theta / 4, so I theta'' + P theta' + K theta / 4 = 0)."""
    i_max = float(np.max(np.diag(inertia)))
    return 4.0 * i_max * omega_n**2, 2.0 * zeta * i_max * omega_n


class StandInDynamics:
    """Rigid body + MRP feedback in numpy: a stand-in for Basilisk (module docstring)."""

    label = "numpy rigid-body stand-in (NOT Basilisk)"

    def __init__(self, inertia, q0, w0, q_target, k: float, p: float):
        self.inertia = np.asarray(inertia, dtype=float)
        self.a = quat_to_matrix(q0)
        self.w = np.asarray(w0, dtype=float)
        self.a_target = quat_to_matrix(q_target)
        self.k, self.p = k, p
        self._meas = (matrix_to_quat(self.a), self.w.copy())

    def set_measurement(self, q, w) -> None:
        self._meas = (np.asarray(q, dtype=float), np.asarray(w, dtype=float))

    def set_target(self, q) -> None:
        self.a_target = quat_to_matrix(q)

    def torque(self) -> np.ndarray:
        q, w = self._meas
        sigma = quat_to_mrp(matrix_to_quat(quat_to_matrix(q) @ self.a_target.T))
        return -self.k * sigma - self.p * w + np.cross(w, self.inertia @ w)

    def step(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        u, i_inv = self.torque(), np.linalg.inv(self.inertia)

        def wdot(w):
            return i_inv @ (u - np.cross(w, self.inertia @ w))

        w0 = self.w
        k1 = wdot(w0)
        k2 = wdot(w0 + 0.5 * dt * k1)
        k3 = wdot(w0 + 0.5 * dt * k2)
        k4 = wdot(w0 + dt * k3)
        self.w = w0 + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        self.a = Rotation.from_rotvec(-0.5 * (w0 + self.w) * dt).as_matrix() @ self.a  # dA/dt = -[w x] A
        return matrix_to_quat(self.a), self.w.copy()


class BasiliskDynamics:
    """Basilisk spacecraft + attTrackingError + mrpFeedback + extForceTorque (module docstring)."""

    label = "Basilisk (bsk): Spacecraft, extForceTorque, inertial3D, attTrackingError, mrpFeedback"

    def __init__(self, inertia, q0, w0, q_target, k: float, p: float, dt: float):
        from Basilisk.architecture import messaging
        from Basilisk.fswAlgorithms import attTrackingError, inertial3D, mrpFeedback
        from Basilisk.simulation import extForceTorque, spacecraft
        from Basilisk.utilities import SimulationBaseClass, macros

        self._messaging, self._macros = messaging, macros
        self.sim = SimulationBaseClass.SimBaseClass()
        self.sim.CreateNewProcess("hil").addTask(self.sim.CreateNewTask("step", macros.sec2nano(dt)))
        sc = spacecraft.Spacecraft()
        sc.ModelTag = "st16-host"
        sc.hub.mHub = 100.0
        sc.hub.IHubPntBc_B = np.asarray(inertia, dtype=float).tolist()
        sc.hub.sigma_BNInit = [[v] for v in quat_to_mrp(q0)]
        sc.hub.omega_BN_BInit = [[float(v)] for v in w0]
        ext = extForceTorque.ExtForceTorque()
        ext.ModelTag = "torquer"
        sc.addDynamicEffector(ext)
        ref = inertial3D.inertial3D()
        ref.ModelTag = "target"
        ref.sigma_R0N = quat_to_mrp(q_target).tolist()
        err = attTrackingError.attTrackingError()
        err.ModelTag = "tracking-error"
        self.nav = messaging.NavAttMsg()
        err.attNavInMsg.subscribeTo(self.nav)
        err.attRefInMsg.subscribeTo(ref.attRefOutMsg)
        ctl = mrpFeedback.mrpFeedback()
        ctl.ModelTag = "mrp-feedback"
        ctl.K, ctl.P, ctl.Ki = k, p, -1.0  # Ki < 0: no integral term
        config = messaging.VehicleConfigMsgPayload()
        config.ISCPntB_B = np.asarray(inertia, dtype=float).ravel().tolist()
        self._config = messaging.VehicleConfigMsg().write(config)
        ctl.guidInMsg.subscribeTo(err.attGuidOutMsg)
        ctl.vehConfigInMsg.subscribeTo(self._config)
        ext.cmdTorqueInMsg.subscribeTo(ctl.cmdTorqueOutMsg)
        for model in (ref, err, ctl, ext, sc):  # flight software first, then the dynamics it commands
            self.sim.AddModelToTask("step", model)
        self.sc, self._ref, self._models = sc, ref, (err, ctl, ext)
        self.t = 0.0
        self.set_measurement(q0, w0)
        self.sim.InitializeSimulation()

    def set_measurement(self, q, w) -> None:
        nav = self._messaging.NavAttMsgPayload()
        nav.sigma_BN = quat_to_mrp(q).tolist()
        nav.omega_BN_B = [float(v) for v in w]
        self.nav.write(nav, self._macros.sec2nano(self.t))

    def set_target(self, q) -> None:
        self._ref.sigma_R0N = quat_to_mrp(q).tolist()

    def step(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        self.t += dt
        self.sim.ConfigureStopTime(self._macros.sec2nano(self.t))
        self.sim.ExecuteSimulation()
        state = self.sc.scStateOutMsg.read()
        return mrp_to_quat(np.asarray(state.sigma_BN, dtype=float)), np.asarray(state.omega_BN_B, dtype=float)
