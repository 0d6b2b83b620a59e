"""SLIP framing (RFC 1055 values) with a streaming decoder for bytes that arrive in pieces.

A frame on the wire is ``FEND, escaped bytes, FEND``; ``FESC TFEND`` stands for a data 0xC0 and
``FESC TFESC`` for a data 0xDB. Back-to-back FENDs (empty frames) are idle and not reported.
A FESC followed by anything else is a framing error; a frame whose decoded length exceeds the
decoder's limit is oversize. Both are reported as events and the rest of that frame (up to the
next FEND) is discarded.
"""

from __future__ import annotations

from dataclasses import dataclass

FEND = 0xC0
FESC = 0xDB
TFEND = 0xDC
TFESC = 0xDD

_FEND_B = bytes([FEND])
_FESC_B = bytes([FESC])


def escape(data: bytes) -> bytes:
    """Escape FEND and FESC in ``data`` (no delimiters added)."""
    return data.replace(_FESC_B, b"\xdb\xdd").replace(_FEND_B, b"\xdb\xdc")


def encode(data: bytes) -> bytes:
    """One SLIP frame: leading FEND (as COSMOS sends), escaped ``data``, trailing FEND."""
    return _FEND_B + escape(data) + _FEND_B


class BadEscape(ValueError):
    """A FESC not followed by TFEND or TFESC."""


def unescape(data: bytes) -> bytes:
    """Undo :func:`escape`; raises :class:`BadEscape` for a FESC not followed by TFEND/TFESC."""
    if FESC not in data:
        return bytes(data)
    parts = bytes(data).split(_FESC_B)
    out = [parts[0]]
    for part in parts[1:]:
        if not part:
            raise BadEscape("FESC at end of frame")
        if part[0] == TFEND:
            out.append(_FEND_B)
        elif part[0] == TFESC:
            out.append(_FESC_B)
        else:
            raise BadEscape(f"FESC followed by 0x{part[0]:02X}")
        out.append(part[1:])
    return b"".join(out)


@dataclass(frozen=True)
class Frame:
    """A complete, unescaped frame."""

    data: bytes


@dataclass(frozen=True)
class FramingError:
    """A frame dropped for a bad escape; ``raw`` is its escaped bytes (possibly truncated)."""

    raw: bytes
    reason: str


@dataclass(frozen=True)
class Oversize:
    """A frame dropped because it exceeds the limit; ``raw`` is its first escaped bytes."""

    raw: bytes


class Decoder:
    """Streaming SLIP decoder. :meth:`feed` takes any piece of the byte stream and returns the
    events (:class:`Frame`, :class:`FramingError`, :class:`Oversize`) completed by it.

    Bytes before the first FEND are treated as the tail of a frame whose start was missed and are
    decoded like any other frame (a receiver cannot tell the difference).
    """

    def __init__(self, max_frame: int = 8192):
        if max_frame < 1:
            raise ValueError("max_frame must be positive")
        self.max_frame = max_frame
        self._buf = bytearray()
        self._discarding = False  # inside an oversize frame: drop until the next FEND

    @property
    def pending(self) -> int:
        """Bytes of an unfinished frame held by the decoder."""
        return len(self._buf)

    def feed(self, chunk: bytes) -> list[Frame | FramingError | Oversize]:
        events: list[Frame | FramingError | Oversize] = []
        start = 0
        n = len(chunk)
        while start < n:
            end = chunk.find(FEND, start)
            if end < 0:
                self._append(chunk[start:], events)
                break
            self._append(chunk[start:end], events)
            self._finish(events)
            start = end + 1
        return events

    def _append(self, piece: bytes, events: list[Frame | FramingError | Oversize]) -> None:
        if self._discarding or not piece:
            return
        self._buf += piece
        # An escaped frame is at most twice its decoded length: beyond that it is surely oversize.
        if len(self._buf) > 2 * self.max_frame:
            events.append(Oversize(bytes(self._buf[:64])))
            self._buf.clear()
            self._discarding = True

    def _finish(self, events: list[Frame | FramingError | Oversize]) -> None:
        if self._discarding:
            self._discarding = False
            return
        if not self._buf:
            return
        raw = bytes(self._buf)
        self._buf.clear()
        try:
            data = unescape(raw)
        except BadEscape as exc:
            events.append(FramingError(raw[:256], str(exc)))
            return
        if len(data) > self.max_frame:
            events.append(Oversize(raw[:64]))
            return
        events.append(Frame(data))
