"""Housekeeping of the emulated electronics: duty-cycle thermal model, current, noisy analog frame."""

import numpy as np
import pytest

from firmware_model.device.housekeeping import (
    AMBIENT_C,
    BOARD,
    CURRENT_BUSY_A,
    DETECTOR,
    PROCESSOR,
    SAMPLE_HZ,
    VOLTAGE_NOISE,
    Housekeeping,
)
from protocol import result
from protocol.telemetry_meta import ANALOG


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


def test_idle_device_reads_its_nominal_values():
    clock = Clock()
    hk = Housekeeping(clock)
    assert hk.temperatures() == (20.0, 25.0, 20.0)
    frame = hk.analog_frame()
    assert frame == hk.analog_frame()  # one ADC sample
    for value, channel in zip(frame, ANALOG):
        assert abs(value / channel.nominal - 1) < 5 * 0.01, channel.name
    clock.t += 1.0 / SAMPLE_HZ
    assert hk.analog_frame() != frame  # the next sample has its own noise
    raw = hk.result_fields()  # as COSMOS converts them
    assert result.detector_temp_c(raw["hardware.detector_temp_raw"]) == 20.0
    assert result.processor_temp_c(raw["hardware.processor_temp_raw"]) == 25.0


def test_temperatures_follow_the_duty_cycle():
    clock = Clock()
    hk = Housekeeping(clock)
    hk.set_busy(True)
    clock.t += 5 * max(DETECTOR.tau_s, PROCESSOR.tau_s, BOARD.tau_s)  # continuous solving
    det, proc, board = hk.temperatures()
    assert (det, proc, board) == pytest.approx(
        (AMBIENT_C + DETECTOR.busy_rise_c, AMBIENT_C + PROCESSOR.busy_rise_c, AMBIENT_C + BOARD.busy_rise_c), abs=0.05
    )
    assert hk.analog_frame()[0] == pytest.approx(CURRENT_BUSY_A, rel=0.05)
    # one processor time constant after stopping: 1/e of the way back to idle
    hk.set_busy(False)
    clock.t += PROCESSOR.tau_s
    rise = hk.temperatures()[1] - (AMBIENT_C + PROCESSOR.idle_rise_c)
    assert rise == pytest.approx((PROCESSOR.busy_rise_c - PROCESSOR.idle_rise_c) / np.e, rel=0.01)
    # a 50 % duty cycle of short sequences settles between idle and busy
    hk2 = Housekeeping(clock)
    for _ in range(2000):
        hk2.set_busy(True)
        clock.t += 0.2
        hk2.set_busy(False)
        clock.t += 0.2
    proc = hk2.temperatures()[1]
    half = AMBIENT_C + (PROCESSOR.idle_rise_c + PROCESSOR.busy_rise_c) / 2
    assert proc == pytest.approx(half, abs=0.2)


def test_voltage_noise_is_what_is_declared():
    clock = Clock()
    hk = Housekeeping(clock, seed=3)
    bus = []
    for _ in range(2000):
        clock.t += 1.0 / SAMPLE_HZ
        bus.append(hk.analog_frame()[1] / ANALOG[1].nominal - 1)
    assert np.std(bus) == pytest.approx(VOLTAGE_NOISE, rel=0.1) and abs(np.mean(bus)) < 3 * VOLTAGE_NOISE / 40
