"""NASA 42 as the attitude feed's dynamics simulator: ``st16-device --attitude-feed
42://HOST:PORT[?mount=W,X,Y,Z&speed=S&position=on|off]`` (docs/hil.md "NASA 42").

42 (github.com/ericstoneking/42; built from ``../shared/tools/nasa42``) serves its state over an
IPC socket in TX mode, server role (``Source/AutoCode/TxRxIPC.c``, ``WriteToSocket``): per
simulation step one message of text lines, ``TIME YYYY-DOY-HH:MM:SS.sssssssss`` (UTC, day of year)
first and ``[ENDMSG]`` last, ``NAME = [v v v]`` between, then it waits for 4 bytes (``Ack`` and a
NUL) before it goes on. The device connects as the client (:class:`Reader`, a thread; it retries
until 42 listens), and per message:

* takes ``SC[0].B[0].qn = [q1 q2 q3 q4]`` (body 0 with respect to 42's N, the J2000 equator:
  ICRS here; **scalar last**). 42's ``Q2C`` (``Kit/Source/dcmkit.c``) makes of it the matrix
  taking N components to body components, which is our ``quat_to_matrix`` of the **conjugate**,
  scalar first: ours is ``[q4, -q1, -q2, -q3]`` (:func:`body_quaternion`; ``[q4, q1, q2, q3]``
  gives the transpose, as ``tests/test_nasa42.py`` shows against ``Q2C`` transcribed; Basilisk's
  Euler parameters are likewise our conjugate, docs/hil.md section 1);
  ``SC[0].B[0].wn`` (rad/s, body axes) and, with ``position=on`` (the default),
  ``Orb[0].PosN + SC[0].PosR`` (m, N) as the sample's GCRS position, so the device's bright-body
  check sees 42's orbit;
* turns body into sensor by the mounting ``mount`` (``q_body_to_sensor``, scalar first, unit:
  ``v_sensor = quat_to_matrix(mount) v_body``, docs/CONVENTIONS.md; default the identity):
  ``A_sensor = M A_body``, ``w_sensor = M w_body``;
* offers one sample, stamped with 42's TIME (POSIX s), to the feed (its checks apply), only once
  the whole message has come: never an attitude from half a message;
* acknowledges. ``speed`` (simulated s per real s, default 1: real time; 0: at once) holds the
  acknowledgement back so that 42's time keeps pace; 42 in FAST mode is then in lockstep with the
  device, and in REAL mode paces itself (keep ``speed=0`` there).

The device's clocks follow 42's TIME (``ground.sim.feed_clock``). Faults, each counted once and
the device serving on: a line that does not parse (the message is dropped, still acknowledged), a
message without the lines it needs or over :data:`MAX_MESSAGE` bytes, a socket that closes (inside
a message or not): the reader reconnects.
"""

from __future__ import annotations

import math
import re
import shutil
import socket
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from firmware_model.reference_frames import matrix_to_quat, quat_to_matrix
from ground.sim.feed_wire import Sample

ACK = b"Ack\x00"
END = "[ENDMSG]"
MAX_MESSAGE = 1 << 20  #: bytes; 42 writes at most 16 kB a message
RETRY_S = 0.2  #: between attempts to connect
MOUNT_TOL = 1e-6  #: | |mount| - 1 | above this is not a unit quaternion
_TIME = re.compile(r"^TIME (\d{4})-(\d{3})-(\d{2}):(\d{2}):(\d+(?:\.\d*)?)$")
_VALUE = re.compile(r"^([A-Za-z_][\w\[\]\.]*) = \[([^\]]*)\]$")
NEEDED = ("SC[0].B[0].qn", "SC[0].B[0].wn")


class MalformedMessage(ValueError):
    """A 42 message that does not give an attitude."""


def parse_time(text: str) -> float:
    """POSIX s of 42's line ``TIME YYYY-DOY-HH:MM:SS.sss`` (UTC)."""
    m = _TIME.match(text)
    if not m:
        raise MalformedMessage(f"not a 42 TIME line: {text[:80]!r}")
    year, doy, hour, minute = (int(v) for v in m.groups()[:4])
    second = float(m.group(5))
    if not (1 <= doy <= 366 and hour < 24 and minute < 60 and second < 61):
        raise MalformedMessage(f"42 TIME out of range: {text[:80]!r}")
    day = datetime(year, 1, 1, tzinfo=UTC) + timedelta(days=doy - 1, hours=hour, minutes=minute)
    return day.timestamp() + second


def body_quaternion(qn_scalar_last) -> np.ndarray:
    """Our scalar-first ``q_icrs_to_body`` of 42's ``qn`` (scalar last): the conjugate, reordered,
    so that ``quat_to_matrix`` gives 42's ``Q2C`` matrix (module docstring)."""
    q = np.asarray(qn_scalar_last, dtype=float)
    return np.array([q[3], -q[0], -q[1], -q[2]])


def parse_message(lines: list[str]) -> dict[str, object]:
    """{"t": POSIX s, NAME: np.ndarray, ...} of one message's lines (without ``[ENDMSG]``);
    MalformedMessage for a line that is neither TIME nor ``NAME = [numbers]``, or no TIME."""
    out: dict[str, object] = {}
    for line in lines:
        line = line.strip()
        if not line:
            continue
        if line.startswith("TIME"):
            out["t"] = parse_time(line)
            continue
        m = _VALUE.match(line)
        if not m:
            raise MalformedMessage(f"not a 42 line: {line[:80]!r}")
        try:
            values = np.array([float(v) for v in m.group(2).split()])
        except ValueError:
            raise MalformedMessage(f"not numbers: {line[:80]!r}") from None
        out[m.group(1)] = values
    if "t" not in out:
        raise MalformedMessage("a 42 message without its TIME line")
    return out


def parse_mount(text: str) -> np.ndarray:
    """``W,X,Y,Z`` -> a unit ``q_body_to_sensor``; ValueError (one line) otherwise."""
    try:
        q = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise ValueError(f"mount={text[:60]!r}: four numbers W,X,Y,Z (q_body_to_sensor, scalar first)") from None
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise ValueError(f"mount={text[:60]!r}: four finite numbers W,X,Y,Z (q_body_to_sensor, scalar first)")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > MOUNT_TOL:
        raise ValueError(f"mount={text[:60]!r}: not a unit quaternion (norm {norm:.9g})")
    return q / norm


class Nasa42Options:
    """The ``42://`` URL: host, port and the 42-specific options popped from ``options`` (the rest
    are the feed's, ``ground.sim.attitude_feed``)."""

    def __init__(self, spec: str):
        if not spec.startswith("42://"):
            raise ValueError("a 42 feed is 42://HOST:PORT")
        parts = urlsplit("tcp://" + spec[len("42://") :])
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None:
            raise ValueError("needs HOST:PORT")
        self.host, self.port = parts.hostname, port
        pairs = parse_qsl(parts.query, keep_blank_values=True)
        self.options = dict(pairs)
        if len(self.options) < len(pairs):
            raise ValueError("an option given twice")
        self.mount = parse_mount(self.options.pop("mount", "1,0,0,0"))
        speed = self.options.pop("speed", "1")
        try:
            self.speed = float(speed)
        except ValueError:
            raise ValueError(f"speed={speed[:40]!r}: a number of simulated s per real s") from None
        if not (math.isfinite(self.speed) and 0.0 <= self.speed <= 1000.0):
            raise ValueError(f"speed={speed[:40]}: outside [0, 1000]")
        position = self.options.pop("position", "on")
        if position not in ("on", "off"):
            raise ValueError(f"position={position[:40]!r}: on or off")
        self.position = position == "on"
        if "format" in self.options:
            raise ValueError("format= is not a 42 option (42 speaks text)")


class Reader:
    """The device's client of 42's IPC socket (module docstring): a daemon thread offering one
    sample per whole message to ``on_sample`` and each fault to ``on_error``."""

    def __init__(
        self,
        opts: Nasa42Options,
        on_sample: Callable[[Sample], None],
        on_error: Callable[[str], None],
        on_connect: Callable[[], None] | None = None,
        wall: Callable[[], float] = time.monotonic,
    ):
        self.opts = opts
        self._on_sample, self._on_error = on_sample, on_error
        self._on_connect = on_connect or (lambda: None)
        self._wall = wall
        self._m = quat_to_matrix(opts.mount)
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self.messages = 0  #: whole messages taken
        self._thread = threading.Thread(target=self._serve, name="nasa42", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        sock = self._sock
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self._thread.join(timeout=2.0)

    def sample(self, msg: dict[str, object]) -> Sample:
        """The sensor's sample of one parsed message (MalformedMessage when it lacks a line)."""
        missing = [k for k in NEEDED if k not in msg]
        if missing:
            raise MalformedMessage(f"a 42 message without {', '.join(missing)}")
        qn, wn = np.asarray(msg["SC[0].B[0].qn"]), np.asarray(msg["SC[0].B[0].wn"])
        if qn.shape != (4,) or wn.shape != (3,):
            raise MalformedMessage("42's qn needs 4 numbers, wn 3")
        q_body = body_quaternion(qn)
        norm = float(np.linalg.norm(q_body))
        if not (math.isfinite(norm) and norm > 0.5):
            raise MalformedMessage(f"42's qn has norm {norm:.6g}")
        a_sensor = self._m @ quat_to_matrix(q_body / norm)
        q = matrix_to_quat(a_sensor)
        q = q / np.linalg.norm(q)  # a unit quaternion to the feed's 1e-6
        w = self._m @ wn
        r = None
        if self.opts.position and "Orb[0].PosN" in msg:
            pos = np.asarray(msg["Orb[0].PosN"], dtype=float)
            rel = np.asarray(msg.get("SC[0].PosR", np.zeros(3)), dtype=float)
            if pos.shape == (3,) and rel.shape == (3,):
                r = (pos + rel) / 1000.0
        return Sample(float(msg["t"]), q, w, r)  # type: ignore[arg-type]

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                sock = socket.create_connection((self.opts.host, self.opts.port), timeout=RETRY_S * 5)
            except OSError:
                self._stop.wait(RETRY_S)
                continue
            sock.settimeout(None)
            self._sock = sock
            self._on_connect()
            try:
                self._session(sock)
            finally:
                sock.close()
                self._sock = None

    def _session(self, sock: socket.socket) -> None:
        buf = b""
        lines: list[str] = []
        bad: str | None = None
        t_first: float | None = None
        wall_first = 0.0
        while not self._stop.is_set():
            try:
                data = sock.recv(65536)
            except OSError:
                data = b""
            if not data:
                if not self._stop.is_set():
                    inside = bool(lines or buf.strip())
                    self._on_error("42 closed its socket" + (" inside a message (dropped)" if inside else ""))
                return
            buf += data
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                line = raw.decode("ascii", "replace").strip()
                if line != END:
                    lines.append(line)
                    if sum(len(x) for x in lines) > MAX_MESSAGE:
                        bad, lines = bad or f"a 42 message over {MAX_MESSAGE} bytes", []
                    continue
                sample = None
                if bad is None:
                    try:
                        sample = self.sample(parse_message(lines))
                    except MalformedMessage as exc:
                        bad = str(exc)
                lines = []
                if bad is not None:
                    self._on_error(f"42 message dropped: {bad}")
                    bad = None
                elif sample is not None:
                    self.messages += 1
                    try:
                        self._on_sample(sample)
                    except Exception as exc:  # noqa: BLE001 - counted; the reader serves on
                        self._on_error(f"42 sample dropped: {exc!r}"[:200])
                    if self.opts.speed > 0:
                        if t_first is None:
                            t_first, wall_first = sample.t, self._wall()
                        due = wall_first + (sample.t - t_first) / self.opts.speed
                        while not self._stop.is_set() and self._wall() < due:
                            time.sleep(min(0.05, max(0.0, due - self._wall())))
                try:
                    sock.sendall(ACK)
                except OSError:
                    pass  # the next recv sees the close
            if len(buf) > MAX_MESSAGE:
                self._on_error(f"42 line over {MAX_MESSAGE} bytes: the message dropped")
                buf, lines = b"", []


def run_folder(dest: Path, name: str, port: int, seconds: float) -> Path:
    """A run of 42 built in ``dest`` (``../shared/tools/nasa42/build.sh``): a copy of its
    ``ipc-tx`` inputs as ``dest/name`` with the IPC socket on ``port`` and ``seconds`` of 0.1 s
    steps, output every step (``Inp_IPC.txt`` line 7, ``Inp_Sim.txt`` lines 4-5)."""
    run = dest / name
    shutil.copytree(dest / "ipc-tx", run)
    ipc = (run / "Inp_IPC.txt").read_text().splitlines()
    ipc[6] = f"localhost     {port}                     ! Server Host Name, Port "
    (run / "Inp_IPC.txt").write_text("\n".join(ipc) + "\n")
    sim = (run / "Inp_Sim.txt").read_text().splitlines()
    sim[3] = f"{seconds:.1f}     0.1                 !  Sim Duration, Step Size [sec]"
    sim[4] = "0.1                             !  File Output Interval [sec]"
    (run / "Inp_Sim.txt").write_text("\n".join(sim) + "\n")
    return run
