"""The device against the ICD pages where they speak (docs/ICD.md §6-§8, issue 39): TIME and the
device clock, IMAGE Rectangular Poke and image injection, the functional processor's boot, the
cached triangle table, the result's epoch on the device clock. In-process devices with a manual
clock source; the pty conformance suite (tests/conformance/) checks the same from the wire."""

import struct
import threading

import numpy as np
import pytest
from manual_clock import ManualClock

from firmware_model.device import cli
from firmware_model.device.clock import ClockModel
from firmware_model.device.device import Device
from firmware_model.device.sequence import BOOT_MESSAGE, Timing
from protocol import edac, nsp, result, slip
from protocol.commands import (
    Code,
    NackInfo,
    NackReason,
    RectangularPoke,
    SlotRequest,
    TimeReply,
    XferBegin,
    XferState,
    XferStatus,
)


def _send(dev, code, data=b"", arrived=None):
    frames = dev.receive(nsp.command(0x0E, 0x11, code, data).frame(), arrived)
    return [nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(f)[0].data) for f in frames]


def _ok(dev, code, data=b"", arrived=None) -> bytes:
    (rep,) = _send(dev, code, data, arrived)
    assert rep.ack, NackInfo.unpack(rep.data)
    return rep.data


def _nack(dev, code, data=b"") -> NackInfo:
    (rep,) = _send(dev, code, data)
    assert not rep.ack
    return NackInfo.unpack(rep.data)


def _time(dev, arrived=None) -> int:
    data = _ok(dev, Code.TIME, arrived=arrived)
    assert len(data) == 6
    return TimeReply.unpack(data).micros


def test_time_counts_microseconds_from_the_epoch_at_the_drifted_rate_with_lsb_zero():
    """ICD page 1-35918: 48 bits of microseconds, LSB 0; the model's epoch and drift are exact."""
    source = ManualClock(1000.0)
    dev = Device(clock_model=ClockModel(epoch_s=10.0, drift_ppm=50.0), clock_source=source)
    assert _time(dev) == 10_000_000
    source.advance(100.0)
    assert _time(dev) == 10_000_000 + 100_005_000  # 100 s at +50 ppm
    source.advance(0.0000013)  # 1.3 us later: an odd count is never reported
    t = _time(dev)
    assert t % 2 == 0 and t == 110_005_000 + 0 or t == 110_005_002


def test_time_is_latched_when_the_final_fend_arrived_not_when_it_is_handled():
    source = ManualClock(50.0)
    dev = Device(clock_source=source)
    source.advance(2.0)  # handled at 2 s; the frame's last byte arrived on the line at 1.5 s
    assert _time(dev, arrived=50.0 + 1.5) == 1_500_000
    assert _time(dev) == 2_000_000


def test_time_rolls_over_at_2_to_the_48_microseconds():
    source = ManualClock(0.0)
    dev = Device(clock_model=ClockModel(epoch_s=(1 << 48) / 1e6 - 1.0), clock_source=source)
    before = _time(dev)
    source.advance(2.0)
    assert before > (1 << 48) - 2_000_000 and _time(dev) == pytest.approx(1_000_000, abs=2)


def test_time_jitter_is_seeded_and_bounded_by_the_model():
    def polls(seed):
        source = ManualClock(0.0)
        dev = Device(clock_model=ClockModel(jitter_us=20.0, seed=seed), clock_source=source)
        out = []
        for _ in range(200):
            source.advance(1.0)
            out.append(_time(dev) - round(source() * 1e6))
        return np.array(out)

    a, b = polls(1), polls(1)
    assert np.array_equal(a, b) and not np.array_equal(a, polls(2))
    assert 10 < a.std() < 30 and np.abs(a).max() < 20 * 6


def test_a_reset_starts_the_clock_again_from_its_epoch():
    source = ManualClock(0.0)
    dev = Device(clock_model=ClockModel(epoch_s=5.0), clock_source=source)
    source.advance(30.0)
    assert _time(dev) == 35_000_000
    dev.reset()
    assert _time(dev) == 5_000_000


def test_time_with_a_data_field_is_nacked_and_an_old_xfer_begin_on_0x13_opens_nothing():
    dev = Device()
    old_begin = XferBegin(0, 1000, 0xDEADBEEF).pack()  # XFER BEGIN's 9 bytes, on its old code
    info = _nack(dev, Code.TIME, old_begin)
    assert info.reason == NackReason.BAD_LENGTH and "XFER BEGIN" in info.text and "0x1A" in info.text
    status = XferStatus.unpack(_ok(dev, Code.XFER_STATUS, SlotRequest(0).pack()))
    assert status.state == XferState.NONE
    assert XferStatus.unpack(_ok(dev, Code.XFER_BEGIN, old_begin)).state == XferState.RECEIVING  # 0x1A works


def test_clock_options_out_of_range_are_one_line_and_exit_2(capsys):
    for opts in (["--clock-drift-ppm", "1001"], ["--clock-epoch-s", "-1"], ["--clock-jitter-us", "nan"]):
        with pytest.raises(SystemExit) as exc:
            cli.main(["--pty", *opts])
        assert exc.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert "clock" in err[-1] and "Traceback" not in "".join(err)


# ------------------------------------------------------------------ image injection


def _app(dev):
    _ok(dev, Code.INIT, struct.pack("<I", 0x2000))
    return dev


def _small_device(**kw):
    return _app(Device(sensor_shape=(8, 12), **kw))


def test_rectangular_poke_writes_the_buffer_and_refuses_bad_rectangles_leaving_it_unchanged():
    dev = _small_device()
    values = np.arange(6, dtype="<u2").reshape(2, 3) + 100
    poke = RectangularPoke(0, 1, 2, 2, 3, values.tobytes())
    assert _ok(dev, Code.IMAGE, poke.pack()) == poke.head()
    buf = dev.runner.buffers[0]
    assert np.array_equal(buf[1:3, 2:5], values) and buf.sum() == values.sum()
    before = buf.copy()
    bad = (
        (RectangularPoke(0, 7, 0, 2, 1, bytes(4)), NackReason.OUT_OF_RANGE),  # past the last row
        (RectangularPoke(0, 0, 11, 1, 2, bytes(4)), NackReason.OUT_OF_RANGE),  # past the last column
        (RectangularPoke(0, 0, 0, 0, 1, b""), NackReason.OUT_OF_RANGE),  # no rows
        (RectangularPoke(0, 0, 0, 2, 2, bytes(6)), NackReason.BAD_LENGTH),  # 3 of 4 pixels
        (RectangularPoke(2, 0, 0, 1, 1, bytes(2)), NackReason.BAD_PARAMETER),  # no buffer 2
    )
    for poke, reason in bad:
        info = _nack(dev, Code.IMAGE, poke.pack())
        assert info.reason == reason, (poke, info)
    assert np.array_equal(dev.runner.buffers[0], before)
    assert _nack(dev, Code.IMAGE, poke.pack()[:9]).reason == NackReason.BAD_LENGTH  # a short head


def test_a_go_with_injected_processes_image_buffer_0_instead_of_exposing():
    seen = []

    def solver(ctx):
        seen.append(ctx.frame)
        return {"return_code": result.make_return_code(result.Status.TOO_FEW_STARS)}

    dev = _small_device(solver=solver, frame_source=lambda ctx: pytest.fail("the detector exposed"))
    dev.runner.transfers.objects[0] = "catalog"
    values = np.full((8, 12), 300, "<u2")
    for row in range(8):
        _ok(dev, Code.IMAGE, RectangularPoke(0, row, 0, 1, 12, values[row].tobytes()).pack())
    _ok(dev, Code.GO, bytes([0x0B | 0x40]))
    assert dev.wait_idle(30)
    (frame,) = seen
    assert frame.pattern == "RGGB" and np.array_equal(frame.pixels, values) and frame.white_level == 4095
    rc = int(result.parse(dev.runner.result)["return_code"])
    assert not rc & result.ReturnBits.DETECTOR_IMAGE  # not from the detector
    dev.runner.buffers[0][:] = 0  # the sequence had its own copy
    assert frame.pixels.max() == 300


# ------------------------------------------------------------------ boot, cadence, epoch


def test_a_go_with_load_nand_boots_the_functional_processor_and_leaves_its_boot_message():
    dev = Device()
    dev.runner.timing = Timing(boot_s=0.3)
    assert dev.edac_image()[edac.BOOT_MESSAGE_AT : edac.BOOT_MESSAGE_AT + 64] == bytes(64)
    _ok(dev, Code.GO, b"\x02")  # LOAD_NAND alone: boot, no sequence
    assert dev.busy and not dev.app_mode
    assert _nack(dev, Code.GO, b"\x0b").reason == NackReason.BUSY
    assert _nack(dev, Code.READ_RESULT, struct.pack("<HH", 0, 4)).reason == NackReason.WRONG_MODE
    assert dev.wait_idle(30) and dev.app_mode
    message = dev.edac_image()[edac.BOOT_MESSAGE_AT : edac.BOOT_MESSAGE_AT + 64].rstrip(b"\0").decode()
    assert message == BOOT_MESSAGE and "ASIC ID" in message


def test_fast_timing_boots_at_once():
    dev = Device()
    _ok(dev, Code.GO, b"\x02")
    assert dev.app_mode and not dev.busy and dev.runner.boot_message == BOOT_MESSAGE


def test_the_cached_triangle_table_makes_the_first_go_slower_and_later_ones_faster():
    """ICD page 1-35924: bits 2 and 5 with the control structure's cache bit."""
    from firmware_model.device.sensor_input import DeviceParams

    timing = Timing()
    dev = Device()
    runner = dev.runner
    cached = DeviceParams(cache_triangle_table=True)
    holds = [timing.hold(runner._table(code, cached)) for code in (0x2F, 0x2F, 0x0B, 0x2F)]
    assert holds == pytest.approx([0.6, 0.35, 0.5, 0.35])
    dev.reset()  # a reset loses the cache
    assert timing.hold(runner._table(0x2F, cached)) == pytest.approx(0.6)
    assert [timing.hold(runner._table(0x2F, DeviceParams())) for _ in range(2)] == pytest.approx([0.5, 0.5])


def test_the_result_epoch_is_the_exposure_mid_time_on_the_device_clock():
    source, posix = ManualClock(500.0), ManualClock(1.7e9)
    gate = threading.Event()

    def solver(ctx):
        gate.wait(30)
        return {"return_code": 0, "ext.utc_epoch": ctx.started + 0.05}  # the exposure's mid-time

    dev = _app(
        Device(
            solver=solver,
            frame_source=lambda ctx: "frame",
            clock=posix,
            clock_source=source,
            clock_model=ClockModel(epoch_s=7.0, drift_ppm=100.0),
        )
    )
    dev.runner.transfers.objects[0] = "catalog"
    source.advance(3.0)
    _ok(dev, Code.GO, b"\x0b")
    gate.set()
    assert dev.wait_idle(30)
    rec = result.parse(dev.runner.result)
    device_at_go = 7.0 + 3.0 * (1 + 100e-6)
    # to the resolution of POSIX seconds near 1.7e9 (0.24 us)
    assert float(rec["epoch"]) == pytest.approx(device_at_go + 0.05 * (1 + 100e-6), abs=1e-6)
    assert float(rec["ext"]["utc_epoch"]) == pytest.approx(1.7e9 + 0.05, abs=1e-6)


def test_the_attitude_covariance_is_the_upper_triangle_row_by_row():
    """ICD page 1-35920: matching telemetry +0x80, six f64, the upper triangle."""
    from firmware_model.pipeline.result_fields import upper_triangle_by_rows

    cov = np.array([[1.0, 4.0, 5.0], [4.0, 2.0, 6.0], [5.0, 6.0, 3.0]])
    assert upper_triangle_by_rows(cov).tolist() == [1.0, 4.0, 5.0, 2.0, 6.0, 3.0]


def test_the_parameter_file_sets_the_clock_model_and_the_options_win(tmp_path):
    from firmware_model.device.sensor_input import DeviceParams
    from protocol.commands import SlotRejected

    params = tmp_path / "params.json"
    params.write_text('{"clock_drift_ppm": 50, "clock_epoch_s": 12.5, "clock_jitter_us": 3}')
    args = cli.build_parser().parse_args(["--pty", "--params", str(params), "--clock-jitter-us", "7"])
    model = cli.build_device(args).device_clock.model
    assert (model.drift_ppm, model.epoch_s, model.jitter_us) == (50.0, 12.5, 7.0)
    for bad in (b'{"clock_drift_ppm": 1500}', b'{"clock_epoch_s": -1}', b'{"clock_jitter_us": "x"}'):
        with pytest.raises(SlotRejected) as exc:
            DeviceParams.from_json(bad)
        assert exc.value.code == 0x0402 and "clock_" in exc.value.message
