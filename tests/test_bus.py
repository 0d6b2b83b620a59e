"""Several heads on one link (docs/ICD.md section 14, issue 45): two heads behind one pty answer
each its own address, their replies never interleave on the line (checked on the raw bytes), a
frame to an unknown address is ignored and counted; the heads file's bad input is one line, exit 2."""

import json
import os
import select
import struct
import subprocess
import threading
import time

import guards
import numpy as np
import pytest

from firmware_model.device.bus import Bus
from firmware_model.device.device import Device
from firmware_model.device.heads import MountedSource, parse_heads
from firmware_model.device.link import PtyLink, serve
from firmware_model.reference_frames import quat_to_matrix
from ground.link.client import Client
from ground.testing.device_proc import device_command
from protocol import nsp, result, slip
from protocol.commands import APP_START_ADDRESS, Code, Combination

A, B = 0x0E, 0x0F
HOST = nsp.HOST_ADDRESS


class _Slow:
    """A solver that takes ``seconds``."""

    def __init__(self, seconds: float):
        self.seconds = seconds

    def __call__(self, ctx):
        time.sleep(self.seconds)
        return {"return_code": result.make_return_code(result.Status.OK)}


def _head(address: int, seconds: float = 0.05) -> Device:
    dev = Device(address, solver=_Slow(seconds), frame_source=lambda ctx: "frame")
    dev.runner.transfers.objects[0] = "catalog"
    return dev


@pytest.fixture
def line():
    """Two heads on a bus served on a pty; yields (bus, pty path)."""
    bus = Bus([_head(A), _head(B, 0.2)])
    link = PtyLink()
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(bus, link, stop), daemon=True)
    thread.start()
    yield bus, link.path
    stop.set()
    thread.join(guards.HANG_S)
    bus.wait_idle(guards.HANG_S)
    link.close()


def _raw_exchange(path: str, data: bytes, expect: int, bound: float = guards.REPLY_S) -> list[nsp.Message]:
    """Write ``data`` on the line; the ``expect`` frames read back, each decoded (CRC checked):
    an interleaved pair of replies would fail to decode."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    try:
        os.write(fd, data)
        decoder = slip.Decoder(nsp.MAX_MESSAGE)
        events: list = []
        deadline = time.monotonic() + bound
        while len(events) < expect and time.monotonic() < deadline:
            ready, _, _ = select.select([fd], [], [], 0.05)
            if ready:
                events += decoder.feed(os.read(fd, 65536))
        assert all(isinstance(e, slip.Frame) for e in events), events
        return [nsp.decode(e.data) for e in events]
    finally:
        os.close(fd)


def test_each_head_answers_its_own_address_and_an_unknown_address_is_counted(line):
    bus, path = line
    cmds = b"".join(nsp.command(dst, HOST, Code.PING).frame() for dst in (A, B, 0x42, B, A))
    replies = _raw_exchange(path, cmds, 4)
    assert [(m.src, m.dst) for m in replies] == [(A, HOST), (B, HOST), (B, HOST), (A, HOST)]
    assert all(f"addr=0x{m.src:02X}".encode() in m.data for m in replies)
    assert bus.unknown == 1 and bus.routed == {A: 2, B: 2}
    assert bus.by_address[A].counters.other_address == 3  # B's two and the unknown one


def test_late_replies_of_two_heads_never_interleave_on_the_line(line):
    """Both heads run a COMBINATION (answered late, from their workers) while PINGs to both go on:
    every frame on the line decodes, and each carries its head's address."""
    bus, path = line
    init = struct.pack("<I", APP_START_ADDRESS)
    for dst in (A, B):
        (rep,) = _raw_exchange(path, nsp.command(dst, HOST, Code.INIT, init).frame(), 1)
        assert rep.ack and rep.src == dst
    combo = Combination(0x0B, 0x0003, 3).pack()
    burst = (
        nsp.command(A, HOST, Code.COMBINATION, combo).frame() + nsp.command(B, HOST, Code.COMBINATION, combo).frame()
    )
    burst += b"".join(nsp.command(dst, HOST, Code.PING).frame() for dst in (A, B) * 20)
    replies = _raw_exchange(path, burst, 40 + 2, bound=guards.HANG_S)
    by_code: dict[tuple[int, int], int] = {}
    for m in replies:
        assert m.dst == HOST and m.src in (A, B)
        by_code[(m.src, m.code)] = by_code.get((m.src, m.code), 0) + 1
    assert by_code[(A, Code.PING)] == by_code[(B, Code.PING)] == 20
    assert by_code[(A, Code.COMBINATION)] == by_code[(B, Code.COMBINATION)] == 1  # one message: the sections
    assert all(m.ack for m in replies)


def test_the_client_addresses_one_head(line):
    bus, path = line
    with Client(path, timeout=guards.REPLY_S, device_address=B) as c:
        assert "addr=0x0F" in c.ping()
    with Client(path, timeout=guards.REPLY_S, device_address=A) as c:
        assert "addr=0x0E" in c.ping()


def test_the_heads_command_shows_each_heads_state(line):
    import argparse

    from ground.link.commands import COMMANDS

    bus, path = line
    run = COMMANDS["heads"][2]
    with Client(path, timeout=0.3, device_address=A) as c:
        c.init()
        out = run(c, argparse.Namespace(addresses=[A, B, 0x42]))["heads"]
        assert c.device_address == A
    assert out["0x0E"]["mode"] == "application" and out["0x0F"]["mode"] == "bootloader"
    assert out["0x0E"]["accepted"] == 2 and not out["0x0E"]["busy"] and "status" not in out["0x0E"]
    assert out["0x42"]["answers"] is False
    assert bus.unknown >= 1
    with Client(path, timeout=guards.REPLY_S, device_address=A) as c:
        c.go_and_wait(timeout=guards.REPLY_S)
        out = run(c, argparse.Namespace(addresses=[A, B]))["heads"]
    assert out["0x0E"]["status"] == "OK" and out["0x0E"]["result_ready"] and "status" not in out["0x0F"]


def test_a_bus_refuses_duplicate_addresses_and_more_than_four_heads():
    with pytest.raises(ValueError, match="two heads at address 0x0E"):
        Bus([Device(A), Device(A)])
    with pytest.raises(ValueError, match="1-4 heads"):
        Bus([Device(a) for a in range(5)])


def test_a_mounted_source_renders_the_body_attitude_through_the_mounting():
    seen = {}

    def source(ctx, mount=None):
        seen["mount"] = mount
        return "frame"

    q = [np.sqrt(0.5), 0.0, np.sqrt(0.5), 0.0]
    (head,) = parse_heads({"heads": [{"address": "0x0F", "mount_q": q}]})
    assert MountedSource(source, head.mount)(None) == "frame"
    body = quat_to_matrix([1.0, 0.0, 0.0, 0.0])  # the body aligned with ICRS
    # v_sensor = M @ v_body: this head's attitude is its mounting; its boresight (+z) is the body's -x
    np.testing.assert_allclose(seen["mount"] @ body, quat_to_matrix(q), atol=1e-12)
    np.testing.assert_allclose(seen["mount"].T @ [0, 0, 1], [-1, 0, 0], atol=1e-7)


@pytest.mark.parametrize(
    "heads, says",
    [
        ({"heads": [{"address": "0x0E"}, {"address": 14}]}, "duplicate address 0x0E"),
        ({"heads": [{"address": "0x100"}]}, "outside 0x00-0xFF"),
        ({"heads": [{"address": -1}]}, "outside 0x00-0xFF"),
        ({"heads": [{"address": 1, "mount_q": [1, 0, 0, 0.1]}]}, "is not 1"),
        ({"heads": [{"address": a} for a in range(5)]}, "5 heads; a bus carries 1-4"),
        ({"heads": []}, "0 heads"),
        ({"heads": [{"address": 1, "mount": [1, 0, 0, 0]}]}, "unknown key"),
    ],
)
def test_bad_heads_files_are_one_line_exit_2(tmp_path, heads, says):
    path = tmp_path / "heads.json"
    path.write_text(json.dumps(heads))
    run = subprocess.run(
        device_command() + ["--pty", "--heads", str(path)], capture_output=True, text=True, timeout=guards.HANG_S
    )
    assert run.returncode == 2 and run.stdout == ""
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and says in lines[0] and str(path) in lines[0], run.stderr


def test_a_missing_heads_file_is_one_line_exit_2(tmp_path):
    run = subprocess.run(
        device_command() + ["--pty", "--heads", str(tmp_path / "none.json")],
        capture_output=True,
        text=True,
        timeout=guards.HANG_S,
    )
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1 and "none.json" in run.stderr
