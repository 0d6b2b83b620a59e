"""The device clock: the supervisor's real-time clock that TIME (0x13) returns and that stamps every
time the device reports (docs/ICD.md section 6, "TIME and the device clock").

The real clock (ICD page 1-35918) is a 48-bit count of microseconds whose least significant bit is
always 0, and the ICD warns that the clocks of one hardware revision drift. A 48-bit field wraps
at 2**48 us (8.9 years; the page says about 17, which 48 bits of microseconds cannot hold:
docs/ICD.md says so). The model counts from ``epoch_s`` at power-on (and again
after a reset), runs fast by ``drift_ppm``, and latches TIME with a Gaussian ``jitter_us``
(seeded), so a driver's time correlation can be tested against a clock that is wrong in known
ways. It reads a monotonic source (``time.monotonic`` unless given: a simulator's time in the
simulated-time mode).
"""

from __future__ import annotations

import math
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from protocol.commands import TIME_BITS

MAX_DRIFT_PPM = 1000.0  #: largest |drift| the model accepts
MAX_JITTER_US = 1000.0  #: largest latch jitter (1 sigma) the model accepts
ROLLOVER_US = 1 << TIME_BITS  #: the count wraps here


@dataclass(frozen=True)
class ClockModel:
    """How the device clock is wrong: the count at power-on (``epoch_s``, s, >= 0), its rate error
    (``drift_ppm``, positive runs fast) and the 1-sigma jitter of a TIME latch (``jitter_us``),
    drawn from ``seed``. The defaults are an ideal clock that starts at 0."""

    epoch_s: float = 0.0
    drift_ppm: float = 0.0
    jitter_us: float = 0.0
    seed: int = 0

    def problems(self) -> list[str]:
        """Why this model is refused (empty when it is fine), one phrase each."""
        out = []
        if not (math.isfinite(self.epoch_s) and 0.0 <= self.epoch_s < ROLLOVER_US / 1e6):
            out.append(f"clock epoch {self.epoch_s:g} s outside [0, {ROLLOVER_US / 1e6:.0f}) s")
        if not (math.isfinite(self.drift_ppm) and abs(self.drift_ppm) <= MAX_DRIFT_PPM):
            out.append(f"clock drift {self.drift_ppm:g} ppm outside +-{MAX_DRIFT_PPM:g} ppm")
        if not (math.isfinite(self.jitter_us) and 0.0 <= self.jitter_us <= MAX_JITTER_US):
            out.append(f"clock jitter {self.jitter_us:g} us outside [0, {MAX_JITTER_US:g}] us")
        return out


class DeviceClock:
    """The device's clock per :class:`ClockModel`, reading ``source`` (monotonic s)."""

    def __init__(self, model: ClockModel = ClockModel(), source: Callable[[], float] = time.monotonic):
        problems = model.problems()
        if problems:
            raise ValueError("; ".join(problems))
        self.model = model
        self.source = source
        self._rng = random.Random(model.seed)
        self._lock = threading.Lock()
        self._t0 = source()

    def power_on(self) -> None:
        """Start counting from the model's epoch again (a reset)."""
        self._t0 = self.source()

    def seconds(self, at: float | None = None) -> float:
        """The clock's reading (s, modulo the rollover) at source time ``at`` (now when None)."""
        elapsed = (self.source() if at is None else at) - self._t0
        return (self.model.epoch_s + elapsed * (1.0 + self.model.drift_ppm * 1e-6)) % (ROLLOVER_US / 1e6)

    def latch(self, at: float | None = None) -> int:
        """TIME's value latched at source time ``at``: microseconds with the latch jitter, least
        significant bit 0, modulo 2**48."""
        us = self.seconds(at) * 1e6
        if self.model.jitter_us > 0:
            with self._lock:
                us += self._rng.gauss(0.0, self.model.jitter_us)
        return (int(round(us)) % ROLLOVER_US) & ~1
