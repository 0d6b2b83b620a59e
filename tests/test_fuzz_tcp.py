"""TCP link policy (firmware_model.device.link.TcpLink): one active client, the newest takes over, idle
clients closed, cut frames ended, a connection flood absorbed; each proved against a device.

No clock decides an outcome: replies that must come are waited for with tests/guards.py's hang
guards, a race is set up by events (a sequence held open until the test releases it), and the one
timing the policy has (the idle timeout) is tested with a guard far beyond it."""

import socket
import threading
import time

import numpy as np
import pytest
from guards import HANG_S, REPLY_S

from firmware_model.device.device import Device
from firmware_model.device.link import TcpLink, serve
from firmware_model.pipeline.raw_frame import Frame
from ground.link.client import Client, LinkDown
from ground.testing import tcp_faults
from protocol import nsp, result, slip
from protocol.commands import GO_OPERATIONAL, Code, Combination, Slot


def _serve(device: Device, idle_timeout: float):
    link, stop = TcpLink("127.0.0.1", 0, idle_timeout=idle_timeout), threading.Event()
    thread = threading.Thread(target=serve, args=(device, link, stop), daemon=True)
    thread.start()
    return link, stop, thread


@pytest.fixture
def tcp_device():
    """An in-process device on a TcpLink with a 0.4 s idle timeout: (link, device)."""
    device = Device()
    link, stop, thread = _serve(device, 0.4)
    yield link, device
    stop.set()
    thread.join(HANG_S)
    link.close()


def _address(link: TcpLink) -> tuple[str, int]:
    host, port = link.path[len("socket://") :].rsplit(":", 1)
    return host, int(port)


def test_the_newest_client_takes_over_and_the_old_one_gets_a_link_error(tcp_device):
    link, _ = tcp_device
    with Client(link.path, timeout=REPLY_S, retries=0) as a:
        assert a.ping().startswith("ST16-EMU")
        with Client(link.path, timeout=REPLY_S, retries=0) as b:
            assert b.ping().startswith("ST16-EMU")  # b connected last: a is closed
            with pytest.raises(LinkDown):
                a.ping()
            assert b.ping().startswith("ST16-EMU") and link.taken_over == 1


def _replies(sock: socket.socket, decoder, want: int) -> list[int]:
    """The codes of the next ``want`` NSP messages ``sock`` receives (a hang guard bounds the wait)."""
    codes: list[int] = []
    sock.settimeout(HANG_S)
    while len(codes) < want:
        data = sock.recv(65536)
        assert data, f"the device closed the connection after {codes}"
        codes += [nsp.decode(e.data).code for e in decoder.feed(data) if isinstance(e, slip.Frame)]
    return codes


def test_a_late_reply_goes_only_to_the_client_that_asked(synthetic_catalog):
    """A's COMBINATION waits for its sequence, held open by the test; B takes over meanwhile and gets
    only its own PING replies: A's reply, produced once the sequence is released, is dropped and
    counted (it used to go to B). Events, not sleeps, order the race."""
    started, release = threading.Event(), threading.Event()

    def held(ctx):  # the sequence's solve: runs until the test releases it
        started.set()
        assert release.wait(HANG_S)
        return {"return_code": result.make_return_code(result.Status.NO_MATCH)}

    device = Device(solver=held, frame_source=lambda ctx: Frame(pixels=np.zeros((8, 8), np.uint16)))
    device.transfers.objects[Slot.CATALOG] = synthetic_catalog(20)
    link, stop, thread = _serve(device, HANG_S)
    try:
        with Client(link.path, timeout=REPLY_S) as c:
            if "BOOTLOADER" in c.ping():
                c.init()
        combination = nsp.command(
            nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, Code.COMBINATION, Combination(GO_OPERATIONAL, 1).pack()
        )
        ping = nsp.command(nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, Code.PING, b"").frame()
        with socket.create_connection(_address(link), timeout=HANG_S) as a_sock:
            a_sock.sendall(combination.frame())
            assert started.wait(HANG_S)  # the sequence runs: A's reply is pending
            with socket.create_connection(_address(link), timeout=HANG_S) as b_sock:
                decoder = slip.Decoder(nsp.MAX_MESSAGE)
                b_sock.sendall(ping)
                got = _replies(b_sock, decoder, 1)  # B is served: it took over
                release.set()  # A's sequence ends: its reply is ready now
                assert device.wait_idle(HANG_S)
                deadline = time.monotonic() + HANG_S  # a hang guard: the drop is counted at once
                while link.late_dropped < 1 and time.monotonic() < deadline:
                    time.sleep(0.01)
                b_sock.sendall(ping)
                got += _replies(b_sock, decoder, 1)
        assert got == [Code.PING, Code.PING], got  # never A's COMBINATION reply
        assert link.late_dropped == 1 and link.taken_over == 1
    finally:
        release.set()
        stop.set()
        thread.join(HANG_S)
        link.close()


def test_a_silent_client_is_closed_after_the_idle_timeout(tcp_device):
    link, _ = tcp_device
    silent = socket.create_connection(_address(link))
    try:
        assert tcp_faults.closed_by_peer(silent, HANG_S)  # 0.4 s idle; the guard far beyond it
        assert link.idle_closed == 1
    finally:
        silent.close()


def test_a_silent_client_locks_nobody_out():
    """With an idle timeout longer than the client's reply guard, only the takeover can serve the
    newcomer: a silent connection that held the line would time the PING out."""
    device = Device()
    link, stop, thread = _serve(device, 4 * REPLY_S)
    try:
        with socket.create_connection(_address(link)):
            with Client(link.path, timeout=REPLY_S, retries=0) as c:
                assert c.ping().startswith("ST16-EMU")
        assert link.idle_closed == 0
    finally:
        stop.set()
        thread.join(HANG_S)
        link.close()


def test_a_frame_cut_by_a_disconnect_is_ended_and_counted(tcp_device):
    link, device = tcp_device
    with socket.create_connection(_address(link)) as cut:
        cut.sendall(b"\x0e\x11\x80")  # no end: the client vanishes mid-message
        deadline = time.monotonic() + HANG_S  # a hang guard: once the device holds them
        while device._decoder.pending < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert device._decoder.pending == 3
    with Client(link.path, timeout=REPLY_S, retries=0) as c:
        assert c.ping().startswith("ST16-EMU")
        assert c.diagnostic().runt == 1  # ended by the link when the client went, not joined to PING


def test_tcp_scenarios_and_a_flood_of_100_connections_leave_a_serving_device(monkeypatch):
    """ground.testing.tcp_faults' campaign with its waits as hang guards: replies within
    guards.REPLY_S, the idle close within guards.HANG_S; its late takeover (a race set up by a
    sleep) is left to test_a_late_reply_goes_only_to_the_client_that_asked, which sets it up by events."""
    monkeypatch.setattr(tcp_faults, "TIMEOUT", REPLY_S)
    closed_by_peer = tcp_faults.closed_by_peer
    monkeypatch.setattr(tcp_faults, "closed_by_peer", lambda sock, within: closed_by_peer(sock, HANG_S))
    monkeypatch.delitem(tcp_faults.SCENARIOS, "late_takeover")
    tally = tcp_faults.run(seed=2, rounds=len(tcp_faults.SCENARIOS), connections=100, idle=0.5)
    assert tally.failures == 0, tally.notes
    assert tally.faults >= 100 and tally.messages >= 10
