"""The ground client against ports that misbehave: garbage, noise around the reply, replies to
other commands, slow, silent, and a peer that never stops sending (pty or ``socket://``).

A fake device (:class:`FakePort`) answers each command through a *behaviour*; the good reply to
a command carries a per-command nonce, so a client that returns anything but its own command's
nonce has taken a reply that was not for it. Behaviours that end in a good reply must be
answered; the others must raise a :class:`~ground.link.client.LinkError` within the client's bound.

Nothing here depends on how fast the machine is: a call that must be answered gets a generous
timeout (:data:`ANSWER_TIMEOUT`, a hang guard), a reply that must come too late is sent only once
the client's call has ended (:data:`AFTER_CALL`), and the bound a call must end within allows
:data:`SLACK` beyond the client's own (a client that ignores its bound hangs for good, which that
still catches; a loaded machine only delays it).
"""

from __future__ import annotations

import random
import socket
import threading
import time

from firmware_model.device.link import PtyLink
from ground.link.client import Client, LinkError
from ground.testing.tally import Tally
from protocol import nsp, slip

SLACK = 30.0  #: seconds allowed beyond the client's own bound: a hang guard
ANSWER_TIMEOUT = 30.0  #: the client's timeout (s) for a call the fake answers: a hang guard
AFTER_CALL = -1.0  #: a behaviour's delay meaning "once the client's call has ended"


def good(msg: nsp.Message, nonce: int) -> bytes:
    return nsp.reply_to(msg, f"ST16-EMU fake {nonce}".encode()).frame()


def _other_code(msg: nsp.Message, nonce: int) -> bytes:
    return nsp.Message(msg.src, msg.dst, 0xA0 | (msg.mcf & 0x40) | ((msg.code + 1) & 0x1F), b"other").frame()


def _stale_b(msg: nsp.Message, nonce: int) -> bytes:
    return nsp.Message(msg.src, msg.dst, (msg.mcf ^ 0x40) | 0xA0, f"ST16-EMU stale {nonce}".encode()).frame()


def _bad_crc(msg: nsp.Message, nonce: int) -> bytes:
    raw = bytearray(nsp.reply_to(msg, b"ST16-EMU damaged").encode())
    raw[-1] ^= 0x5A
    return slip.encode(bytes(raw))


def _garbage(rng: random.Random) -> bytes:
    return rng.randbytes(rng.randrange(1, 300))


#: name -> (answered?, fn(rng, msg, nonce, timeout) -> list of (delay s or AFTER_CALL, bytes)).
BEHAVIOURS = {
    "good": (True, lambda rng, m, n, t: [(0, good(m, n))]),
    "noise_then_good": (True, lambda rng, m, n, t: [(0, _garbage(rng) + b"\xc0" + _bad_crc(m, n)), (0, good(m, n))]),
    "others_then_good": (True, lambda rng, m, n, t: [(0, _other_code(m, n) + _stale_b(m, n)), (0, good(m, n))]),
    "slow_in_time": (True, lambda rng, m, n, t: [(t * 0.4, good(m, n))]),
    "garbage": (False, lambda rng, m, n, t: [(0, _garbage(rng))]),
    "damaged": (False, lambda rng, m, n, t: [(0, _bad_crc(m, n))]),
    "others_only": (False, lambda rng, m, n, t: [(0, _other_code(m, n) + _stale_b(m, n))]),
    "too_slow": (False, lambda rng, m, n, t: [(AFTER_CALL, good(m, n))]),
    "silent": (False, lambda rng, m, n, t: []),
}


class FakePort:
    """A fake device on a pty (``tcp=False``) or a TCP socket; :attr:`url` is what a client opens.
    ``behaviour`` names an entry of :data:`BEHAVIOURS`; ``flood`` makes it send garbage nonstop;
    :attr:`call_over` is set by the harness when the client's call has ended (:data:`AFTER_CALL`)."""

    def __init__(self, seed: int, timeout: float, tcp: bool = False, flood: bool = False):
        self.rng = random.Random(seed)
        self.timeout = timeout
        self.behaviour = "good"
        self.flood = flood
        self.nonces: list[int] = []  #: nonce of every command received, in order
        self.call_over = threading.Event()
        self._stop = threading.Event()
        self._conn: socket.socket | None = None
        if tcp:
            self._server = socket.create_server(("127.0.0.1", 0))
            self.url = f"socket://127.0.0.1:{self._server.getsockname()[1]}"
            self.link = None
        else:
            self.link = PtyLink()
            self.url = self.link.path
        self._threads = [threading.Thread(target=self._run, daemon=True)]
        if flood:
            self._threads.append(threading.Thread(target=self._flood, daemon=True))
        for thread in self._threads:
            thread.start()

    def _read(self, timeout: float) -> bytes:
        if self.link is not None:
            return self.link.read(timeout)
        if self._conn is None:
            self._server.settimeout(timeout)
            try:
                self._conn, _ = self._server.accept()
                self._conn.settimeout(0.01)
            except OSError:
                return b""
        try:
            return self._conn.recv(65536)
        except OSError:
            return b""

    def _write(self, data: bytes) -> None:
        try:
            if self.link is not None:
                self.link.write(data)
            elif self._conn is not None:
                self._conn.sendall(data)
        except OSError:
            pass

    def _flood(self) -> None:
        junk = random.Random(0).randbytes(65536)
        while not self._stop.is_set():
            if self.link is None and self._conn is None:
                time.sleep(0.005)
            else:
                self._write(junk)

    def _run(self) -> None:
        decoder = slip.Decoder()
        while not self._stop.is_set():
            for event in decoder.feed(self._read(0.02)):
                if not isinstance(event, slip.Frame):  # a framing error or an oversize frame
                    continue
                try:
                    msg = nsp.decode(event.data)
                except nsp.MessageError:
                    continue
                nonce = self.rng.randrange(1 << 30)
                self.nonces.append(nonce)
                for delay, data in BEHAVIOURS[self.behaviour][1](self.rng, msg, nonce, self.timeout):
                    if delay == AFTER_CALL:
                        while not self.call_over.wait(0.05):
                            if self._stop.is_set():
                                return
                    elif self._stop.wait(delay):
                        return
                    self._write(data)

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(3)
        if self.link is not None:
            self.link.close()
        else:
            if self._conn is not None:
                self._conn.close()
            self._server.close()


def run(seed: int, trials: int, timeout: float = 0.2, tcp: bool = False) -> Tally:
    """``trials`` PINGs on one fake port and one client, going through every behaviour in turn
    (a shuffled order per round)."""
    rng = random.Random(seed)
    tally = Tally()
    port = FakePort(seed, timeout, tcp=tcp)
    order: list[str] = []
    try:
        with Client(port.url, timeout=timeout, retries=0) as client:
            for _ in range(trials):
                if not order:
                    order = sorted(BEHAVIOURS)
                    rng.shuffle(order)
                port.behaviour = order.pop()
                answered, _fn = BEHAVIOURS[port.behaviour]
                tally.messages += 1
                tally.faults += port.behaviour != "good"
                check_call(client, port, answered, tally, timeout)
    finally:
        port.close()
    return tally


def check_call(client: Client, port: FakePort, answered: bool, tally: Tally, timeout: float) -> None:
    """One PING: answered with this command's nonce, or a LinkError, within the bound. ``timeout``:
    the client's for a call that must fail (one that must be answered gets :data:`ANSWER_TIMEOUT`)."""
    client.timeout = ANSWER_TIMEOUT if answered else timeout
    bound = client.timeout * (1 + client.retries) + SLACK
    port.call_over.clear()
    t0 = time.monotonic()
    try:
        banner = client.ping()
        if not answered or banner != f"ST16-EMU fake {port.nonces[-1]}":
            tally.fail("misattributed", f"{port.behaviour}: took {banner!r}")
    except LinkError as exc:
        if answered:
            tally.fail("unanswered_pings", f"{port.behaviour}: {exc}")
    except Exception as exc:  # anything else would reach the user as a traceback
        tally.fail("tracebacks", f"{port.behaviour}: {type(exc).__name__}: {exc}")
    finally:
        port.call_over.set()
    if time.monotonic() - t0 > bound:
        tally.fail("hangs", f"{port.behaviour}: {time.monotonic() - t0:.2f} s > {bound:.2f} s")


def run_flood(seed: int, calls: int, timeout: float = 0.2, tcp: bool = True) -> Tally:
    """A peer that never stops sending garbage: every call must fail within its bound."""
    tally = Tally()
    port = FakePort(seed, timeout, tcp=tcp, flood=True)
    port.behaviour = "silent"
    try:
        with Client(port.url, timeout=timeout, retries=0) as client:
            for _ in range(calls):
                tally.messages += 1
                tally.faults += 1
                check_call(client, port, False, tally, timeout)
    finally:
        port.close()
    return tally
