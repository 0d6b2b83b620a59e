"""JSONL log of link exchanges: one line per frame sent or received.

Fields: ``t`` (UTC ISO-8601), ``dir`` (``tx``/``rx``), ``hex`` (unescaped NSP bytes), and when the
frame decodes: ``dst``, ``src``, ``mcf``, ``code``, ``name``, ``poll_final``, ``b``, ``ack``,
``data`` (hex); otherwise ``error``. ``note`` marks e.g. stale replies the client discarded.
"""

from __future__ import annotations

import json
import threading
from datetime import UTC, datetime
from pathlib import Path

from protocol import nsp
from protocol.commands import Code


def code_name(code: int) -> str:
    try:
        return Code(code).name
    except ValueError:
        return f"0x{code:02X}"


def describe(raw: bytes) -> dict:
    """Decoded fields of an unescaped frame (or an ``error``)."""
    try:
        msg = nsp.decode(raw)
    except nsp.MessageError as exc:
        return {"error": str(exc)}
    return {
        "dst": msg.dst,
        "src": msg.src,
        "mcf": msg.mcf,
        "code": msg.code,
        "name": code_name(msg.code),
        "poll_final": msg.poll,
        "b": msg.b,
        "ack": msg.ack,
        "data": msg.data.hex(),
    }


class LogWriteError(Exception):
    """The exchange log could not be opened or written (a full disk, a vanished directory): not a
    link failure, whatever the exchange was doing."""


class ExchangeLog:
    """Append-only JSONL writer (thread-safe, line-buffered); raises :class:`LogWriteError`."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        try:
            self._fh = open(self.path, "a", encoding="utf-8", buffering=1)
        except OSError as exc:
            raise LogWriteError(f"exchange log {self.path}: {exc}") from exc
        self._lock = threading.Lock()

    def record(self, direction: str, raw: bytes, note: str | None = None) -> None:
        entry = {
            "t": datetime.now(UTC).isoformat(timespec="microseconds"),
            "dir": direction,
            "hex": bytes(raw).hex(),
            **describe(raw),
        }
        if note:
            entry["note"] = note
        with self._lock:
            try:
                self._fh.write(json.dumps(entry) + "\n")
            except OSError as exc:
                raise LogWriteError(f"exchange log {self.path}: {exc}") from exc

    def close(self) -> None:
        self._fh.close()
