"""Byte transports for the device (pty, serial port, TCP) and the serving loop with line pacing.

A link (:class:`Link`) offers ``read(timeout) -> bytes`` (``b""`` when nothing arrived),
``write(data, session=None) -> bool``, ``session`` (which peer the bytes read last came from),
``close()`` and ``describe()``; :func:`open_link` makes one from a URL, as
pyserial's ``serial_for_url`` does for ports. :func:`serve` moves bytes between a link and a :class:`~firmware_model.device.device.Device`
until a stop event is set. With pacing (``baud``), received bytes are handed to the device no
earlier than a UART at ``baud`` (10 bits per byte) could have delivered them, each reply starts
``turnaround`` seconds after the command's last byte, and reply bytes leave no faster than the
line rate.
"""

from __future__ import annotations

import logging
import os
import select
import socket
import threading
import time
import tty
from typing import Protocol

import serial

log = logging.getLogger(__name__)

WRITE_TIMEOUT = 2.0  #: seconds a reply may wait for the peer to drain; then it is dropped
DEFAULT_IDLE_TIMEOUT = 60.0  #: seconds of silence after which a TCP client is closed
LISTEN_BACKLOG = 128  #: TCP connections the kernel holds until the device accepts them
MAX_ACCEPT = 64  #: TCP connections accepted per read (a flood cannot starve the active client)
FEND = b"\xc0"  #: SLIP frame end, handed to the device when a TCP client goes
PACE_SLICE = 64  #: bytes written per paced slice


class PtyLink:
    """A pseudo-terminal; the peer opens :attr:`path`. The slave stays open here so the master
    never sees end-of-file when a client disconnects."""

    def __init__(self):
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self.session = 0  #: a line has one peer: always the same session

    def read(self, timeout: float) -> bytes:
        ready, _, _ = select.select([self._master], [], [], timeout)
        if not ready:
            return b""
        try:
            return os.read(self._master, 65536)
        except (BlockingIOError, InterruptedError):
            return b""

    def write(self, data: bytes, session: int | None = None) -> bool:
        view = memoryview(data)
        deadline = time.monotonic() + WRITE_TIMEOUT
        while view:
            try:
                n = os.write(self._master, view)
                view = view[n:]
            except (BlockingIOError, InterruptedError):
                if time.monotonic() > deadline:
                    return False
                select.select([], [self._master], [], 0.05)
        return True

    def close(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def describe(self) -> str:
        return self.path


class SerialLink:
    """A real serial port through pyserial (8N1 at ``baud``)."""

    def __init__(self, port: str, baud: int):
        self._ser = serial.serial_for_url(port, baudrate=baud, timeout=0.1, write_timeout=WRITE_TIMEOUT)
        self.path = port
        self.session = 0  #: a line has one peer: always the same session

    def read(self, timeout: float) -> bytes:
        if self._ser.timeout != timeout:  # reconfiguring a port costs a system call: only on change
            self._ser.timeout = timeout
        first = self._ser.read(1)
        if not first:
            return b""
        return first + self._ser.read(self._ser.in_waiting)

    def write(self, data: bytes, session: int | None = None) -> bool:
        try:
            self._ser.write(data)
            return True
        except serial.SerialTimeoutException:
            return False

    def close(self) -> None:
        self._ser.close()

    def describe(self) -> str:
        return self.path


class TcpLink:
    """A TCP server for one client at a time (reach it with pyserial ``socket://host:port``).

    Policy, as a serial line with one peer would behave (docs/bad_input.md):

    - one active client; a new connection **takes over**: the previous client is closed, after
      one more read of what it had already sent (answered to it), so a forgotten, hung or
      chattering session can never lock the device;
    - a client silent for ``idle_timeout`` s (None: never) is closed;
    - when a client goes (disconnect, takeover, idle), a FEND is handed to the device so a frame it
      left half sent is ended there (counted as a damaged frame), never joined to the next
      client's bytes;
    - a connection flood is accepted and closed as fast as it arrives, at most
      :data:`MAX_ACCEPT` per read, the newest connection staying active (one superseded before
      the device read from it is closed unread);
    - a reply the client does not read within :data:`WRITE_TIMEOUT` s closes the connection;
    - a reply goes only to the connection that sent the command: every accepted connection is a
      new :attr:`session`, and a reply for a session that has gone (a COMBINATION answered after
      a takeover) is dropped and counted in :attr:`late_dropped`, never written to its successor.
    """

    def __init__(self, host: str, port: int, idle_timeout: float | None = DEFAULT_IDLE_TIMEOUT):
        if idle_timeout is not None and not idle_timeout > 0:
            raise ValueError(f"TCP idle timeout must be > 0 s, got {idle_timeout}")
        self.idle_timeout = idle_timeout
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind((host, port))
        self._server.listen(LISTEN_BACKLOG)
        self._server.setblocking(False)
        self._conn: socket.socket | None = None
        self._newcomer_waited = False  #: a connection waited while the active client's bytes were read
        self._last = 0.0  #: monotonic time of the active client's last byte (or its connection)
        self.taken_over = self.idle_closed = 0  #: connections closed by the policy, per reason
        self.session = 0  #: number of the active connection (each accepted one gets the next)
        self.late_dropped = 0  #: replies dropped because their connection had gone
        host, port = self._server.getsockname()[:2]
        self.path = f"socket://{host}:{port}"

    def read(self, timeout: float) -> bytes:
        """Bytes of the active client; a lone FEND when a client went; ``b""`` when nothing came."""
        if self._conn is not None and self.idle_timeout is not None:
            left = self._last + self.idle_timeout - time.monotonic()
            if left <= 0:
                self.idle_closed += 1
                return self._drop()
            timeout = min(timeout, left)
        watch = [self._server] if self._conn is None else [self._server, self._conn]
        ready, _, _ = select.select(watch, [], [], timeout)
        if self._server in ready and (self._conn not in ready or self._newcomer_waited):
            self._newcomer_waited = False
            return self._accept_newcomers()
        if self._conn is None or self._conn not in ready:
            return b""
        # The active client's bytes first (a command it sent before a newcomer arrived is served
        # and answered to it), but only once: a client that never stops sending cannot hold on.
        self._newcomer_waited = self._server in ready
        try:
            data = self._conn.recv(65536)
        except OSError:
            data = b""
        if not data:
            return self._drop()
        self._last = time.monotonic()
        return data

    def _accept_newcomers(self) -> bytes:
        """Accept waiting connections (at most MAX_ACCEPT); the newest becomes the active client."""
        went = b""
        for _ in range(MAX_ACCEPT):
            try:
                conn, _ = self._server.accept()
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:  # e.g. out of file descriptors: refuse this one, keep serving
                log.warning("link: accept failed: %s", exc)
                break
            if self._conn is not None:
                self.taken_over += 1
                went = self._drop()
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(WRITE_TIMEOUT)
            self.session += 1  # before the connection: a writer that reads it then the number never pairs them wrong
            self._conn, self._last = conn, time.monotonic()
        return went

    def _drop(self) -> bytes:
        """Close the active client; the FEND that ends whatever frame it left unfinished."""
        if self._conn is None:
            return b""
        try:
            self._conn.close()
        finally:
            self._conn = None
        return FEND

    def write(self, data: bytes, session: int | None = None) -> bool:
        """Send ``data`` to the active client, only if it is still ``session`` (when given)."""
        conn, active = self._conn, self.session  # a late reply comes from another thread: read both once
        if session is not None and session != active:
            self.late_dropped += 1
            log.info("link: reply for connection %d dropped: connection %d is active", session, active)
            return False
        if conn is None:
            return False
        try:
            conn.sendall(data)
            return True
        except OSError:
            if self._conn is conn:
                self._drop()
            return False

    def close(self) -> None:
        self._drop()
        self._server.close()

    def describe(self) -> str:
        return self.path


class Link(Protocol):
    """The one transport interface :func:`serve` uses. ``session`` numbers the peer the last
    bytes read came from; ``write(data, session)`` drops ``data`` if that peer has gone."""

    session: int

    def read(self, timeout: float) -> bytes: ...

    def write(self, data: bytes, session: int | None = None) -> bool: ...

    def close(self) -> None: ...

    def describe(self) -> str: ...


def open_link(url: str, baud: int = 115200, tcp_idle: float | None = DEFAULT_IDLE_TIMEOUT) -> Link:
    """A link from a URL: ``pty://`` (a new pseudo-terminal), ``tcp://HOST:PORT`` (a server for
    one client at a time, idle clients closed after ``tcp_idle`` s), anything else a pyserial
    URL or device path opened at ``baud``."""
    if url in ("pty", "pty://"):
        return PtyLink()
    if url.startswith("tcp://"):
        host, port = parse_tcp(url[len("tcp://") :])
        return TcpLink(host, port, idle_timeout=tcp_idle)
    return SerialLink(url, baud)


def parse_tcp(text: str) -> tuple[str, int]:
    """``host:port`` or ``:port``/``port`` (host 127.0.0.1)."""
    host, _, port = text.rpartition(":")
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f"bad TCP address {text!r}: expected host:port") from None
    if not 0 <= number <= 65535:
        raise ValueError(f"TCP port {number} outside 0..65535")
    return host or "127.0.0.1", number


class Pacer:
    """Line timing of a UART at ``baud`` (10 bits per byte) with a command ``turnaround``."""

    def __init__(self, baud: int, turnaround: float):
        if baud <= 0:
            raise ValueError("baud must be positive")
        self.byte_time = 10.0 / baud
        self.turnaround = turnaround
        self._rx_end = 0.0
        self._tx_free = 0.0

    def arrived(self, n: int) -> float:
        """Time the last of ``n`` bytes just read would have finished arriving on the line."""
        self._rx_end = max(self._rx_end, time.monotonic()) + n * self.byte_time
        return self._rx_end

    def send(self, link, data: bytes, ready_at: float, session: int | None = None) -> bool:
        """Write ``data`` to ``session`` starting no earlier than ``ready_at`` and no faster than the line."""
        start = max(ready_at, self._tx_free)
        for i in range(0, len(data), PACE_SLICE):
            piece = data[i : i + PACE_SLICE]
            _sleep_until(start + i * self.byte_time)
            if not link.write(piece, session):
                return False
        self._tx_free = start + len(data) * self.byte_time
        return True


def _sleep_until(t: float) -> None:
    delay = t - time.monotonic()
    if delay > 0:
        time.sleep(delay)


def _pieces(chunk: bytes):
    """Split after every FEND so each frame is handed over when its last byte has arrived."""
    start = 0
    while start < len(chunk):
        end = chunk.find(0xC0, start)
        end = len(chunk) if end < 0 else end + 1
        yield chunk[start:end]
        start = end


def serve(
    device, link, stop: threading.Event, *, baud: int | None = None, turnaround: float = 0.0, poll: float = 0.1
) -> None:
    """Serve ``device`` on ``link`` until ``stop`` is set; pace to ``baud`` if given. Replies the
    device produces later (a COMBINATION's, when its sequence ends) are written as they come,
    while the loop goes on reading and answering, and only to the link session (the TCP
    connection) that sent the command."""
    pacer = Pacer(baud, turnaround) if baud else None
    write_lock = threading.Lock()

    def send(frames: list[bytes], ready_at: float, session: int) -> None:
        """Write ``frames`` to ``session`` (paced: starting no earlier than ``ready_at``,
        monotonic s); one writer at a time, the loop's replies and the late ones alike."""
        with write_lock:
            if pacer is None:
                link.write(b"".join(frames), session)
            else:
                for frame in frames:
                    if not pacer.send(link, frame, ready_at, session):
                        return

    serving = True

    def late_reply_to(session: int):
        """The device's late-reply callback for commands read from ``session`` (a reply ready
        after serving stopped is dropped)."""

        def late(frames: list[bytes]) -> None:
            if serving:
                send(frames, time.monotonic() + turnaround, session)

        return late

    try:
        while not stop.is_set():
            try:
                chunk = link.read(poll)
            except OSError as exc:
                log.warning("link: read failed: %s", exc)
                time.sleep(poll)
                continue
            if not chunk:
                continue
            session = link.session  # the peer these bytes came from; their replies go to it alone
            device.late_reply = late_reply_to(session)
            if pacer is None:
                replies = device.receive(chunk)
                if replies:
                    if turnaround > 0:
                        time.sleep(turnaround)
                    send(replies, 0.0, session)
                continue
            for piece in _pieces(chunk):
                done = pacer.arrived(len(piece))
                _sleep_until(done)
                send(device.receive(piece, done), done + pacer.turnaround, session)
    finally:
        serving = False
        device.late_reply = None
