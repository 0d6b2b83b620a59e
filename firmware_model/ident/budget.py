"""Counted search budgets: the data decides an answer, never the clock.

Every search is bounded by the work it does, counted in units that do not depend on the
machine: hypotheses verified in one solve (:class:`SearchBudget`, ``SolveParams.max_verifications``),
pattern seeds refined and verifications made over a whole frame (``OpticsSearch.max_seeds``,
``OpticsSearch.max_verifications``). The same frame, camera, catalog and parameters therefore
spend the same work and give the same answer on a quiet laptop, a loaded CI runner or a Dask
worker.

A wall-clock deadline exists only in the device's opt-in flight-timing mode (``st16-device
--timing realistic``). It is checked at the same places as the counts; when it stops a search,
the answer says so (``deadline_missed``: the result's ``ext.search_flags`` bit and its reason),
and is no longer reproducible, as flight timing on a real tracker is not.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from enum import StrEnum


class Stop(StrEnum):
    """What stopped a search before it ran out of hypotheses (a typed outcome: callers never read
    reason texts to tell a budget from a miss)."""

    NONE = ""  #: nothing: the search ended on its own (an answer, or every hypothesis tried)
    COUNT = "count"  #: its counted budget ran out
    DEADLINE = "deadline"  #: the flight-timing deadline passed


@dataclass
class SearchBudget:
    """The verifications one search may make (``limit``), counted as it makes them, and an optional
    flight-timing ``deadline`` (a ``time.perf_counter`` value; None: counts alone). Once
    exhausted it stays exhausted, so every check after the first agrees."""

    limit: int
    deadline: float | None = None
    used: int = 0
    stopped: Stop = Stop.NONE  #: what stopped the search, once something has

    def spend(self) -> None:
        """Count one verification."""
        self.used += 1

    @property
    def exhausted(self) -> bool:
        """Whether the search must stop: the count reached, or (flight timing) the deadline passed."""
        if self.stopped is Stop.NONE:
            if self.used >= self.limit:
                self.stopped = Stop.COUNT
            elif self.deadline is not None and time.perf_counter() > self.deadline:
                self.stopped = Stop.DEADLINE
        return self.stopped is not Stop.NONE

    @property
    def reason(self) -> str:
        """Why the search stopped (:func:`stop_reason`; empty while it has not)."""
        return stop_reason(self.stopped, self.limit, "verification")


def stop_reason(stop: Stop, limit: int, unit: str, per: str = "") -> str:
    """Why a search stopped: its count of ``unit`` (singular; ``per`` what it counts over), named
    in the same words on every machine, or the deadline."""
    if stop is Stop.COUNT:
        return f"search budget of {limit} {unit}{'' if limit == 1 else 's'}{per} reached"
    if stop is Stop.DEADLINE:
        return "flight-timing deadline missed"
    return ""
