"""BUSY (docs/ICD.md §7): while a sequence runs, GO with COMMAND is NACKed BUSY and COMBINATION
gets its failure reply, both texts naming the running sequence; a GO without COMMAND terminates it;
the device keeps answering everything else."""

import struct
import threading
import types

import pytest
from manual_clock import ManualClock

from firmware_model.device.device import Device
from firmware_model.device.sequence import Timing
from protocol import nsp, result, slip
from protocol.commands import Code, Combination, NackInfo, NackReason, ReadRange, SequenceState


def _send(dev, code, data=b""):
    frames = dev.receive(nsp.command(0x0E, 0x11, code, data).frame())
    return [nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(f)[0].data) for f in frames]


class _Gated:
    """Solver that runs until its gate opens."""

    def __init__(self):
        self.gate = threading.Event()

    def __call__(self, ctx):
        self.gate.wait(10)
        return {"return_code": result.make_return_code(result.Status.OK)}


def _busy_text(dev, code, data) -> str:
    (rep,) = _send(dev, code, data)
    info = NackInfo.unpack(rep.data)
    assert not rep.ack and info.reason == NackReason.BUSY
    return info.text


def test_go_and_combination_refused_busy_naming_the_running_sequence():
    solver = _Gated()
    dev = Device(solver=solver, frame_source=lambda ctx: "frame")
    dev.runner.transfers.objects[0] = "catalog"
    assert _send(dev, Code.INIT, struct.pack("<I", 0x2000))[0].ack
    for seq in (1, 2):
        solver.gate.clear()
        assert _send(dev, Code.GO, b"\x0b")[0].ack
        assert _busy_text(dev, Code.GO, b"\x0b") == f"sequence {seq} still running"
        # COMBINATION's refusal is the ICD's failure reply: the sequence state, then the text
        (rep,) = _send(dev, Code.COMBINATION, Combination(0x0B, 0x0003, 3).pack())
        assert (
            not rep.ack
            and rep.final
            and rep.data == bytes([SequenceState.RUNNING]) + f"sequence {seq} still running".encode()
        )
        assert b"BUSY" in _send(dev, Code.PING)[0].data
        assert _send(dev, Code.READ_EDAC, ReadRange(0x4C, 4).pack())[0].data[2:] == bytes(4)
        solver.gate.set()
        assert dev.wait_idle(5)
        assert int(result.parse(dev.runner.result)["sequence"]) == seq


def test_a_go_without_command_terminates_the_running_sequence_and_is_a_no_op_otherwise():
    """ICD page 1-35916: GO starts or terminates a sequence. The terminated sequence's result says
    TERMINATED with no attitude, its solver's late answer is dropped, and a COMBINATION waiting
    for it gets the failure reply with state TERMINATED."""
    solver = _Gated()
    dev = Device(solver=solver, frame_source=lambda ctx: "frame")
    dev.runner.transfers.objects[0] = "catalog"
    assert _send(dev, Code.INIT, struct.pack("<I", 0x2000))[0].ack
    assert _send(dev, Code.GO, b"\x03")[0].ack and not dev.busy  # nothing runs: a no-op
    assert result.status_of(int(result.parse(dev.runner.result)["return_code"])) == result.Status.NO_RESULT
    replies: list = []
    dev.late_reply = replies.append
    assert _send(dev, Code.COMBINATION, Combination(0x0B, 0x0003, 3).pack()) == []  # answered when done
    assert dev.busy
    assert _send(dev, Code.GO, b"\x03")[0].ack and not dev.busy
    rec = result.parse(dev.runner.result)
    assert result.status_of(int(rec["return_code"])) == result.Status.TERMINATED and not rec["quaternion"].any()
    assert int(rec["sequence"]) == 1 and b"terminated by GO 0x03" in bytes(rec["ext"]["reason"])
    assert _send(dev, Code.READ_EDAC, ReadRange(0x4C, 4).pack())[0].data[2:] == struct.pack("<I", 2616)
    solver.gate.set()  # the solver finishes late: its answer is dropped
    for _ in range(200):
        if replies:
            break
        threading.Event().wait(0.01)
    (frames,) = replies
    reply = nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(frames[0])[0].data)
    assert not reply.ack and reply.data[0] == SequenceState.TERMINATED
    rec = result.parse(dev.runner.result)
    assert result.status_of(int(rec["return_code"])) == result.Status.TERMINATED


def test_realistic_timing_holds_the_result_busy(monkeypatch):
    """The device's clock is a manual one and its hold's sleep a gate the test opens: the solve
    takes 0.05 s by that clock, so the result is held 0.25 s more, busy until then."""
    import firmware_model.device.sequence as sequence

    clock, held, holding, release = ManualClock(), [], threading.Event(), threading.Event()

    def hold(seconds):
        held.append(seconds)
        holding.set()
        assert release.wait(60)  # a hang guard

    monkeypatch.setattr(sequence, "time", types.SimpleNamespace(sleep=hold, perf_counter=sequence.time.perf_counter))

    def solver(ctx):
        clock.advance(0.05)
        return {"return_code": 0}

    dev = Device(solver=solver, frame_source=lambda ctx: "frame", clock=clock, clock_source=clock)
    dev.runner.transfers.objects[0] = "catalog"
    dev.runner.timing = Timing(exposure_s=0.1, processing_s=0.2)
    assert _send(dev, Code.INIT, struct.pack("<I", 0x2000))[0].ack
    assert _send(dev, Code.GO, b"\x0b")[0].ack
    assert holding.wait(60)  # the solve is done; the result is held
    assert _busy_text(dev, Code.GO, b"\x0b") == "sequence 1 still running"
    assert _send(dev, Code.READ_EDAC, ReadRange(0x4C, 4).pack())[0].data[2:] == bytes(4)
    release.set()
    assert dev.wait_idle(60)
    assert held == [pytest.approx(0.25)] and dev.runner.result_ready


def test_timing_options():
    from firmware_model.device import cli

    args = cli.build_parser().parse_args(
        ["--pty", "--timing", "realistic", "--exposure-ms", "50", "--processing-ms", "70"]
    )
    timing = cli.build_device(args).runner.timing
    assert timing is not None and timing.hold("built") == pytest.approx(0.12)
    assert cli.build_device(cli.build_parser().parse_args(["--pty"])).runner.timing is None
    realistic = cli.build_device(cli.build_parser().parse_args(["--pty", "--timing", "realistic"])).runner.timing
    assert realistic is not None and realistic.hold("built") == pytest.approx(0.5)  # about 2 Hz (ICD page 1-35923)
    with pytest.raises(SystemExit):
        cli.main(["--pty", "--exposure-ms", "50"])  # needs --timing realistic
