"""The HIL closed loop (docs/hil.md): dynamics propagated in real time stream their truth to the
device's attitude feed, and a flight-software loop reads the tracker's attitude over the serial
link and feeds it back as the controller's measurement.

* Dynamics thread (the caller's): every ``dt`` s of wall time, step the dynamics (``ground.sim.
  hil_dynamics``), send the truth sample stamped with its wall time (POSIX s) to the feed, and give
  the controller the flight loop's estimate.
* Flight loop thread: COMBINATION (GO 0x0B with a minimal section mask: return code, quaternion,
  epoch) back to back; an OK attitude, valid at the exposure mid-time ``epoch + exposure / 2``,
  becomes the estimate, carried forward with the gyro (the truth rate) to the present; statuses
  other than OK keep the previous estimate (the controller coasts on the gyro).

A scenario (``ground.hil.scenarios``, docs/hil.md "Scenarios") adds a moving target
(``target_at``: s since the start -> q, given to the dynamics every step) and an orbit
(``position_at``: s -> GCRS km, sent as each sample's ``r`` so the device sees the bodies from the
spacecraft); both are logged per step.

The loop runs ``duration_s`` and on until the flight loop has ``min_ok_updates`` OK answers (0:
no such wait), at most ``overrun_s`` past ``duration_s``; a test sets a count, so what it checks
does not depend on how many solves a loaded machine manages in the time. ``clock`` and ``sleep``
(``time.time``, ``time.sleep``) are the loop's: the device stamps GO with its own POSIX clock, so
only a device on the same clock can share a different one.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from firmware_model.reference_frames import matrix_to_quat, quat_to_matrix, rotation_angle
from ground.sim.attitude_feed import slerp
from ground.sim.feed_wire import Sample, Sender
from protocol import result

#: return code (0x0002), quaternion (0x0004), epoch (0x0010): 44 result bytes per update
MINIMAL_MASK = 0x0016
GO_CODE = 0x0B  #: ON | LOAD_NAND | COMMAND


@dataclass
class Update:
    """One COMBINATION of the flight loop: host times (POSIX s), the tracker's answer."""

    sent: float
    received: float
    status: str
    q: list[float] | None  #: the attitude, OK answers only
    t_mid: float | None  #: exposure mid-time (device clock = POSIX s), for every status


@dataclass
class HilLog:
    """What a closed-loop run recorded: truth every step and every flight-loop update."""

    dynamics: str
    q_target: list[float]
    truth_t: list[float] = field(default_factory=list)
    truth_q: list[list[float]] = field(default_factory=list)
    target_q: list[list[float]] = field(default_factory=list)  #: per step, when the target moves
    truth_r: list[list[float]] = field(default_factory=list)  #: GCRS km per step, when in orbit
    updates: list[Update] = field(default_factory=list)

    def ok_updates(self) -> int:
        """Updates that brought an OK attitude."""
        return sum(u.status == "OK" for u in list(self.updates))

    def _at(self, qs: list[list[float]], t: float) -> np.ndarray:
        k = int(np.clip(np.searchsorted(self.truth_t, t), 1, len(self.truth_t) - 1))
        t0, t1 = self.truth_t[k - 1], self.truth_t[k]
        f = float(np.clip((t - t0) / (t1 - t0), 0.0, 1.0))
        return slerp(np.array(qs[k - 1]), np.array(qs[k]), f)

    def truth_at(self, t: float) -> np.ndarray:
        """Truth quaternion at POSIX ``t`` (slerp between the logged steps)."""
        return self._at(self.truth_q, t)

    def target_at(self, t: float) -> np.ndarray:
        """Target quaternion at POSIX ``t`` (the fixed target, or slerp between the steps)."""
        return self._at(self.target_q, t) if self.target_q else np.asarray(self.q_target, dtype=float)

    def rows(self) -> list[dict]:
        """Per update: time since start, status; at the exposure mid-time the truth and its
        angle to the target (deg); for an OK answer also latency and measured vs truth (arcsec)."""
        t0 = self.truth_t[0]
        out = []
        for u in self.updates:
            row: dict = {"t": u.received - t0, "status": u.status, "sent": u.sent, "received": u.received}
            if u.t_mid is not None and u.t_mid > t0:
                a_true = quat_to_matrix(self.truth_at(u.t_mid))
                row |= {
                    "t_mid": u.t_mid - t0,
                    "q_truth": [float(v) for v in matrix_to_quat(a_true)],
                    "pointing_error_deg": math.degrees(rotation_angle(a_true, quat_to_matrix(self.target_at(u.t_mid)))),
                }
                if u.q is not None:
                    row |= {
                        "latency_s": u.received - u.t_mid,
                        "q_measured": u.q,
                        "measured_error_arcsec": math.degrees(rotation_angle(quat_to_matrix(u.q), a_true)) * 3600,
                    }
            out.append(row)
        return out


class Estimator:
    """The flight software's attitude: the last tracker attitude carried forward with the gyro."""

    def __init__(self, q0, w0, now: float):
        self._lock = threading.Lock()
        self.a = quat_to_matrix(q0)
        self.w = np.asarray(w0, dtype=float)
        self.t = now

    def propagate(self, w, now: float) -> tuple[np.ndarray, np.ndarray]:
        """Carry the estimate to ``now`` with gyro rate ``w``; returns (q, w)."""
        with self._lock:
            self.a = Rotation.from_rotvec(-np.asarray(w) * (now - self.t)).as_matrix() @ self.a
            self.w, self.t = np.asarray(w, dtype=float), now
            return matrix_to_quat(self.a), self.w

    def measured(self, q, t_mid: float) -> None:
        """A tracker attitude valid at ``t_mid``: carried to the estimate's time with the gyro."""
        with self._lock:
            self.a = Rotation.from_rotvec(-self.w * (self.t - t_mid)).as_matrix() @ quat_to_matrix(q)


def _parse(parts: dict[int, bytes]) -> tuple[str, list[float] | None, float | None]:
    """(status name, quaternion of an OK answer else None, epoch or None when not stamped)."""
    rc = struct.unpack("<I", parts[0x004])[0]
    status = result.status_of(rc)
    name = status.name if isinstance(status, result.Status) else f"status {status}"
    epoch = struct.unpack("<d", parts[0x040])[0]
    q = list(struct.unpack("<4d", parts[0x008])) if status == result.Status.OK else None
    return name, q, (epoch if epoch > 0 else None)


class FlightLoop(threading.Thread):
    """COMBINATIONs back to back on ``client`` until stopped, each answered within ``timeout`` s;
    OK attitudes go to ``estimator``; ``clock`` stamps each update's send and receipt."""

    def __init__(
        self,
        client,
        estimator: Estimator,
        log: HilLog,
        exposure_s: float,
        mask: int = MINIMAL_MASK,
        timeout: float = 5.0,
        clock: Callable[[], float] = time.time,
    ):
        super().__init__(name="flight-loop", daemon=True)
        self.client, self.estimator, self.log = client, estimator, log
        self.exposure_s, self.mask, self.timeout, self.clock = exposure_s, mask, timeout, clock
        self.stop = threading.Event()
        self.error: Exception | None = None

    def run(self) -> None:
        try:
            while not self.stop.is_set():
                sent = self.clock()
                parts = self.client.combination(GO_CODE, self.mask, timeout=self.timeout)
                received = self.clock()
                status, q, epoch = _parse(parts)
                t_mid = None if epoch is None else epoch + self.exposure_s / 2.0
                if q is not None and t_mid is not None:
                    self.estimator.measured(q, t_mid)
                self.log.updates.append(Update(sent, received, status, q, t_mid))
        except Exception as exc:  # noqa: BLE001 - reported by the caller after join
            self.error = exc


def run_closed_loop(
    dynamics,
    client,
    feed_url: str,
    q0,
    w0,
    q_target,
    duration_s: float,
    dt: float = 0.02,
    exposure_s: float = 0.1,
    mask: int = MINIMAL_MASK,
    progress: bool = True,
    min_ok_updates: int = 0,
    overrun_s: float = 10.0,
    combination_timeout: float = 5.0,
    clock: Callable[[], float] = time.time,
    sleep: Callable[[float], None] = time.sleep,
    target_at: Callable[[float], np.ndarray] | None = None,
    position_at: Callable[[float], np.ndarray] | None = None,
) -> HilLog:
    """Run the loop for ``duration_s`` of wall time and on until ``min_ok_updates`` OK answers,
    at most ``overrun_s`` more (module docstring); ``client`` is a connected
    ``ground.link.client.Client`` of a device serving ``--attitude-feed feed_url``; each
    COMBINATION is answered within ``combination_timeout`` s; ``target_at`` and ``position_at``
    (s since the start) a scenario's moving target and orbit."""
    log = HilLog(dynamics.label, [float(v) for v in q_target])

    def send(t: float, q, w) -> None:
        log.truth_t.append(t)
        log.truth_q.append([float(v) for v in q])
        if target_at is not None:
            target = target_at(t - start)
            dynamics.set_target(target)
            log.target_q.append([float(v) for v in target])
        if position_at is None:
            sender.send(Sample(t, q, w))
            return
        r = position_at(t - start)
        log.truth_r.append([float(v) for v in r])
        sender.send(Sample(t, q, w, r=r))  # the feed sample's r (docs/hil.md section 1)

    q, w = np.asarray(q0, dtype=float), np.asarray(w0, dtype=float)
    n = int(round(duration_s / dt))
    with Sender(feed_url) as sender:
        start = clock()
        estimator = Estimator(q0, w0, start)
        send(start, q, w)
        loop = FlightLoop(client, estimator, log, exposure_s, mask, combination_timeout, clock)
        loop.start()
        bar = tqdm(total=n, desc="closed loop", unit="step", disable=not progress)
        k = 0
        try:
            while loop.is_alive() and (k < n or clock() < start + duration_s + overrun_s):
                if k >= n and not loop.stop.is_set() and log.ok_updates() >= min_ok_updates:
                    loop.stop.set()  # the feed goes on until the last COMBINATION is answered
                k += 1
                t = start + k * dt
                sleep(max(0.0, t - clock()))
                dynamics.set_measurement(*estimator.propagate(w, t))  # gyro: the truth rate
                q, w = dynamics.step(dt)
                send(t, q, w)  # the target for the next step is set with this one's truth
                if k <= n:
                    bar.update()
        finally:
            bar.close()
            loop.stop.set()
            loop.join(timeout=combination_timeout + 10.0)
    if loop.error is not None:
        raise loop.error
    return log
