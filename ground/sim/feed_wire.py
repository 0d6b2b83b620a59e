"""The attitude feed's wire format and transports (docs/hil.md): what a dynamics simulator sends
to ``st16-device --attitude-feed URL``.

A sample is the sensor's attitude at a time: ``t`` POSIX UTC seconds, ``q`` the scalar-first
``q_icrs_to_sensor`` (docs/CONVENTIONS.md), ``w`` the angular velocity of the sensor frame with
respect to ICRS in sensor axes (rad/s). Two encodings:

* JSON lines: ``{"t": 1790000000.25, "q": [w, x, y, z], "w": [wx, wy, wz]}`` + ``\\n``, with an
  optional ``"r": [x, y, z]``: the spacecraft's GCRS position (km) at ``t``;
* binary: one little-endian record ``<d4d3d`` (64 bytes: t, qw, qx, qy, qz, wx, wy, wz); it has
  no position (the record stays as it was: a simulator that sends positions uses JSON, or the
  source's ``orbit`` option places the spacecraft).

Transports on loopback: ``tcp://HOST:PORT`` (the device listens; one simulator connection at a
time, samples back to back) or ``udp://HOST:PORT`` (the device binds; one or more samples per
datagram). ``?format=json`` (default) or ``?format=binary`` picks the encoding; further query keys
configure the capture source (``ground.sim.attitude_feed``).
"""

from __future__ import annotations

import json
import logging
import select
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from urllib.parse import parse_qsl, urlsplit

import numpy as np

log = logging.getLogger(__name__)

RECORD = struct.Struct("<d4d3d")  #: the binary sample, 64 bytes
FORMATS = ("json", "binary")
MAX_LINE = 4096  #: bytes; a longer JSON line is malformed
POLL_S = 0.2  #: how often the listener thread looks whether it should stop
IDLE_S = 60.0  #: a TCP feed peer silent this long is closed (the NSP TCP link's default, --tcp-idle)


@dataclass(frozen=True)
class Sample:
    """One attitude sample: ``t`` POSIX s, ``q`` scalar-first q_icrs_to_sensor, ``w`` rad/s (sensor
    axes), ``r`` the spacecraft's GCRS position (km) or None."""

    t: float
    q: np.ndarray
    w: np.ndarray
    r: np.ndarray | None = None


class MalformedSample(ValueError):
    """Bytes that do not decode to a sample."""


def encode_json(s: Sample) -> bytes:
    obj = {"t": float(s.t), "q": [float(v) for v in s.q], "w": [float(v) for v in s.w]}
    if s.r is not None:
        obj["r"] = [float(v) for v in s.r]
    return (json.dumps(obj) + "\n").encode()


def encode_binary(s: Sample) -> bytes:
    return RECORD.pack(float(s.t), *(float(v) for v in s.q), *(float(v) for v in s.w))


def decode_json(line: bytes) -> Sample:
    """A sample from one JSON line; NaN and infinities decode (the feed's checks flag them)."""
    try:
        obj = json.loads(line)
        t, q, w = float(obj["t"]), np.array(obj["q"], dtype=float), np.array(obj["w"], dtype=float)
        r = None if obj.get("r") is None else np.array(obj["r"], dtype=float)
    except Exception as exc:  # noqa: BLE001 - whatever a line holds (3000 nested brackets: RecursionError;
        # a 400-digit time: OverflowError) is a malformed sample, counted and dropped, never the listener's end
        why = " ".join(str(exc).split())[:80] or type(exc).__name__
        raise MalformedSample(f"not a JSON sample ({why}): {line[:80]!r}") from None
    if q.shape != (4,) or w.shape != (3,) or (r is not None and r.shape != (3,)):
        raise MalformedSample(f"q needs 4 numbers, w and r 3: {line[:80]!r}")
    return Sample(t, q, w, r)


def decode_binary(record: bytes) -> Sample:
    if len(record) != RECORD.size:
        raise MalformedSample(f"binary sample of {len(record)} bytes, not {RECORD.size}")
    v = RECORD.unpack(record)
    return Sample(v[0], np.array(v[1:5]), np.array(v[5:8]))


@dataclass(frozen=True)
class FeedUrl:
    """A parsed feed URL: transport (tcp/udp), host, port, format and the other query options."""

    transport: str
    host: str
    port: int
    format: str
    options: dict[str, str]

    @classmethod
    def parse(cls, url: str) -> FeedUrl:
        parts = urlsplit(url)
        if parts.scheme not in ("tcp", "udp"):
            raise ValueError(f"attitude feed {url!r}: scheme must be tcp:// or udp://")
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None:
            raise ValueError(f"attitude feed {url!r}: needs HOST:PORT")
        pairs = parse_qsl(parts.query, keep_blank_values=True)
        options = dict(pairs)
        if len(options) < len(pairs):
            twice = sorted({k for k, _ in pairs if sum(k == j for j, _ in pairs) > 1})
            raise ValueError(f"attitude feed {url!r}: option(s) {twice} given twice")
        fmt = options.pop("format", "json")
        if fmt not in FORMATS:
            raise ValueError(f"attitude feed {url!r}: format must be one of {FORMATS}")
        return cls(parts.scheme, parts.hostname, port, fmt, options)


OnSample = Callable[[Sample], None]
OnError = Callable[[str], None]


class Listener:
    """Receives samples on ``url`` in a daemon thread: ``on_sample(sample)`` for each decoded one,
    ``on_error(reason)`` for bytes that do not decode (or a sample ``on_sample`` fails on: counted
    and dropped, the listener serves on), ``on_connect()`` when a TCP peer connects. Over TCP one
    peer at a time: the newest connection takes over, a peer silent for ``idle_s`` is closed (None:
    never). Binds at construction (OSError if it cannot)."""

    def __init__(
        self,
        url: FeedUrl,
        on_sample: OnSample,
        on_error: OnError,
        on_connect: Callable[[], None] | None = None,
        idle_s: float | None = IDLE_S,
    ):
        self.url, self.idle_s = url, idle_s
        self._on_sample, self._on_error = on_sample, on_error
        self._on_connect = on_connect or (lambda: None)
        kind = socket.SOCK_STREAM if url.transport == "tcp" else socket.SOCK_DGRAM
        self._sock = socket.socket(socket.AF_INET, kind)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind((url.host, url.port))
        if url.transport == "tcp":
            self._sock.listen(1)
        self._sock.settimeout(POLL_S)
        self._stop = threading.Event()
        target = self._serve_tcp if url.transport == "tcp" else self._serve_udp
        self._thread = threading.Thread(target=target, name="attitude-feed", daemon=True)
        self._thread.start()

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close()

    def _decode(self, data: bytes) -> None:
        """Every sample in ``data`` (whole records or lines)."""
        if self.url.format == "binary":
            if len(data) % RECORD.size:
                self._on_error(f"binary data of {len(data)} bytes is not whole {RECORD.size}-byte samples")
                return
            chunks = [data[k : k + RECORD.size] for k in range(0, len(data), RECORD.size)]
        else:
            chunks = [ln for ln in data.split(b"\n") if ln.strip()]
        for chunk in chunks:
            try:
                sample = decode_binary(chunk) if self.url.format == "binary" else decode_json(chunk)
                self._on_sample(sample)
            except Exception as exc:  # noqa: BLE001 - one bad sample is counted and dropped; the listener serves on
                self._on_error(str(exc) if isinstance(exc, MalformedSample) else f"sample dropped: {exc!r}"[:200])

    def _serve_udp(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            self._decode(data)

    def _serve_tcp(self) -> None:
        """One peer at a time, as the NSP TCP link serves (``firmware_model.device.link.TcpLink``):
        a new connection takes over from the one before, and a peer silent for ``idle_s`` is
        closed, so a connection that sends nothing never holds the port from the simulator."""
        conn: socket.socket | None = None
        buf, last = b"", 0.0
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._sock] + ([conn] if conn else []), [], [], POLL_S)
            except (OSError, ValueError):
                return  # the listening socket was closed
            if self._sock in ready:
                try:
                    new, _ = self._sock.accept()
                except OSError:
                    continue
                if conn is not None:
                    self._close_peer(conn, buf, "a new connection took over the attitude feed")
                conn, buf, last = new, b"", time.monotonic()
                conn.setblocking(False)
                self._on_connect()
            if conn is not None and conn in ready:
                try:
                    data = conn.recv(65536)
                except (BlockingIOError, InterruptedError):
                    data = None
                except OSError:
                    data = b""
                if data == b"":
                    self._close_peer(conn, buf, None)
                    conn, buf = None, b""
                elif data:
                    last = time.monotonic()
                    buf = self._take(buf + data)
            if conn is not None and self.idle_s is not None and time.monotonic() - last > self.idle_s:
                self._close_peer(conn, buf, f"attitude feed peer silent for {self.idle_s:g} s: closed")
                conn, buf = None, b""
        if conn is not None:
            conn.close()

    def _close_peer(self, conn: socket.socket, buf: bytes, why: str | None) -> None:
        """Close a peer's connection; a sample it left cut, and ``why`` when given, are faults."""
        if buf:
            self._on_error(f"connection closed inside a sample ({len(buf)} bytes left)")
        if why:
            self._on_error(why)
        conn.close()

    def _take(self, buf: bytes) -> bytes:
        """Decode the whole samples at the head of ``buf``; the cut one left."""
        if self.url.format == "binary":
            whole = len(buf) - len(buf) % RECORD.size
            if whole:
                self._decode(buf[:whole])
            return buf[whole:]
        head, sep, rest = buf.rpartition(b"\n")
        if sep:
            self._decode(head)
        if len(rest) > MAX_LINE:
            self._on_error(f"JSON line longer than {MAX_LINE} bytes")
            return b""
        return rest


class Sender:
    """The simulator's side: sends samples to a device's feed ``url`` (connects on TCP, so the
    device must listen first)."""

    def __init__(self, url: str):
        self.url = FeedUrl.parse(url)
        kind = socket.SOCK_STREAM if self.url.transport == "tcp" else socket.SOCK_DGRAM
        self._sock = socket.socket(socket.AF_INET, kind)
        if self.url.transport == "tcp":
            self._sock.connect((self.url.host, self.url.port))

    def send(self, *samples: Sample) -> None:
        encode = encode_binary if self.url.format == "binary" else encode_json
        self.send_raw(b"".join(encode(s) for s in samples))

    def send_raw(self, data: bytes) -> None:
        if self.url.transport == "tcp":
            self._sock.sendall(data)
        else:  # unconnected: a device not (yet) listening loses the datagram, as on a real bus
            self._sock.sendto(data, (self.url.host, self.url.port))

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> Sender:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
