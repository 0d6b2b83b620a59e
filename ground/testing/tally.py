"""Counts of a fuzz or fault campaign; every count but ``messages`` and ``faults`` should be 0."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

#: Counts that must stay at zero.
FAILURES = ("crashes", "hangs", "unanswered_pings", "state_corruptions", "tracebacks", "misattributed", "bad_replies")


@dataclass
class Tally:
    """``messages`` sent, ``faults`` injected, and the failures seen; ``notes`` say what failed."""

    messages: int = 0
    faults: int = 0
    crashes: int = 0  #: device process died
    hangs: int = 0  #: a call overran its bound
    unanswered_pings: int = 0
    state_corruptions: int = 0  #: an active image changed when it should not have, or became unreadable
    tracebacks: int = 0  #: a traceback on any stderr
    misattributed: int = 0  #: a reply taken for a command it was not for
    bad_replies: int = 0  #: bytes from the device that are not a valid NSP reply to the host
    notes: list[str] = field(default_factory=list)

    def fail(self, kind: str, note: str) -> None:
        """Count one failure of ``kind`` (a name of :data:`FAILURES`) and remember why."""
        setattr(self, kind, getattr(self, kind) + 1)
        if len(self.notes) < 50:
            self.notes.append(f"{kind}: {note}")

    def add(self, other: Tally) -> Tally:
        for f in fields(self):
            if f.name != "notes":
                setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))
        self.notes += other.notes
        return self

    @property
    def failures(self) -> int:
        return sum(getattr(self, name) for name in FAILURES)

    def row(self) -> tuple[int, ...]:
        return tuple(getattr(self, f.name) for f in fields(self) if f.name != "notes")


def table(rows: dict[str, Tally]) -> str:
    """A plain-text table, one line per campaign and a total line."""
    names = [f.name for f in fields(Tally) if f.name != "notes"]
    total = Tally()
    for t in rows.values():
        total.add(Tally(**{n: getattr(t, n) for n in names}))
    width = max([len(k) for k in rows] + [8])
    head = f"{'campaign':<{width}} " + " ".join(names)
    lines = [head, "-" * len(head)]
    for key, t in {**rows, "total": total}.items():
        lines.append(f"{key:<{width}} " + " ".join(f"{v:>{len(n)}}" for n, v in zip(names, t.row())))
    return "\n".join(lines)
