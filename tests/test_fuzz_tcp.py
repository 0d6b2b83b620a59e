"""TCP link policy (firmware_model.device.link.TcpLink): one active client, the newest takes over, idle
clients closed, cut frames ended, a connection flood absorbed; each proved against a device."""

import random
import socket
import threading
import time

import pytest

from firmware_model.device.device import Device
from firmware_model.device.link import TcpLink, serve
from ground.link.client import Client, LinkDown
from ground.testing import tcp_faults
from ground.testing.device_proc import DeviceProcess
from ground.testing.tally import Tally


@pytest.fixture
def tcp_device():
    """An in-process device on a TcpLink with a 0.4 s idle timeout: (link, device)."""
    link, stop, device = TcpLink("127.0.0.1", 0, idle_timeout=0.4), threading.Event(), Device()
    thread = threading.Thread(target=serve, args=(device, link, stop), daemon=True)
    thread.start()
    yield link, device
    stop.set()
    thread.join(2)
    link.close()


def test_the_newest_client_takes_over_and_the_old_one_gets_a_link_error(tcp_device):
    link, _ = tcp_device
    with Client(link.path, timeout=1.0, retries=0) as a:
        assert a.ping().startswith("ST16-EMU")
        with Client(link.path, timeout=1.0, retries=0) as b:
            assert b.ping().startswith("ST16-EMU")  # b connected last: a is closed
            with pytest.raises(LinkDown):
                a.ping()
            assert b.ping().startswith("ST16-EMU") and link.taken_over == 1


def test_a_late_reply_goes_only_to_the_client_that_asked():
    """A's COMBINATION waits for a slow sequence; B takes over meanwhile and gets only its own
    PING reply (it used to receive A's COMBINATION reply)."""
    with DeviceProcess("--tcp", "127.0.0.1:0", "--timing", "realistic", "--processing-ms", "500") as device:
        tally = Tally()
        for seed in range(3):
            tcp_faults.late_takeover(device, random.Random(seed), tally)
        assert tally.failures == 0, tally.notes
        assert tally.faults == 3 and device.alive


def test_a_silent_client_is_closed_after_the_idle_timeout_and_locks_nobody_out(tcp_device):
    link, _ = tcp_device
    silent = socket.create_connection(link.path[len("socket://") :].rsplit(":", 1))
    try:
        assert tcp_faults.closed_by_peer(silent, 2.0)
        assert link.idle_closed == 1
    finally:
        silent.close()
    with socket.create_connection(link.path[len("socket://") :].rsplit(":", 1)):
        with Client(link.path, timeout=1.0, retries=0) as c:
            t0 = time.monotonic()
            assert c.ping().startswith("ST16-EMU") and time.monotonic() - t0 < 1.0


def test_a_frame_cut_by_a_disconnect_is_ended_and_counted(tcp_device):
    link, device = tcp_device
    with socket.create_connection(link.path[len("socket://") :].rsplit(":", 1)) as cut:
        cut.sendall(b"\x0e\x11\x80")  # no end: the client vanishes mid-message
        deadline = time.monotonic() + 2.0
        while device._decoder.pending < 3 and time.monotonic() < deadline:  # once the device holds them
            time.sleep(0.01)
    with Client(link.path, timeout=1.0, retries=0) as c:
        assert c.ping().startswith("ST16-EMU")
        assert c.diagnostic().runt == 1  # ended by the link when the client went, not joined to PING


def test_tcp_scenarios_and_a_flood_of_100_connections_leave_a_serving_device():
    tally = tcp_faults.run(seed=2, rounds=len(tcp_faults.SCENARIOS), connections=100, idle=0.5)
    assert tally.failures == 0, tally.notes
    assert tally.faults >= 100 and tally.messages >= 10
