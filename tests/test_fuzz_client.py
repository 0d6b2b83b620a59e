"""The ground client against ports that answer garbage, slowly, never, or nonstop; replies meant
for other commands or for a killed client are never taken (fixed seeds; long run in bench/).

A reply that must be taken is waited for with a generous timeout (a hang guard); a short timeout
only where the reply must not come: no outcome depends on how fast the machine is."""

import threading

import pytest

from firmware_model.device.link import PtyLink
from ground.cli.main import main as cli_main
from ground.link.client import Client, Nack, ReplyTimeout
from ground.testing import port_faults
from ground.testing.port_faults import ANSWER_TIMEOUT, FakePort
from protocol import nsp, slip
from protocol.commands import Code, NackInfo, NackReason


@pytest.mark.parametrize("tcp", [False, True], ids=["pty", "socket"])
def test_every_misbehaviour_is_answered_or_a_link_error_in_time(tcp):
    tally = port_faults.run(seed=5, trials=len(port_faults.BEHAVIOURS), timeout=0.25, tcp=tcp)
    assert tally.failures == 0, tally.notes
    assert tally.messages == 9 and tally.faults == 8


@pytest.mark.parametrize("tcp", [False, True], ids=["pty", "socket"])
def test_a_peer_that_never_stops_sending_does_not_defeat_the_timeout(tcp):
    tally = port_faults.run_flood(seed=6, calls=3, timeout=0.2, tcp=tcp)
    assert tally.failures == 0, tally.notes


def test_noise_before_an_intact_reply_is_read_past():
    port = FakePort(seed=1, timeout=0.5)
    port.behaviour = "noise_then_good"
    try:
        with Client(port.url, timeout=ANSWER_TIMEOUT, retries=0) as c:
            assert c.ping() == f"ST16-EMU fake {port.nonces[-1]}"
    finally:
        port.close()


def test_a_late_reply_to_a_killed_client_is_not_taken_by_the_next_one(tmp_path):
    """The previous client sent GO and went away; its ACK arrives after the next client opened
    the port. The next client's GO (same first B bit) gets the device's BUSY NACK, not that ACK."""
    link, stop, seen, late_ack = PtyLink(), threading.Event(), [], threading.Event()

    def device():
        dec = slip.Decoder()
        while not stop.is_set():
            for event in dec.feed(link.read(0.01)):
                msg = nsp.decode(event.data)
                seen.append(msg)
                if len(seen) == 1:
                    late_ack.wait(ANSWER_TIMEOUT)  # the first GO is acknowledged once the next client has opened
                    link.write(nsp.reply_to(msg, b"\x0b").frame())
                else:
                    link.write(
                        nsp.reply_to(
                            msg, NackInfo(NackReason.BUSY, "sequence 1 still running").pack(), ack=False
                        ).frame()
                    )

    thread = threading.Thread(target=device, daemon=True)
    thread.start()
    try:
        first = Client(link.path, timeout=ANSWER_TIMEOUT)
        first._synced = True  # the killed client's command leaves at once
        first.write_raw(nsp.command(0x0E, 0x11, Code.GO, b"\x0b", b=True).frame())
        first.close()  # killed before the reply
        with Client(link.path, timeout=ANSWER_TIMEOUT) as second:
            late_ack.set()
            with pytest.raises(Nack) as exc:
                second.go(0x0B)
        assert exc.value.reason == NackReason.BUSY and len(seen) == 2 and seen[0].b == seen[1].b
    finally:
        stop.set()
        thread.join(2)
        link.close()


@pytest.mark.parametrize("behaviour", ["garbage", "too_slow", "silent"])
def test_ground_cli_names_the_failure_without_a_traceback_within_its_timeout(behaviour, capsys):
    port = FakePort(seed=2, timeout=0.2)
    port.behaviour = behaviour
    try:
        rc = cli_main(["--port", port.url, "--timeout", "0.2", "ping"])
    finally:
        port.close()
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert rc == 4 and len(lines) == 1, err  # the link's exit code, one line
    assert lines[0].startswith("st16-ground: ") and "PING: no" in lines[0] and "reply within 0.200 s" in lines[0], err
    assert "Traceback" not in err
    # PING is retried: three attempts, each given up after 0.2 s (a too-slow fake answers the
    # first only after the call has ended, so it reads no more)
    assert len(port.nonces) == (1 if behaviour == "too_slow" else 3)


def test_replies_to_other_commands_and_stale_b_bits_alone_are_malformed_not_taken():
    port = FakePort(seed=3, timeout=0.3)
    port.behaviour = "others_only"
    try:
        with Client(port.url, timeout=0.3, retries=0) as c:
            with pytest.raises(Exception) as exc:
                c.ping()
            assert "code 0x01" in str(exc.value) and not isinstance(exc.value, ReplyTimeout)
            assert c.stale_replies == 1
    finally:
        port.close()
