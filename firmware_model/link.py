"""Byte transports for the device (pty, serial port, TCP) and the serving loop with line pacing.

A link offers ``read(timeout) -> bytes`` (``b""`` when nothing arrived), ``write(data)`` and
``close()``. :func:`serve` moves bytes between a link and a :class:`~firmware_model.device.Device`
until a stop event is set. With pacing (``baud``), received bytes are handed to the device no
earlier than a UART at ``baud`` (10 bits per byte) could have delivered them, each reply starts
``turnaround`` seconds after the command's last byte, and reply bytes leave no faster than the
line rate.
"""

from __future__ import annotations

import os
import select
import socket
import sys
import threading
import time
import tty

import serial

WRITE_TIMEOUT = 2.0  #: seconds a reply may wait for the peer to drain; then it is dropped
PACE_SLICE = 64  #: bytes written per paced slice


class PtyLink:
    """A pseudo-terminal; the peer opens :attr:`path`. The slave stays open here so the master
    never sees end-of-file when a client disconnects."""

    def __init__(self):
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)

    def read(self, timeout: float) -> bytes:
        ready, _, _ = select.select([self._master], [], [], timeout)
        if not ready:
            return b""
        try:
            return os.read(self._master, 65536)
        except (BlockingIOError, InterruptedError):
            return b""

    def write(self, data: bytes) -> bool:
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

    def read(self, timeout: float) -> bytes:
        if self._ser.timeout != timeout:  # reconfiguring a port costs a system call: only on change
            self._ser.timeout = timeout
        first = self._ser.read(1)
        if not first:
            return b""
        return first + self._ser.read(self._ser.in_waiting)

    def write(self, data: bytes) -> bool:
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
    """A TCP server serving one client at a time (reach it with pyserial ``socket://host:port``)."""

    def __init__(self, host: str, port: int):
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind((host, port))
        self._server.listen(1)
        self._conn: socket.socket | None = None
        host, port = self._server.getsockname()[:2]
        self.path = f"socket://{host}:{port}"

    def read(self, timeout: float) -> bytes:
        if self._conn is None:
            ready, _, _ = select.select([self._server], [], [], timeout)
            if not ready:
                return b""
            self._conn, _ = self._server.accept()
            self._conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conn.settimeout(WRITE_TIMEOUT)
            return b""
        ready, _, _ = select.select([self._conn], [], [], timeout)
        if not ready:
            return b""
        try:
            data = self._conn.recv(65536)
        except OSError:
            data = b""
        if not data:
            self._drop()
        return data

    def _drop(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def write(self, data: bytes) -> bool:
        if self._conn is None:
            return False
        try:
            self._conn.sendall(data)
            return True
        except OSError:
            self._drop()
            return False

    def close(self) -> None:
        self._drop()
        self._server.close()

    def describe(self) -> str:
        return self.path


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

    def send(self, link, data: bytes, ready_at: float) -> bool:
        """Write ``data`` starting no earlier than ``ready_at`` and no faster than the line."""
        start = max(ready_at, self._tx_free)
        for i in range(0, len(data), PACE_SLICE):
            piece = data[i:i + PACE_SLICE]
            _sleep_until(start + i * self.byte_time)
            if not link.write(piece):
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


def serve(device, link, stop: threading.Event, *, baud: int | None = None, turnaround: float = 0.0,
          poll: float = 0.1) -> None:
    """Serve ``device`` on ``link`` until ``stop`` is set; pace to ``baud`` if given. Replies the
    device produces later (a COMBINATION's, when its sequence ends) are written as they come,
    while the loop goes on reading and answering."""
    pacer = Pacer(baud, turnaround) if baud else None
    write_lock = threading.Lock()

    def late(frames: list[bytes]) -> None:
        with write_lock:
            if pacer is None:
                link.write(b"".join(frames))
            else:
                for frame in frames:
                    pacer.send(link, frame, time.monotonic() + pacer.turnaround)

    device.late_reply = late
    try:
        while not stop.is_set():
            try:
                chunk = link.read(poll)
            except OSError as exc:
                print(f"link: read failed: {exc}", file=sys.stderr)
                time.sleep(poll)
                continue
            if not chunk:
                continue
            if pacer is None:
                replies = device.receive(chunk)
                if replies:
                    if turnaround > 0:
                        time.sleep(turnaround)
                    with write_lock:
                        link.write(b"".join(replies))
                continue
            for piece in _pieces(chunk):
                done = pacer.arrived(len(piece))
                _sleep_until(done)
                for frame in device.receive(piece):
                    with write_lock:
                        pacer.send(link, frame, done + pacer.turnaround)
    finally:
        device.late_reply = None
