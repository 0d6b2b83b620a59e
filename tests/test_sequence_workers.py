"""The threads GO sequences run on: kept between sequences, so a sequence after a COMBINATION runs
where the one after a GO does (a fresh thread per sequence took the malloc arena of whichever
thread ended last, and its capture page-faulted into new memory); a new one only beside a
sequence that a terminate or a reset abandoned while it still computes."""

import struct
import threading

import pytest
from guards import HANG_S

from firmware_model.device.device import Device
from protocol import nsp, result, slip
from protocol.commands import Code, Combination


def _send(dev, code, data=b""):
    """The reply messages of one command."""
    replies = []
    for frame in dev.receive(nsp.command(0x0E, 0x11, code, data).frame()):
        (event,) = slip.Decoder(nsp.MAX_MESSAGE).feed(frame)
        assert isinstance(event, slip.Frame)
        replies.append(nsp.decode(event.data))
    return replies


class _Recorder:
    """Solver that keeps the thread each sequence ran on; the sequences in ``gated`` wait for
    :attr:`gate`."""

    def __init__(self, gated=()):
        self.threads: list[threading.Thread] = []
        self.gated = set(gated)
        self.gate = threading.Event()

    def __call__(self, ctx):
        self.threads.append(threading.current_thread())
        if ctx.sequence in self.gated:
            self.gate.wait(HANG_S)
        return {"return_code": result.make_return_code(result.Status.OK)}


def _device(solver) -> Device:
    dev = Device(solver=solver, frame_source=lambda ctx: "frame")
    dev.runner.transfers.objects[0] = "catalog"
    assert _send(dev, Code.INIT, struct.pack("<I", 0x2000))[0].ack
    return dev


@pytest.mark.timeout(HANG_S)
def test_a_go_right_after_a_combination_runs_on_the_thread_of_the_sequences_before():
    solver = _Recorder()
    dev = _device(solver)
    assert _send(dev, Code.GO, b"\x0b")[0].ack and dev.wait_idle(HANG_S)
    answered = threading.Event()

    def late(frames):  # the COMBINATION's answer; its host sends the next GO at once
        assert _send(dev, Code.GO, b"\x0b")[0].ack
        answered.set()

    dev.late_reply = late
    assert _send(dev, Code.COMBINATION, Combination(0x0B, 0x0003, 3).pack()) == []
    assert answered.wait(HANG_S) and dev.wait_idle(HANG_S)
    assert _send(dev, Code.GO, b"\x0b")[0].ack and dev.wait_idle(HANG_S)
    assert int(result.parse(dev.runner.result)["sequence"]) == 4 == len(solver.threads)
    assert all(t is solver.threads[0] for t in solver.threads)  # one thread each used to have its own
    assert dev.runner.workers == 1


@pytest.mark.timeout(HANG_S)
def test_a_sequence_beside_an_abandoned_one_gets_a_second_worker_and_both_are_kept():
    solver = _Recorder(gated={1})
    dev = _device(solver)
    assert _send(dev, Code.GO, b"\x0b")[0].ack
    assert _send(dev, Code.GO, b"\x03")[0].ack and not dev.busy  # terminated: its solver still runs
    assert _send(dev, Code.GO, b"\x0b")[0].ack and dev.wait_idle(HANG_S)  # done beside it
    assert int(result.parse(dev.runner.result)["sequence"]) == 2 and dev.runner.workers == 2
    solver.gate.set()
    for _ in range(3):
        assert _send(dev, Code.GO, b"\x0b")[0].ack and dev.wait_idle(HANG_S)
    assert int(result.parse(dev.runner.result)["sequence"]) == 5 and dev.runner.workers == 2
    assert len({id(t) for t in solver.threads}) == 2
