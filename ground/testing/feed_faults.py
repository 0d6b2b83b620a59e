"""Attitude-feed faults against ``st16-device --pty --attitude-feed tcp://...`` holding a catalog.

A simulator thread streams the true attitude in real time (JSON lines, every 20 ms, reconnecting
when its connection is taken over or closed). Each round injects one fault, then GOs until a
solve is OK: malformed lines (random bytes, 3 000 nested brackets, a 400-digit time, a line over
the length limit, NaN, an unnormalised quaternion), samples far in the future or the past, a
rate beyond the renderer's reach, a flood of 20 000 samples, a silent peer that takes the port
over, and a peer that connects and drops at once.

Failures: the device dies or prints a traceback (crashes, tracebacks), a PING goes unanswered
during the round (unanswered_pings), no OK solve within :data:`RECOVERY_S` s of the fault
(hangs; the flood of 20 000 samples has :data:`FLOOD_RECOVERY_S`, the device must first take
them all), an OK solve whose attitude is off the truth by more than :data:`MAX_ERROR_DEG`
(bad_replies). The recovery times are kept in ``notes`` as summary lines. Tests pass a generous
``recovery_s`` (a hang guard: timing is the bench's business, never a test's).
"""

from __future__ import annotations

import json
import random
import socket
import threading
import time
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from firmware_model.reference_frames import matrix_to_quat, quat_to_matrix, rotation_angle
from ground.link.client import Client, LinkError
from ground.link.solve_report import solve_record
from ground.sim.feed_wire import MAX_LINE, Sample, encode_json
from ground.testing.checks import ping_check, stderr_check
from ground.testing.device_proc import DeviceProcess
from ground.testing.tally import Tally

RECOVERY_S = 2.0  #: s: an OK solve must follow any single bad sample or bad peer within this long
FLOOD_RECOVERY_S = 5.0  #: s: the same after a flood of 20 000 samples
MAX_ERROR_DEG = 0.05  #: an OK attitude off the truth by more than this is a wrong answer
STEP_S = 0.02  #: the simulator's sample period
OMEGA = np.radians([0.3, -0.2, 0.5])  #: rad/s: a few pixels of smear in the 0.1 s exposure
GO_TIMEOUT_S = 10.0  #: a GO's result must come within this (a hang guard, not a figure)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Simulator(threading.Thread):
    """Streams ``truth(t)`` to the feed at ``port`` every :data:`STEP_S` s, stamped with the
    time sent; reconnects at once when its connection goes (a takeover, an idle close)."""

    def __init__(self, port: int, truth: Callable[[float], np.ndarray]):
        super().__init__(daemon=True, name="feed-simulator")
        self.port, self.truth = port, truth
        self.stop = threading.Event()
        self.reconnects = 0
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None

    def _connect(self) -> socket.socket:
        while not self.stop.is_set():
            try:
                return socket.create_connection(("127.0.0.1", self.port), timeout=1.0)
            except OSError:
                self.stop.wait(0.05)
        raise ConnectionError("stopped")

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                self.send(encode_json(Sample(time.time(), matrix_to_quat(self.truth(time.time())), OMEGA)))
            except (OSError, ConnectionError):
                pass
            self.stop.wait(STEP_S)

    def send(self, data: bytes) -> None:
        """Send ``data`` on the simulator's connection (reconnecting once if it has gone)."""
        with self._lock:
            for attempt in range(2):
                if self._sock is None:
                    self._sock = self._connect()
                    self.reconnects += attempt
                try:
                    self._sock.sendall(data)
                    return
                except OSError:
                    self._sock.close()
                    self._sock = None

    def close(self) -> None:
        self.stop.set()
        self.join(5.0)
        if self._sock is not None:
            self._sock.close()


def _line(obj) -> bytes:
    return json.dumps(obj).encode() + b"\n"


def _faults(sim: Simulator, rng: random.Random) -> dict[str, Callable[[], None]]:
    """Name -> inject one fault of that kind."""

    def sample(t: float, q=None, w=None) -> bytes:
        q = matrix_to_quat(sim.truth(time.time())) if q is None else q
        return _line({"t": t, "q": [float(v) for v in q], "w": [float(v) for v in (OMEGA if w is None else w)]})

    def peer(send: bytes | None, hold: float) -> None:
        with socket.create_connection(("127.0.0.1", sim.port), timeout=1.0) as s:
            if send:
                s.sendall(send)
            time.sleep(hold)

    return {
        "garbage": lambda: sim.send(rng.randbytes(rng.randrange(1, 3000)) + b"\n"),
        "nested": lambda: sim.send(b"[" * 3000 + b"\n"),
        "huge_time": lambda: sim.send(b'{"t": ' + b"9" * 400 + b', "q": [1,0,0,0], "w": [0,0,0]}\n'),
        "long_line": lambda: sim.send(b'{"t": 1' + b" " * (MAX_LINE + 10) + b"}\n"),
        "nan": lambda: sim.send(sample(time.time(), q=[float("nan"), 0, 0, 0])),
        "unnormalised": lambda: sim.send(sample(time.time(), q=2 * matrix_to_quat(sim.truth(time.time())))),
        "future": lambda: sim.send(sample(time.time() + 1e6)),
        "past": lambda: sim.send(sample(time.time() - 1e6)),
        "too_fast": lambda: sim.send(sample(time.time(), w=[0.0, 0.0, 100.0])),
        "flood": lambda: sim.send(b"".join(sample(time.time() - 5 + k * 1e-4) for k in range(20000))),
        "silent_peer": lambda: peer(None, 0.3),
        "drop_peer": lambda: peer(rng.randbytes(rng.randrange(0, 200)), 0.0),
    }


def _solve(client: Client) -> tuple[dict, float]:
    """GO and wait: the decoded result and its exposure's mid-time (``ext.utc_epoch``, POSIX s)."""
    raw = client.go_and_wait(timeout=GO_TIMEOUT_S)
    return solve_record(raw), float(raw["ext"]["utc_epoch"])


def _round(
    client: Client, device: DeviceProcess, sim: Simulator, name: str, inject, tally: Tally, bound: float
) -> float | None:
    """Inject one fault, then GO until OK (within ``bound`` s of the fault, else a failure);
    check the OK attitude and the link. The time to that OK solve, s (None: none came)."""
    tally.faults += 1
    t0 = time.monotonic()
    inject()
    tally.messages += 1
    while True:
        try:
            rec, epoch = _solve(client)
        except LinkError as exc:
            tally.fail("hangs", f"{name}: GO failed: {type(exc).__name__}: {exc}")
            return None
        tally.messages += 1
        took = time.monotonic() - t0
        if rec["status"] == "OK":
            break
        if took > bound + GO_TIMEOUT_S:
            tally.fail("hangs", f"{name}: no OK solve {took:.1f} s after the fault (last: {rec['reason']})")
            return None
    if took > bound:
        tally.fail("hangs", f"{name}: first OK solve {took:.2f} s after the fault (> {bound} s)")
    truth = sim.truth(epoch)  # the exposure's mid-time
    err = np.degrees(rotation_angle(quat_to_matrix(rec["q_icrs_to_sensor"]), truth))
    if err > MAX_ERROR_DEG:
        tally.fail("bad_replies", f"{name}: OK solve {err:.3f} deg off the truth")
    ping_check(client, tally, device)
    return took


def run(seed: int, rounds: int, recovery_s: float = RECOVERY_S, flood_recovery_s: float = FLOOD_RECOVERY_S) -> Tally:
    """``rounds`` faults (each kind once, then at random) against one device process; an OK
    solve must follow each within ``recovery_s`` s (a flood: ``flood_recovery_s``)."""
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_to_image
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.sim.device_process import pick_attitudes

    rng = random.Random(seed)
    tally, times = Tally(), {"single": list[float](), "flood": list[float]()}
    camera = CameraModel.reference_design()
    catalog = build_catalog(CatalogDesign())
    (a0,) = pick_attitudes(catalog, camera, 1, np.random.default_rng(seed))
    t_start = time.time()

    def truth(t: float) -> np.ndarray:
        return Rotation.from_rotvec(-OMEGA * (t - t_start)).as_matrix() @ a0

    port = _free_port()
    device = DeviceProcess("--pty", "--attitude-feed", f"tcp://127.0.0.1:{port}")
    sim = Simulator(port, truth)
    try:
        with Client(device.path, timeout=2.0) as client:
            client.init()
            client.upload(0, catalog_to_image(catalog), progress=False)
            sim.start()
            rec, _ = _solve(client)
            if rec["status"] != "OK":
                tally.fail("bad_replies", f"the clean feed does not solve: {rec['status']} {rec['reason']}")
            faults = _faults(sim, rng)
            names = sorted(faults)
            for k in range(rounds):
                name = names[k] if k < len(names) else rng.choice(names)
                kind = "flood" if name == "flood" else "single"
                bound = flood_recovery_s if kind == "flood" else recovery_s
                took = _round(client, device, sim, name, faults[name], tally, bound)
                if took is not None:
                    times[kind].append(took)
        if not device.alive:
            tally.fail("crashes", f"device exited {device.proc.returncode}")
    finally:
        sim.close()
        rc = device.stop()
        if rc != 0:
            tally.fail("crashes", f"device exit code {rc} at stop")
        stderr_check(device, tally)
    for kind, kept in times.items():
        if kept:
            t = np.array(kept)
            tally.notes.append(
                f"recovery to an OK solve after a {kind} fault: median {np.median(t):.2f} s, "
                f"p90 {np.percentile(t, 90):.2f} s, max {t.max():.2f} s over {t.size}"
            )
    tally.notes.append(f"simulator reconnects: {sim.reconnects}")
    return tally
