"""Simulated time for the device (docs/hil.md "Simulated time"): a clock that reads the dynamics
simulator's time instead of the machine's.

With the attitude feed's ``clock=sim`` option (or a ``42://`` feed, whose messages carry 42's
``TIME``) the device reads no wall clock for what it reports: its POSIX clock (the GO time the
exposure starts at, ``ext.utc_epoch``, the Sun and the Moon) is the newest accepted sample's time,
and its device clock (TIME, the result's ``epoch``) counts the simulated seconds since the first
accepted sample, from the clock model's epoch. A simulator that stops holds the device's time
still; what waits on the feed is bounded by a wall-clock guard instead (``WALL_GUARD_S``), so a
dead simulator is a BAD_FRAME, never a hang.
"""

from __future__ import annotations

import math
import threading

WALL_GUARD_S = 30.0  #: real seconds a capture waits for the simulator before it gives up


class FeedClock:
    """Simulated time from the samples the feed accepts: :meth:`posix` (POSIX s) and
    :meth:`elapsed` (s since the first accepted sample, 0 before it: the device clock's source)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._first: float | None = None
        self._newest: float | None = None
        self._offered: float | None = None  #: a first sample being checked, before it is accepted

    def offering(self, t: float) -> None:
        """A sample stamped ``t`` is about to be checked: before the first accepted one, its own time
        is the clock (its check against "the device clock" then compares it with itself)."""
        with self._lock:
            if self._newest is None and math.isfinite(t):
                self._offered = t

    def accepted(self, t: float) -> None:
        """A sample stamped ``t`` was kept: time moves on to it (never back)."""
        with self._lock:
            if self._first is None:
                self._first = t
            if self._newest is None or t > self._newest:
                self._newest = t

    def posix(self) -> float:
        with self._lock:
            if self._newest is not None:
                return self._newest
            return 0.0 if self._offered is None else self._offered

    def elapsed(self) -> float:
        with self._lock:
            return 0.0 if self._first is None or self._newest is None else self._newest - self._first
