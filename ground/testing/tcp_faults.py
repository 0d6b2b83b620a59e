"""TCP link faults against ``st16-device --tcp``: several clients, silent clients, clients that
vanish mid-message, idle clients, and a connection flood, under the link's policy (one active
client, the newest takes over, idle clients closed; see ``firmware_model.device.link.TcpLink``).

After every scenario a fresh client must get its PING answered; a client that was taken over
must get a link error, never a reply meant for someone else.
"""

from __future__ import annotations

import os
import random
import socket
import threading
import time

from ground.link.client import Client, LinkError
from ground.testing.checks import ping_check, stderr_check
from ground.testing.device_proc import DeviceProcess
from ground.testing.tally import Tally
from protocol import nsp, slip
from protocol.commands import GO_OPERATIONAL, Code, Combination

TIMEOUT = 1.0  #: client reply timeout, s
SLOW_SEQUENCE_S = 0.6  #: the campaign device's exposure + processing time (--timing realistic), s


def _address(device: DeviceProcess) -> tuple[str, int]:
    host, port = device.path[len("socket://") :].rsplit(":", 1)
    return host, int(port)


def _raw(device: DeviceProcess) -> socket.socket:
    return socket.create_connection(_address(device), timeout=TIMEOUT)


def open_fds(pid: int) -> int:
    """File descriptors the process holds (Linux /proc); -1 where unavailable."""
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return -1


def closed_by_peer(sock: socket.socket, within: float) -> bool:
    """True if the device closes ``sock`` within ``within`` s (EOF or reset; data is read past)."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        try:
            if not sock.recv(65536):
                return True
        except TimeoutError:
            return False
        except OSError:
            return True
    return False


def _takeover(device: DeviceProcess, rng: random.Random, tally: Tally) -> None:
    """A pings, B connects and pings, A's next command is a link error (taken over)."""
    with Client(device.path, timeout=TIMEOUT, retries=0) as a:
        ping_check(a, tally, device)
        with Client(device.path, timeout=TIMEOUT, retries=0) as b:
            ping_check(b, tally, device)
            tally.messages += 1
            tally.faults += 1
            try:
                banner = a.ping()
                tally.fail("misattributed", f"a client taken over still got {banner!r}")
            except LinkError:
                pass
            ping_check(b, tally, device)


def _silent(device: DeviceProcess, rng: random.Random, tally: Tally) -> None:
    """A client that connects and says nothing does not lock the next one out."""
    tally.faults += 1
    with _raw(device):
        with Client(device.path, timeout=TIMEOUT, retries=0) as c:
            ping_check(c, tally, device)


def _cut(device: DeviceProcess, rng: random.Random, tally: Tally) -> None:
    """A client sends part of a frame (or a whole command) and vanishes; the next one is served."""
    frame = nsp.command(
        nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, rng.randrange(32), rng.randbytes(rng.randrange(30))
    ).frame()
    tally.faults += 1
    tally.messages += 1
    with _raw(device) as s:
        s.sendall(frame[: rng.randrange(1, len(frame) + 1)])
        if rng.random() < 0.5:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\0\0\0\0\0\0\0")  # reset, not FIN
    with Client(device.path, timeout=TIMEOUT, retries=0) as c:
        ping_check(c, tally, device)


def _garbage(device: DeviceProcess, rng: random.Random, tally: Tally) -> None:
    """A client that sends garbage and never reads; the next one is served."""
    tally.faults += 1
    with _raw(device) as s:
        s.sendall(rng.randbytes(rng.randrange(1, 20000)))
        with Client(device.path, timeout=TIMEOUT, retries=0) as c:
            ping_check(c, tally, device)


def _chatter(device: DeviceProcess, rng: random.Random, tally: Tally) -> None:
    """A client that never stops sending cannot keep a newcomer out."""
    tally.faults += 1
    stop = threading.Event()
    junk = rng.randbytes(8192)

    def send(sock: socket.socket) -> None:
        while not stop.is_set():
            try:
                sock.sendall(junk)
            except OSError:
                return

    with _raw(device) as s:
        thread = threading.Thread(target=send, args=(s,), daemon=True)
        thread.start()
        time.sleep(0.05)
        try:
            with Client(device.path, timeout=TIMEOUT, retries=0) as c:
                ping_check(c, tally, device)
        finally:
            stop.set()
            s.close()  # the device has closed its end already: the sender stops on its error
            thread.join(2)


def _frames(sock: socket.socket, within: float) -> list[nsp.Message]:
    """The NSP messages ``sock`` receives within ``within`` s."""
    decoder = slip.Decoder(nsp.MAX_MESSAGE)
    out: list[nsp.Message] = []
    deadline = time.monotonic() + within
    while (left := deadline - time.monotonic()) > 0:
        sock.settimeout(left)
        try:
            data = sock.recv(65536)
        except TimeoutError:
            break
        if not data:
            break
        out += [nsp.decode(e.data) for e in decoder.feed(data) if isinstance(e, slip.Frame)]
    return out


def late_takeover(device: DeviceProcess, rng: random.Random, tally: Tally) -> None:
    """A sends COMBINATION, whose reply waits for the device's slow sequence (the campaign's
    device runs ``--timing realistic``), and B takes over meanwhile: B gets its PING answered
    and never A's reply."""
    with Client(device.path, timeout=TIMEOUT, retries=0) as a:
        if "BOOTLOADER" in a.ping():
            a.init()
    combination = nsp.command(
        nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, Code.COMBINATION, Combination(GO_OPERATIONAL, 1).pack()
    )
    ping = nsp.command(nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, Code.PING, b"")
    tally.faults += 1
    tally.messages += 2
    with _raw(device) as a_sock:
        a_sock.sendall(combination.frame())
        time.sleep(rng.uniform(0.02, 0.1))  # the sequence runs: A's reply is pending
        with _raw(device) as b_sock:
            b_sock.sendall(ping.frame())
            got = _frames(b_sock, SLOW_SEQUENCE_S + 1.0)  # A's sequence ends meanwhile
    codes = [m.code for m in got]
    if any(code != Code.PING for code in codes):
        tally.fail("misattributed", f"a client that took over received replies of codes {codes}")
    elif not codes:
        tally.fail("unanswered_pings", "a client that took over got no reply to its PING")


SCENARIOS = {
    "takeover": _takeover,
    "late_takeover": late_takeover,
    "silent": _silent,
    "cut": _cut,
    "garbage": _garbage,
    "chatter": _chatter,
}


def flood(device: DeviceProcess, rng: random.Random, tally: Tally, connections: int) -> None:
    """``connections`` sockets at once (silent, half frames, garbage, closed at once); then a
    client is served and the device holds no more descriptors than before the flood."""
    with Client(device.path, timeout=TIMEOUT, retries=0) as c:
        ping_check(c, tally, device)
        before = open_fds(device.proc.pid)
    socks = []
    for _ in range(connections):
        tally.faults += 1
        try:
            s = _raw(device)
        except OSError as exc:
            tally.notes.append(f"flood: connect refused ({exc})")  # a full backlog may refuse: allowed
            continue
        kind = rng.randrange(4)
        try:
            if kind == 1:
                s.sendall(b"\xc0\x0e\x11\x80")
            elif kind == 2:
                s.sendall(rng.randbytes(200))
        except OSError:
            pass
        if kind == 3:
            s.close()
        else:
            socks.append(s)
    with Client(device.path, timeout=TIMEOUT, retries=0) as c:
        ping_check(c, tally, device)
        for s in socks:
            s.close()
        after = open_fds(device.proc.pid)
        ping_check(c, tally, device)
    if before >= 0 and after > before:
        tally.fail("hangs", f"device holds {after} descriptors after the flood, {before} before")


def run(seed: int, rounds: int, connections: int = 200, idle: float = 0.5) -> Tally:
    """``rounds`` random scenarios, an idle-timeout check and a flood of ``connections``."""
    rng = random.Random(seed)
    tally = Tally()
    slow = ("--timing", "realistic", "--exposure-ms", "100", "--processing-ms", str(SLOW_SEQUENCE_S * 1000 - 100))
    device = DeviceProcess("--tcp", "127.0.0.1:0", "--tcp-idle", str(idle), *slow)
    try:
        names = sorted(SCENARIOS)
        for k in range(rounds):
            SCENARIOS[names[k % len(names)] if k < len(names) else rng.choice(names)](device, rng, tally)
        tally.faults += 1
        with _raw(device) as s:  # idle: closed after `idle` s of silence
            if not closed_by_peer(s, idle + 2.0):
                tally.fail("hangs", f"an idle client was not closed within {idle + 2.0} s")
        flood(device, rng, tally, connections)
        if not device.alive:
            tally.fail("crashes", f"device exited {device.proc.returncode}")
    finally:
        rc = device.stop()
        if rc != 0:
            tally.fail("crashes", f"device exit code {rc} at stop")
        stderr_check(device, tally)
    return tally
