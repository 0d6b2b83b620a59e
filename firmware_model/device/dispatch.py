"""Command dispatch of the device shell: one handler per entry of the command table
(:data:`protocol.command_table.COMMANDS`), the counters it keeps, and how a handler's outcome
becomes reply messages (ACK parts, a NACK for a refusal or a bug, or a reply sent later).

A handler takes the command's decoded data field (the table's ``request`` type; the raw bytes
when it has none or decodes them itself) and returns its reply data: bytes, a list of parts, or a
:class:`Pending` reply; it raises :class:`Refused` (or :class:`~protocol.commands.PayloadError`)
to NACK.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from protocol import nsp
from protocol.command_table import COMMANDS
from protocol.commands import APP_START_ADDRESS, Diagnostics, NackInfo, NackReason, PayloadError

log = logging.getLogger("firmware_model.device.device")

Handler = Callable[[Any], Any]


class Refused(Exception):
    """A command the device refuses: NACKed with ``reason`` and ``text``; with ``data``, NACKed
    with those bytes instead (a failure reply the ICD lays out, e.g. FLASH's)."""

    def __init__(self, reason: int, text: str, data: bytes | None = None):
        super().__init__(text)
        self.reason = int(reason)
        self.text = text
        self.data = data


@dataclass(frozen=True)
class Pending:
    """A command's reply that is ready only later: ``wait()`` returns its payload parts (with the
    device lock held; it may wait on the sequence condition, which releases the lock)."""

    wait: Callable[[], list[bytes]]


@dataclass
class Mode:
    """Bootloader (False) or application (True) mode, shared by the parts of a device."""

    app: bool = False

    def require_app(self, what: str) -> None:
        if not self.app:
            raise Refused(NackReason.WRONG_MODE, f"{what} needs application mode (send INIT 0x{APP_START_ADDRESS:08X})")


@dataclass
class Counters:
    framing: int = 0
    runt: int = 0
    oversize: int = 0
    bad_crc: int = 0
    fifo_overflow: int = 0
    accepted: int = 0
    nacked: int = 0
    silent: int = 0
    other_address: int = 0
    replies: int = 0
    per_code: list[int] = field(default_factory=lambda: [0] * 32)

    def snapshot(self) -> Diagnostics:
        """The DIAGNOSTIC reply of these counters (fields matched by name)."""
        return Diagnostics(**{**asdict(self), "per_code": tuple(self.per_code)})


def _frames(replies: list[nsp.Message], late: Callable[[list[bytes]], None] | None = None) -> list[bytes]:
    return [m.frame() for m in replies]


class Dispatcher:
    """Runs commands through ``handlers`` (one per command-table code, checked at construction)
    under ``lock``; ``counters()`` gives the counters to update; ``late_reply()`` the transport's
    callback for replies produced after :meth:`handle` returned (None: wait for them here), to
    which ``frames(replies)`` hands their frames (the device's scripted reply faults act there);
    ``failure_state()`` the sequence state a COMBINATION failure reply carries."""

    def __init__(
        self,
        handlers: Mapping[int, Handler],
        lock: threading.RLock,
        counters: Callable[[], Counters],
        late_reply: Callable[[], Callable[[list[bytes]], None] | None],
        frames: Callable[[list[nsp.Message], Callable[[list[bytes]], None] | None], list[bytes]] = _frames,
        failure_state: Callable[[], int] = int,
    ):
        if set(handlers) != set(COMMANDS):
            raise ValueError(f"handlers for {sorted(handlers)} but the command table has {sorted(COMMANDS)}")
        self.handlers = dict(handlers)
        self._lock = lock
        self._counters = counters
        self._late_reply = late_reply
        self._frames = frames
        #: bumped by a device reset: a reply still to come for a command received before it is never sent
        self.generation = 0
        self._failure_state = failure_state

    def handle(self, msg: nsp.Message) -> list[nsp.Message]:
        """Execute a command addressed to us; return its reply messages ([] when Poll = 0)."""
        with self._lock:
            counters = self._counters()
            counters.accepted += 1
            counters.per_code[msg.code] += 1
            replies = self._replies(msg, lambda: self._dispatch(msg))
            if isinstance(replies, Pending):
                late = self._late_reply()  # bound now: the reply goes to whoever sent this command
                if late is None:  # no transport to answer later: wait here
                    replies = self._replies(msg, replies.wait)
                else:
                    threading.Thread(
                        target=self._answer_late,
                        args=(msg, replies, late, self.generation),
                        daemon=True,
                        name=f"reply-{msg.code:02X}",
                    ).start()
                    return []
            return self._count_replies(msg, replies)

    def _dispatch(self, msg: nsp.Message) -> list[bytes] | Pending:
        spec = COMMANDS.get(msg.code)
        if spec is None:
            raise Refused(NackReason.UNKNOWN_COMMAND, f"command code 0x{msg.code:02X} is not assigned")
        data: Any = msg.data
        if spec.request is not None and spec.decode_first:
            data = spec.request.unpack(msg.data)
        parts = self.handlers[spec.code](data)
        return parts if isinstance(parts, (list, Pending)) else [parts]

    def _replies(self, msg: nsp.Message, run: Callable[[], Any]) -> Any:
        """Reply messages to ``msg`` from ``run()`` (its payload parts), a NACK for an expected
        refusal or a bug, or the :class:`Pending` that ``run`` returned."""
        try:
            parts = run()
            if isinstance(parts, Pending):
                return parts
            return [nsp.reply_to(msg, data, ack=True, final=(i == len(parts) - 1)) for i, data in enumerate(parts)]
        except (Refused, PayloadError) as exc:
            self._counters().nacked += 1
            text = exc.text if isinstance(exc, Refused) else exc.message
            if isinstance(exc, Refused) and exc.data is not None:  # the ICD's own failure layout
                return [nsp.reply_to(msg, exc.data, ack=False)]
            spec = COMMANDS.get(msg.code)
            if spec is not None and spec.failure is not None:  # the ICD's own failure reply
                return [nsp.reply_to(msg, spec.failure(self._failure_state(), text).pack(), ack=False)]
            return [nsp.reply_to(msg, NackInfo(exc.reason, text).pack(), ack=False)]
        except Exception as exc:  # never crash the link on a bug: NACK and report
            log.exception("device: bug while handling a command or sequence")
            self._counters().nacked += 1
            return [nsp.reply_to(msg, NackInfo(NackReason.INTERNAL, repr(exc)).pack(), ack=False)]

    def _count_replies(self, msg: nsp.Message, replies: list[nsp.Message]) -> list[nsp.Message]:
        if not msg.poll:
            self._counters().silent += 1
            return []
        self._counters().replies += len(replies)
        return replies

    def _answer_late(
        self, msg: nsp.Message, pending: Pending, late: Callable[[list[bytes]], None], generation: int
    ) -> None:
        """Wait for ``pending`` (the lock is released while waiting) and hand its replies to
        ``late``, the transport's callback of the session that sent ``msg``; nothing when a reset
        came meanwhile (``generation`` is no longer the dispatcher's)."""
        with self._lock:
            replies = self._replies(msg, pending.wait)
            if generation != self.generation:
                log.info("device: no reply to command 0x%02X: the device reset since it was received", msg.code)
                return
            replies = self._count_replies(msg, replies)
        frames = self._frames(replies, late)
        if frames:
            late(frames)
