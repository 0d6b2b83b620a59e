"""The HIL closed loop (docs/hil.md): a dynamics simulation streams its truth to the device's
attitude feed, and a flight-software loop reads the tracker's answers over the serial link and
feeds its own estimate to the controller. Lockstep, in simulated time:

* The device runs with the feed's ``clock=sim`` (``ground.sim.feed_clock``): its time is the newest
  sample's, so nothing it reports depends on the machine's clock or load.
* Each step of ``dt`` simulated s: the flight software (``ground.sim.flight_estimator.Mekf`` on the gyro
  of ``ground.sim.gyro``) reads an answer that is due, starts a GO that is due, gives the
  controller its estimate (while lost: the target, so the controller only damps the gyro's rate),
  and the dynamics step; the truth sample goes to the feed. The truth is never given to the flight
  side: it is logged, and scored afterwards.
* A GO (0x0B) every ``go_period_s`` (0.5 s: the ICD's ~2 Hz cadence) is sent only once the device
  has taken the newest sample (TIME, read until it shows that sample's time), so the exposure
  starts at a known simulated time; its answer (return code, quaternion, epoch and the attitude
  covariance, read with READ RESULT) is used ``result_delay_s`` (0.5 s: exposure and processing)
  of simulated time later, the simulation waiting in real time for the device if it must. The
  answer's epoch, on the device clock, is mapped to simulated time by the first TIME reading.
* ``speed``: simulated seconds per real second (1: real time; 0: as fast as the device answers).
  The run's statuses, attitudes and time tags are the same at any speed (docs/hil.md "Lockstep").
* ``tracker_off_after`` (s): no GO after that much simulated time; the flight side coasts on the
  gyro (the control run: at 0 it never gets a fix).
* ``heads``: the tracker heads the flight side reads (:class:`Head`: address and mounting, the
  device serving ``--heads``); each GO cycle goes to every head, and the flight side's selection
  (:func:`prefer_last`: an OK head, the one it used last while it stays OK) picks the answer
  it uses, turned into the body's attitude and axes. Without heads: the client's one head, mounted
  at the identity.

A scenario (``ground.hil.scenarios``) adds a moving target (``target_at``: s since the start -> q)
and an orbit (``position_at``: s -> GCRS km, sent as each sample's ``r``); both are logged per step.
The loop runs ``duration_s`` and on until ``min_ok_updates`` OK answers (0: no such wait), at most
``overrun_s`` past ``duration_s``.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from firmware_model.reference_frames import matrix_to_quat, quat_to_matrix, rotation_angle
from ground.sim.attitude_feed import slerp
from ground.sim.feed_wire import Sample, Sender
from ground.sim.flight_estimator import Mekf, upper_in_body_axes
from ground.sim.gyro import DEFAULT, Gyro, GyroSpec
from protocol import result

GO_CODE = 0x0B  #: ON | LOAD_NAND | COMMAND
#: what the flight side reads of each result: return code, quaternion, omega, epoch; the covariance
READ_HEAD = (0x004, 0x048 - 0x004)
READ_COVARIANCE = (0x7E8 + 128, 48)  #: matching[0].attitude_covariance
MINIMAL_MASK = 0x0416  #: the same sections by COMBINATION (return code, quaternion, epoch, matching)
GO_PERIOD_S = 0.5
RESULT_DELAY_S = 0.5
WALL_GUARD_S = 60.0  #: real seconds the loop waits for the device at most (a hang guard)


@dataclass(frozen=True)
class Head:
    """A tracker head the flight side reads: its NSP address and mounting, the body-to-sensor
    matrix ``M`` (``v_sensor = M v_body``, docs/CONVENTIONS.md)."""

    address: int
    mount: np.ndarray


@dataclass
class Update:
    """One answer of the tracker: simulated times (POSIX s) of the GO and of its use, the answer,
    the exposure mid-time (its epoch mapped to simulated time), the device's epoch as reported, the
    attitude covariance, the real seconds from GO to the result ready, the head that answered
    and whether the flight side used this answer."""

    sent: float
    received: float
    status: str
    q: list[float] | None  #: the attitude, OK answers only (the head's sensor frame)
    t_mid: float | None  #: exposure mid-time (simulated POSIX s, mapped from the device clock), every status
    epoch: float | None = None  #: the result's epoch, device clock s
    cov: list[float] | None = None
    wall_latency_s: float | None = None
    address: int | None = None
    q_body: list[float] | None = None  #: the body's attitude by this answer (M.T A_sensor), OK answers only
    used: bool = False


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
    estimate_q: list[list[float] | None] = field(default_factory=list)  #: per step, None while lost
    first_fix_t: float | None = None  #: simulated POSIX s the estimator took its first attitude

    def ok_updates(self) -> int:
        """Updates whose OK attitude the flight side used."""
        return sum(u.used for u in list(self.updates))

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
            row |= {"epoch": u.epoch, "q": u.q, "address": u.address, "used": u.used}
            if u.t_mid is not None and u.t_mid > t0:
                a_true = quat_to_matrix(self.truth_at(u.t_mid))
                row |= {
                    "t_mid": u.t_mid - t0,
                    "q_truth": [float(v) for v in matrix_to_quat(a_true)],
                    "pointing_error_deg": math.degrees(rotation_angle(a_true, quat_to_matrix(self.target_at(u.t_mid)))),
                }
                if u.q_body is not None:
                    row |= {
                        "latency_s": u.received - u.t_mid,
                        "q_measured": u.q_body,
                        "measured_error_arcsec": math.degrees(rotation_angle(quat_to_matrix(u.q_body), a_true)) * 3600,
                    }
            out.append(row)
        return out


def prefer_last(answers: list[Update], last: int | None) -> Update | None:
    """The flight side's choice among one GO cycle's answers: an OK one, from the head it used
    last while that head stays OK, else the first OK head in the order the heads were given."""
    ok = [u for u in answers if u.q_body is not None]
    return next((u for u in ok if u.address == last), ok[0] if ok else None)


def _epoch_of(head: bytes) -> tuple[str, list[float] | None, float | None, np.ndarray | None]:
    """(status name, OK quaternion, epoch or None, omega) of the result head (READ_HEAD)."""
    rc = struct.unpack_from("<I", head, 0)[0]
    status = result.status_of(rc)
    name = status.name if isinstance(status, result.Status) else f"status {status}"
    q = list(struct.unpack_from("<4d", head, 4)) if status == result.Status.OK else None
    epoch = struct.unpack_from("<d", head, 0x040 - 0x004)[0]
    return name, q, (epoch if epoch > 0 else None), np.array(struct.unpack_from("<3d", head, 0x028 - 0x004))


class DeviceLink:
    """The flight side's use of the link in lockstep: TIME until the device has taken a sample, GO,
    and the result once ready. ``wall`` (real s) bounds every wait."""

    def __init__(self, client, wall: Callable[[], float] = time.monotonic, guard_s: float = WALL_GUARD_S):
        self.client, self.wall, self.guard_s = client, wall, guard_s

    def wait_device_time(self, at_least_s: float) -> float:
        """Read TIME until the device clock shows ``at_least_s`` (it has taken that sample); its s."""
        end = self.wall() + self.guard_s
        while True:
            now = self.client.time() / 1e6
            if now >= at_least_s - 2e-6:
                return now
            if self.wall() > end:
                raise TimeoutError(f"the device clock stayed at {now:.6f} s, short of {at_least_s:.6f} s")
            time.sleep(0.0005)

    def go(self) -> None:
        self.client.go(GO_CODE)

    def to(self, head: Head) -> DeviceLink:
        """Address ``head`` from now on (the heads share one line); this link."""
        self.client.device_address = head.address
        return self

    def answer(self) -> tuple[bytes, bytes]:
        """The result head and covariance, waiting for the sequence to finish."""
        end = self.wall() + self.guard_s
        while self.client.result_length() == 0:
            if self.wall() > end:
                raise TimeoutError(f"no result within {self.guard_s:g} s of GO")
            time.sleep(0.001)
        return self.client.read_result(*READ_HEAD), self.client.read_result(*READ_COVARIANCE)


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
    combination_timeout: float = WALL_GUARD_S,
    start_posix: float = 1_800_000_000.0,
    speed: float = 0.0,
    gyro_spec: GyroSpec = DEFAULT,
    gyro_seed: int = 0,
    tracker_off_after: float | None = None,
    go_period_s: float = GO_PERIOD_S,
    result_delay_s: float = RESULT_DELAY_S,
    wall: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    target_at: Callable[[float], np.ndarray] | None = None,
    position_at: Callable[[float], np.ndarray] | None = None,
    heads: Sequence[Head] | None = None,
) -> HilLog:
    """Run the lockstep loop of the module docstring from simulated POSIX ``start_posix``;
    ``client`` is a connected ``ground.link.client.Client`` of a device serving ``--attitude-feed
    feed_url`` with ``clock=sim`` (its clock epoch 0); ``combination_timeout`` real s bounds each
    wait for the device; ``mask`` is kept for the summary (the loop reads the same sections)."""
    del mask
    log = HilLog(dynamics.label, [float(v) for v in q_target])
    dev = DeviceLink(client, wall, combination_timeout)
    start = float(start_posix)

    def target(t: float) -> np.ndarray:
        return np.asarray(q_target if target_at is None else target_at(t - start), dtype=float)

    def send(t: float, q, w, logged: bool = True) -> None:
        r = None if position_at is None else np.asarray(position_at(t - start), dtype=float)
        sender.send(Sample(t, q, w, r=r))  # the feed sample's r (docs/hil.md section 1)
        if not logged:
            return
        log.truth_t.append(t)
        log.truth_q.append([float(v) for v in q])
        if target_at is not None:
            log.target_q.append([float(v) for v in target(t)])
        if r is not None:
            log.truth_r.append([float(v) for v in r])

    q, w = np.asarray(q0, dtype=float), np.asarray(w0, dtype=float)
    n = int(round(duration_s / dt))
    off_at = math.inf if tracker_off_after is None else start + tracker_off_after
    gyro = Gyro(gyro_spec, gyro_seed)
    est = Mekf(start, gyro_spec)
    heads = tuple(heads) if heads else (Head(client.device_address, np.eye(3)),)
    with Sender(feed_url) as sender:
        send(start - dt, q, w, logged=False)  # the device clocks count from this sample
        send(start, q, w)
        #: per head: simulated POSIX s = its device clock s + offset
        offset = {h.address: start - dev.to(h).wait_device_time(dt) for h in heads}
        wall0 = wall()
        pending: dict[int, tuple[float, float]] = {}  #: address -> (simulated GO time, real GO time)
        last_used: int | None = None
        next_go = start
        bar = tqdm(total=n, desc="closed loop", unit="step", disable=not progress)
        k = 0
        try:
            while True:
                t = start + k * dt
                if pending and t >= min(p[0] for p in pending.values()) + result_delay_s - 1e-9:
                    answers = [_answer(dev.to(h), h, pending[h.address], t, offset[h.address], wall) for h in heads]
                    log.updates.extend(answers)
                    chosen = prefer_last(answers, last_used)
                    if chosen is not None and chosen.q_body is not None and chosen.t_mid is not None:
                        head = next(h for h in heads if h.address == chosen.address)
                        est.update(
                            quat_to_matrix(chosen.q_body), chosen.t_mid, upper_in_body_axes(chosen.cov, head.mount)
                        )
                        chosen.used, last_used = True, chosen.address
                        if log.first_fix_t is None:
                            log.first_fix_t = t
                    pending = {}
                done = k >= n and (log.ok_updates() >= min_ok_updates or t >= start + duration_s + overrun_s)
                if done and not pending:
                    break
                if not pending and not done and t >= next_go - 1e-9 and t < off_at:
                    for h in heads:
                        dev.to(h).wait_device_time(t - offset[h.address])  # it has taken the sample at t
                        pending[h.address] = (t, wall())
                        dev.go()
                    next_go += go_period_s
                log.estimate_q.append(None if est.lost else [float(v) for v in matrix_to_quat(est.a)])
                q_ctl = target(t) if est.lost else matrix_to_quat(est.a)  # lost: damp the rate only
                dynamics.set_measurement(q_ctl, est.w)
                if target_at is not None:
                    dynamics.set_target(target(t))
                w_before = w
                q, w = dynamics.step(dt)
                est.propagate(gyro.measure(0.5 * (w_before + w), dt), t + dt)
                k += 1
                send(start + k * dt, q, w)
                if k <= n:
                    bar.update()
                if speed > 0:
                    sleep(max(0.0, wall0 + (k * dt) / speed - wall()))
        finally:
            bar.close()
    log.estimate_q.append(None if est.lost else [float(v) for v in matrix_to_quat(est.a)])
    return log


def _answer(dev: DeviceLink, head: Head, sent: tuple[float, float], t: float, offset: float, wall) -> Update:
    """``head``'s answer to the GO ``sent`` (simulated, real s), read at simulated ``t``."""
    result_head, cov_bytes = dev.answer()
    status, qm, epoch, _ = _epoch_of(result_head)
    q_body = None if qm is None else [float(v) for v in matrix_to_quat(head.mount.T @ quat_to_matrix(qm))]
    cov = list(struct.unpack("<6d", cov_bytes))
    t_mid = None if epoch is None else epoch + offset
    return Update(sent[0], t, status, qm, t_mid, epoch, cov, wall() - sent[1], head.address, q_body)
