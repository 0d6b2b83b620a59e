"""A clock the test moves by hand, for the code that takes an injectable ``clock``: what the code
decides from the time then does not depend on how fast, or how loaded, the machine is."""

import threading


class ManualClock:
    """Callable like ``time.time``: returns :attr:`now` (s), which only :meth:`advance` and
    :meth:`set` change. Thread-safe (a device's sequence thread reads it while the test moves it)."""

    def __init__(self, now: float = 1_790_000_000.0):
        self._now = float(now)
        self._lock = threading.Lock()

    @property
    def now(self) -> float:
        with self._lock:
            return self._now

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> float:
        """Move the clock on by ``seconds``; returns the new time."""
        with self._lock:
            self._now += seconds
            return self._now

    def set(self, now: float) -> None:
        with self._lock:
            self._now = float(now)
