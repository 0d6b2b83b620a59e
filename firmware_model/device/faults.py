"""Scripted device faults for automated tests (docs/ICD.md section 13): the fault script, parsed
from text lines, its deterministic triggers and the fault counters.

A script has one fault per line, ``name key=value ...``, ``#`` starting a comment. Which replies,
sequences or captures a fault hits is decided by counts ("the next N", "at the Nth GO", "after
the Nth command") or by a fraction drawn from a :class:`random.Random` seeded with the line's
``seed`` (default 0), never by the clock, so a script does the same thing to the same traffic
on any machine. The only time a fault reads is its own effect: ``delay_reply``'s ``ms``.

:class:`FaultInjector` holds the armed faults, the EDAC upsets they placed (a numpy array of
bits per word and region: placing, reading and rewriting them is vectorised, so a load is
bounded, docs/ICD.md section 13), the delayed replies waiting to be sent (:class:`DelayedReplies`)
and the counters (``protocol.edac.FAULT_COUNTERS``, shown at EDAC 0x009C); the device shell asks
it at each reply, command, sequence, capture and memory access.
"""

from __future__ import annotations

import heapq
import logging
import random
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from firmware_model.device.dispatch import Refused
from protocol import edac
from protocol.commands import Code, NackReason

#: fault name -> the keys it takes besides ``seed`` (docs/ICD.md section 13)
KEYS: dict[str, frozenset[str]] = {
    "delay_reply": frozenset({"ms", "fraction", "count"}),
    "drop_reply": frozenset({"fraction", "count"}),
    "corrupt_crc": frozenset({"fraction", "count"}),
    "stuck_result": frozenset({"count"}),
    "reset": frozenset({"at_go", "after", "now"}),
    "edac_upset": frozenset({"region", "bits", "count"}),
    "frozen_detector": frozenset({"count"}),
    # the NAND (docs/ICD.md section 15): applied at load through ``FaultInjector.flash``
    "flash_ecc": frozenset({"bits", "count"}),
    "flash_bad_block": frozenset({"count"}),
    "flash_disturb": frozenset({"reads"}),
}
FLASH_FAULTS = ("flash_ecc", "flash_bad_block", "flash_disturb")  #: counted under their own names
REGIONS = ("scratch", "ram", "result", "catalog")  #: where ``edac_upset`` may strike
MAX_COUNT = 1_000_000  #: largest count, at_go or after (ours: a bound on a typo, not a model)
#: most upset words one script may place, its ``edac_upset`` counts added up (ours: bounds a load's
#: work, docs/ICD.md section 13)
MAX_UPSET_WORDS = 1_000_000
#: most delayed replies waiting at once; a reply that finds them all waiting is dropped (ours)
MAX_DELAYED = 1024
MAX_DELAY_MS = 60_000.0  #: largest ``delay_reply`` delay (ours; the client's longest wait is 60 s)
WORD = 4  #: bytes per EDAC-protected word: a 32-bit word under a (40,32) SEC-DED code (docs/ICD.md section 13)
REPLY_FAULTS = ("drop_reply", "corrupt_crc", "delay_reply")  #: in the order they are decided
GO_CODES = (Code.GO, Code.COMBINATION)  #: the commands that start a sequence (``reset at_go``)

log = logging.getLogger(__name__)


class FaultScriptError(ValueError):
    """A script that does not parse: the message names the source and the line number."""


@dataclass(frozen=True)
class Fault:
    """One parsed line: ``name``, its ``keys`` (numbers already checked; ``now`` as True) and
    its ``line`` number in the script."""

    name: str
    keys: Mapping[str, float | int | str | bool]
    line: int

    @property
    def seed(self) -> int:
        return int(self.keys.get("seed", 0))


def _number(text: str, key: str, integer: bool, lo: float, hi: float) -> float | int:
    try:
        value: float | int = int(text, 0) if integer else float(text)
    except ValueError:
        raise ValueError(f"{key}={text!r} is not {'a whole number' if integer else 'a number'}") from None
    if not lo <= value <= hi:  # also NaN
        raise ValueError(f"{key}={text} outside {lo}..{hi}" if integer else f"{key}={text} outside {lo:g}..{hi:g}")
    return value


def _value(key: str, text: str) -> float | int | str:
    if key == "fraction":
        return _number(text, key, False, 0.0, 1.0)
    if key == "ms":
        return _number(text, key, False, 0.0, MAX_DELAY_MS)
    if key in ("count", "seed"):
        return _number(text, key, True, 0, MAX_COUNT if key == "count" else 2**63 - 1)
    if key in ("at_go", "after"):
        return _number(text, key, True, 1, MAX_COUNT)
    if key == "reads":
        return _number(text, key, True, 1, 10**9)
    if key == "bits":
        if text not in ("1", "2"):
            raise ValueError(f"bits={text!r}: 1 (corrected) or 2 (uncorrectable)")
        return int(text)
    if text not in REGIONS:  # region
        raise ValueError(f"region={text!r}; known: {', '.join(REGIONS)}")
    return text


def _needs(name: str, keys: Mapping[str, object]) -> str | None:
    """What ``name``'s line lacks or has too much of, or None."""
    trigger = {"fraction", "count"} if name in REPLY_FAULTS else {"at_go", "after", "now"} if name == "reset" else None
    if trigger is not None and len(trigger & set(keys)) != 1:
        return f"{name} takes exactly one of {', '.join(sorted(trigger))}"
    if name == "delay_reply" and "ms" not in keys:
        return "delay_reply needs ms="
    if name in ("stuck_result", "frozen_detector") and "count" not in keys:
        return f"{name} needs count="
    if name == "edac_upset" and not {"region", "bits"} <= set(keys):
        return "edac_upset needs region= and bits="
    if name == "flash_ecc" and "bits" not in keys:
        return "flash_ecc needs bits="
    if name == "flash_disturb" and "reads" not in keys:
        return "flash_disturb needs reads="
    return None


def parse_line(text: str, line: int) -> Fault | None:
    """The fault on one line (None for a blank or comment line); ValueError says what is wrong."""
    words = text.split("#", 1)[0].split()
    if not words:
        return None
    name, *rest = words
    if name not in KEYS:
        raise ValueError(f"unknown fault {name!r}; known: {', '.join(KEYS)}")
    keys: dict[str, float | int | str | bool] = {}
    for word in rest:
        key, eq, text_value = word.partition("=")
        if key not in KEYS[name] | {"seed"}:
            raise ValueError(f"{name}: unknown key {key!r}; known: {', '.join(sorted(KEYS[name] | {'seed'}))}")
        if key in keys:
            raise ValueError(f"{name}: {key} given twice")
        if key == "now":
            if eq:
                raise ValueError("reset now takes no value")
            keys[key] = True
            continue
        if not eq:
            raise ValueError(f"{name}: {key} needs a value ({key}=...)")
        keys[key] = _value(key, text_value)
    problem = _needs(name, keys)
    if problem:
        raise ValueError(problem)
    return Fault(name, keys, line)


def parse_script(text: str, source: str = "faults") -> tuple[Fault, ...]:
    """Every fault of ``text``; :class:`FaultScriptError` (``SOURCE line N: what``) at the first
    line that does not parse."""
    faults = []
    upset_words = 0
    for number, line in enumerate(text.splitlines(), start=1):
        try:
            fault = parse_line(line, number)
        except ValueError as exc:
            raise FaultScriptError(f"{source} line {number}: {exc}") from None
        if fault is not None:
            faults.append(fault)
            if fault.name == "edac_upset":
                upset_words += int(fault.keys.get("count", 1))
                if upset_words > MAX_UPSET_WORDS:
                    raise FaultScriptError(
                        f"{source} line {number}: edac_upset: the script's upsets add up to {upset_words} words, "
                        f"over the {MAX_UPSET_WORDS} one script may place"
                    )
    return tuple(faults)


def draw_words(seed: int, n: int, k: int) -> np.ndarray:
    """``k`` distinct word numbers of ``0..n-1`` (``k <= n``), sorted, drawn with
    ``numpy.random.default_rng(seed)``: the same words for the same seed on any machine. Drawn
    with replacement in rounds, repeats thrown out, each round at most half the last; when more
    than half the words are wanted, the ones spared are drawn instead. Time O(k log k), plus O(n)
    when more than half are wanted (then n < 2k)."""
    rng = np.random.default_rng(seed)
    if 2 * k > n:
        chosen = np.ones(n, bool)
        chosen[_draw_few(rng, n, n - k)] = False
        return np.flatnonzero(chosen)
    return _draw_few(rng, n, k)


def _draw_few(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """``k <= n / 2`` distinct numbers of ``0..n-1``, sorted (each round at least halves what is
    missing)."""
    chosen = np.empty(0, np.int32)  # a region has fewer than 2**31 words (a catalog at most 2**24)
    while chosen.size < k:
        drawn = np.sort(rng.integers(0, n, size=k - chosen.size, dtype=np.int32))
        drawn = drawn[np.concatenate(([True], drawn[1:] != drawn[:-1]))]  # each number once
        at = np.searchsorted(chosen, drawn)
        known = at < chosen.size
        known[known] = chosen[at[known]] == drawn[known]  # chosen in an earlier round
        chosen = np.insert(chosen, at[~known], drawn[~known]) if chosen.size else drawn
    return chosen


class DelayedReplies:
    """Replies a ``delay_reply`` fault holds back, each handed to its ``send`` callable when its
    delay is over, by one thread that waits on a condition (never a sleep), while the link serves
    on. :meth:`drop` forgets every one still waiting (FAULT clear, a reset, the device stopping),
    calling its ``unsent``. At most ``limit`` wait at once."""

    def __init__(self, limit: int = MAX_DELAYED):
        self.limit = limit
        self._cond = threading.Condition()
        self._queue: list[tuple[float, int, Callable[[], None], Callable[[], None]]] = []  #: a heap by due time
        self._added = 0
        self._thread: threading.Thread | None = None

    def __len__(self) -> int:
        with self._cond:
            return len(self._queue)

    def add(self, delay_s: float, send: Callable[[], None], unsent: Callable[[], None]) -> bool:
        """Call ``send()`` ``delay_s`` s from now unless dropped first (then ``unsent()``); False,
        and nothing queued, when ``limit`` replies wait already."""
        with self._cond:
            if len(self._queue) >= self.limit:
                return False
            heapq.heappush(self._queue, (time.monotonic() + delay_s, self._added, send, unsent))
            self._added += 1
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, daemon=True, name="delayed-replies")
                self._thread.start()
            self._cond.notify()
        return True

    def drop(self) -> int:
        """Forget every reply still waiting (each one's ``unsent()`` called); how many."""
        with self._cond:
            dropped, self._queue = self._queue, []
            self._cond.notify()
        for _, _, _, unsent in dropped:
            unsent()
        if dropped:
            log.info("faults: %d delayed replies dropped", len(dropped))
        return len(dropped)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue or self._queue[0][0] > time.monotonic():
                    self._cond.wait(None if not self._queue else self._queue[0][0] - time.monotonic())
                _, _, send, _ = heapq.heappop(self._queue)
            try:
                send()
            except Exception:  # a transport's failure must not end the thread: later replies still go
                log.exception("faults: a delayed reply could not be sent")


@dataclass
class _Armed:
    """One armed fault: what is left of its count (None: a fraction, armed until cleared)."""

    fault: Fault
    left: int | None
    rng: random.Random = field(init=False)

    def __post_init__(self) -> None:
        self.rng = random.Random(self.fault.seed)

    def fires(self) -> bool:
        """Whether this event is hit (a count is spent; a fraction draws from the seeded stream)."""
        if self.left is None:
            return self.rng.random() < float(self.fault.keys["fraction"])
        if self.left <= 0:
            return False
        self.left -= 1
        return True

    @property
    def spent(self) -> bool:
        return self.left is not None and self.left <= 0


@dataclass(frozen=True)
class ReplyFault:
    """What happens to one command's reply: dropped, its CRC corrupted, sent ``delay_s`` late."""

    drop: bool = False
    corrupt: bool = False
    delay_s: float = 0.0


def _no_upsets() -> dict[str, np.ndarray]:
    return {r: np.zeros(0, np.uint8) for r in REGIONS}


class FaultInjector:
    """The armed faults of one device and its fault counters. ``words(region)`` gives the number
    of 4-byte words of a region now (the catalog's: of its active image); it chooses where
    ``edac_upset`` strikes. Thread-safe: the sequence worker asks too."""

    def __init__(self, words: Callable[[str], int] = lambda region: 0):
        self._words = words
        self._lock = threading.Lock()
        self._armed: list[_Armed] = []
        self._commands = 0  #: commands (FAULT aside) since the script was loaded
        self._gos = 0  #: GO / COMBINATION commands since then
        #: region -> the upset of each word (0 none, 1 single-bit, 2 double-bit); empty: none placed
        self.upsets: dict[str, np.ndarray] = _no_upsets()
        self.counters: dict[str, int] = dict.fromkeys(edac.FAULT_COUNTERS, 0)
        self.delayed = DelayedReplies()  #: replies of ``delay_reply`` still to be sent
        #: applies a flash fault to the NAND and returns how many pages or blocks it struck
        self.flash: Callable[[Fault], int] | None = None

    # ------------------------------------------------------------------ the script

    def load(self, faults: tuple[Fault, ...]) -> bool:
        """Arm ``faults`` in place of the armed ones (EDAC upsets are placed now); True when one
        of them is ``reset now`` (the caller resets once its reply is out)."""
        now = False
        with self._lock:
            self._armed, self._commands, self._gos = [], 0, 0
            for fault in faults:
                if fault.name == "edac_upset":
                    self._place(fault)
                elif fault.name in FLASH_FAULTS:
                    struck = self.flash(fault) if self.flash is not None else 0
                    self.counters[fault.name] = self.counters.get(fault.name, 0) + struck
                elif fault.name == "reset" and fault.keys.get("now"):
                    now = True
                else:
                    count = fault.keys.get("count", fault.keys.get("at_go", fault.keys.get("after")))
                    self._armed.append(_Armed(fault, None if count is None else int(count)))
        return now

    def clear(self) -> None:
        """Disarm every fault, forget every upset and drop the delayed replies still waiting (the
        counters stay)."""
        with self._lock:
            self._armed = []
            self.upsets = _no_upsets()
        self.delayed.drop()  # outside the lock: a reply's ``unsent`` takes the device's

    @property
    def armed(self) -> int:
        """Faults still to act: armed lines not spent, plus words holding an upset."""
        with self._lock:
            lines = sum(not a.spent for a in self._armed)
            return lines + sum(int(np.count_nonzero(w)) for w in self.upsets.values())

    def upset_words(self, region: str) -> dict[int, int]:
        """The words of ``region`` holding an upset -> its bits (1 or 2)."""
        with self._lock:
            hit = self.upsets[region]
            return {int(w): int(hit[w]) for w in np.flatnonzero(hit)}

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] += n

    def _place(self, fault: Fault) -> None:
        region, bits = str(fault.keys["region"]), int(fault.keys["bits"])
        n_words = max(1, self._words(region))
        count = min(int(fault.keys.get("count", 1)), n_words)
        hit = self.upsets[region]
        if hit.size != n_words:  # first upsets here, or of another catalog image: none of the old words kept
            hit = self.upsets[region] = np.zeros(n_words, np.uint8)
        words = draw_words(fault.seed, n_words, count)
        hit[words] = np.maximum(hit[words], bits)

    def _firing(self, name: str) -> Fault | None:
        """The armed ``name`` fault that fires now, or None: its lines asked in script order until
        one does (the lines after it are not asked, so their counts and draws wait)."""
        with self._lock:
            return next((a.fault for a in self._armed if a.fault.name == name and a.fires()), None)

    def _fire(self, name: str) -> bool:
        """Whether an armed ``name`` fault fires now (:meth:`_firing`)."""
        return self._firing(name) is not None

    def _reset_due(self, trigger: str, n: int) -> bool:
        """Whether an armed ``reset`` whose ``trigger`` (``at_go`` or ``after``) is ``n`` is due;
        it is then spent. Call under the lock."""
        hit = [
            a
            for a in self._armed
            if a.fault.name == "reset" and not a.spent and int(a.fault.keys.get(trigger, -1)) == n
        ]
        for a in hit:
            a.left = 0
        return bool(hit)

    # ------------------------------------------------------------------ replies and commands

    def reply(self, code: int) -> ReplyFault:
        """The fault, if any, on the reply to a command of ``code`` (FAULT's own replies are
        never hit); counted."""
        if code == Code.FAULT:
            return ReplyFault()
        if self._fire("drop_reply"):
            self.count("dropped_replies")
            return ReplyFault(drop=True)
        corrupt = self._fire("corrupt_crc")
        if corrupt:
            self.count("corrupted_crcs")
        delay = self._firing("delay_reply")
        if delay is not None:
            self.count("delayed_replies")
        return ReplyFault(corrupt=corrupt, delay_s=0.0 if delay is None else float(delay.keys["ms"]) / 1000.0)

    def reset_before(self, code: int) -> bool:
        """Whether the device resets on receiving this command, unanswered (``reset at_go``)."""
        if code not in GO_CODES:
            return False
        with self._lock:
            self._gos += 1
            return self._reset_due("at_go", self._gos)

    def reset_after(self, code: int) -> bool:
        """Whether the device resets once this command is answered (``reset after``)."""
        if code == Code.FAULT:
            return False
        with self._lock:
            self._commands += 1
            return self._reset_due("after", self._commands)

    # ------------------------------------------------------------------ sequences and captures

    def stuck(self) -> bool:
        """Whether this sequence completes without a new result (``stuck_result``); counted."""
        if self._fire("stuck_result"):
            self.count("stuck_results")
            return True
        return False

    def frozen(self) -> bool:
        """Whether this capture returns the previous frame (``frozen_detector``); counted. Ask
        only when there is a previous frame."""
        if self._fire("frozen_detector"):
            self.count("frozen_frames")
            return True
        return False

    def catalog_access(self) -> bool:
        """The catalog read by a solve: single-bit upsets corrected, double-bit ones detected;
        True when the active catalog must be reloaded from its stored image (counted)."""
        with self._lock:
            words, self.upsets["catalog"] = self.upsets["catalog"], np.zeros(0, np.uint8)
        single = int(np.count_nonzero(words == 1))
        double = int(np.count_nonzero(words == 2))
        if single:
            self.count("edac_corrected", single)
        if double:
            self.count("edac_uncorrectable", double)
            self.count("catalog_reloads")
        return bool(double)

    # ------------------------------------------------------------------ memory

    def read(self, region: str, offset: int, length: int) -> None:
        """A read of bytes [offset, offset + length) of ``region``: single-bit upsets there are
        corrected (the data reads right; counted, the word scrubbed); a double-bit upset is counted
        and NACKs EDAC_UNCORRECTABLE, the word staying bad until it is written."""
        if length <= 0:
            return
        with self._lock:
            lo = max(0, offset // WORD)
            words = self.upsets[region][lo : (offset + length - 1) // WORD + 1]  # a view: scrubbed in place
            if not words.any():
                return
            single = words == 1
            double = np.flatnonzero(words == 2)
            words[single] = 0
            self.counters["edac_corrected"] += int(np.count_nonzero(single))
            self.counters["edac_uncorrectable"] += int(double.size)
        if double.size:
            raise Refused(
                NackReason.EDAC_UNCORRECTABLE,
                f"uncorrectable double-bit EDAC error in {region} word at offset 0x{(lo + int(double[0])) * WORD:X} "
                f"({double.size} word(s) bad until rewritten)",
            )

    def written(self, region: str, offset: int = 0, length: int | None = None) -> None:
        """Bytes [offset, offset + length) of ``region`` rewritten (None: the whole region): the
        upsets of the words they touch are gone (the catalog's: by a new image, every word)."""
        with self._lock:
            if length is None:
                self.upsets[region] = np.zeros(0, np.uint8)
            elif length > 0:
                self.upsets[region][max(0, offset // WORD) : (offset + length - 1) // WORD + 1] = 0
