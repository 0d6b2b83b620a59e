"""Housekeeping of the emulated electronics (ours: no public datasheet gives these figures).

* Temperatures: three first-order thermal nodes (detector, processor, the supervisor's board)
  over an ambient of :data:`AMBIENT_C`, each rising toward its idle or busy level with its time
  constant while sequences run: the duty cycle drives them. At idle they sit at the analog frame's
  nominal supervisor temperature (20 degC), the detector's 20 degC and the processor's 25 degC
  (the zero point of COSMOS's conversion).
* Supply current: the idle or busy level of the moment.
* The analog frame (EDAC 0x0004, ``protocol.telemetry_meta.ANALOG``): sampled at
  :data:`SAMPLE_HZ` like a supervisor ADC, each channel with Gaussian noise (voltages
  :data:`VOLTAGE_NOISE`, current :data:`CURRENT_NOISE`, relative 1-sigma; seeded by the sample
  index, so reads within one sample agree).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from firmware_model.device.cosmos_compat import detector_temp_raw, processor_temp_raw
from protocol.telemetry_meta import ANALOG

AMBIENT_C = 20.0  #: degC
SAMPLE_HZ = 1.0  #: analog frame samples per second
VOLTAGE_NOISE = 0.002  #: relative 1-sigma of each voltage sample
CURRENT_NOISE = 0.01  #: relative 1-sigma of the current sample
#: supply current (A) at idle (the analog frame's nominal) and while a sequence runs
CURRENT_IDLE_A = next(c.nominal for c in ANALOG if c.name == "current")
CURRENT_BUSY_A = 0.45


@dataclass(frozen=True)
class ThermalNode:
    """Rise over ambient at idle and while a sequence runs (degC), time constant (s)."""

    idle_rise_c: float
    busy_rise_c: float
    tau_s: float

    def step(self, temp_c: float, busy: bool, dt_s: float) -> float:
        """Temperature after ``dt_s`` at a constant state (exact first-order response)."""
        target = AMBIENT_C + (self.busy_rise_c if busy else self.idle_rise_c)
        return target + (temp_c - target) * math.exp(-dt_s / self.tau_s)


DETECTOR = ThermalNode(0.0, 6.0, 180.0)
PROCESSOR = ThermalNode(5.0, 15.0, 40.0)
BOARD = ThermalNode(0.0, 4.0, 120.0)  #: the supervisor's temperature in the analog frame


class Housekeeping:
    """The model of the module docstring; ``set_busy`` follows the sequence runner."""

    def __init__(self, clock: Callable[[], float] = time.monotonic, seed: int = 0):
        self._clock, self._seed = clock, seed
        self._lock = threading.Lock()
        self._t = clock()
        self._busy = False
        self._temps = [AMBIENT_C + n.idle_rise_c for n in (DETECTOR, PROCESSOR, BOARD)]
        #: the NAND's (corrected, uncorrectable, bad blocks): hardware telemetry +0x00 (docs/ICD.md §15)
        self.flash_errors: Callable[[], tuple[int, int, int]] = lambda: (0, 0, 0)

    def _advance(self) -> float:
        now = self._clock()
        dt = max(0.0, now - self._t)
        self._temps = [n.step(t, self._busy, dt) for n, t in zip((DETECTOR, PROCESSOR, BOARD), self._temps)]
        self._t = now
        return now

    def set_busy(self, busy: bool) -> None:
        """A sequence started (True) or ended (False)."""
        with self._lock:
            self._advance()
            self._busy = busy

    def temperatures(self) -> tuple[float, float, float]:
        """(detector, processor, board) in degC now."""
        with self._lock:
            self._advance()
            det, proc, board = self._temps
            return det, proc, board

    def analog_frame(self) -> tuple[float, ...]:
        """The 8 channels of ``protocol.telemetry_meta.ANALOG`` at the current sample."""
        with self._lock:
            now = self._advance()
            board, busy = self._temps[2], self._busy
        rng = np.random.default_rng([self._seed, int(now * SAMPLE_HZ)])
        out = []
        for channel in ANALOG:
            if channel.name == "current":
                level = CURRENT_BUSY_A if busy else CURRENT_IDLE_A
                out.append(level * (1.0 + CURRENT_NOISE * rng.standard_normal()))
            elif channel.name == "supervisor_temp":
                out.append(board)
            else:
                out.append(channel.nominal * (1.0 + VOLTAGE_NOISE * rng.standard_normal()))
        return tuple(out)

    def result_fields(self) -> dict[str, Any]:
        """The result's hardware temperatures now, as COSMOS's conversions read them."""
        det, proc, _ = self.temperatures()
        return {
            "hardware.detector_temp_raw": detector_temp_raw(det),
            "hardware.processor_temp_raw": processor_temp_raw(proc),
            "hardware.flash_errors": list(self.flash_errors()),
        }
