"""A minimal NSP codec and link, written for the conformance suite from the star tracker's public
interface control document (doclecture.net pages 1-35908 to 1-35924) and nothing else of this
project: it imports nothing from ``protocol/``, ``firmware_model/`` or ``ground/`` (a guard test,
``test_conf_guard.py``, checks that), so a change there can never move both sides of a test.

* SLIP framing (1-35919 names FEND, FESC, TFEND, TFESC; the byte values are RFC 1055's).
* NSP message: destination address, source address, message control field (MCF), data, CRC
  (1-35910: bit 7 Poll/Final, bit 6 B, bit 5 ACK, bits 4-0 command code).
* CRC: the 16-bit CCITT polynomial x^16 + x^12 + x^5 + 1 (1-35910), reflected (0x8408), initial
  value 0xFFFF, no final XOR, low byte first: CRC-16/MCRF4XX. The page is cut off after "The
  initial shift register value i..."; the rest is the emulator's docs/ICD.md section 3, which a
  device built to the same public description must match byte for byte (test_conf_codec.py).
"""

from __future__ import annotations

import os
import select
import time
from dataclasses import dataclass

FEND = 0xC0
FESC = 0xDB
TFEND = 0xDC
TFESC = 0xDD

POLL = 0x80  #: command: Poll; reply: Final
FINAL = 0x80
B_BIT = 0x40
ACK = 0x20
CODE_MASK = 0x1F

DEVICE_ADDRESS = 0x0E
HOST_ADDRESS = 0x11

#: Hang guard of one read: a reply that has not come by then is a hang, not a slow machine.
HANG_S = 60.0


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/MCRF4XX: polynomial 0x1021 reflected (0x8408), init 0xFFFF, no final XOR."""
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    return crc


def slip_escape(payload: bytes) -> bytes:
    out = bytearray()
    for byte in payload:
        if byte == FEND:
            out += bytes((FESC, TFEND))
        elif byte == FESC:
            out += bytes((FESC, TFESC))
        else:
            out.append(byte)
    return bytes(out)


def slip_frame(payload: bytes) -> bytes:
    """FEND, the escaped payload, FEND (a leading FEND, as COSMOS sends)."""
    return bytes((FEND,)) + slip_escape(payload) + bytes((FEND,))


def nsp_payload(dst: int, src: int, mcf: int, data: bytes = b"", *, crc: int | None = None) -> bytes:
    """dst, src, MCF, data and the CRC (low byte first) over them; ``crc`` overrides it."""
    body = bytes((dst, src, mcf)) + data
    value = crc16(body) if crc is None else crc
    return body + bytes((value & 0xFF, value >> 8))


def nsp_frame(dst: int, src: int, mcf: int, data: bytes = b"") -> bytes:
    return slip_frame(nsp_payload(dst, src, mcf, data))


class SlipDecoder:
    """Feeds bytes, returns whole frames: ``(payload, ok)``; ``ok`` is False for a frame with an
    escape error. Empty frames (back-to-back FENDs) are idle and not returned."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._esc = False
        self._bad = False

    def feed(self, data: bytes) -> list[tuple[bytes, bool]]:
        out: list[tuple[bytes, bool]] = []
        for byte in data:
            if byte == FEND:
                if self._buf or self._bad:
                    out.append((bytes(self._buf), not self._bad))
                self._buf.clear()
                self._esc = self._bad = False
            elif self._esc:
                self._esc = False
                if byte == TFEND:
                    self._buf.append(FEND)
                elif byte == TFESC:
                    self._buf.append(FESC)
                else:
                    self._bad = True
            elif byte == FESC:
                self._esc = True
            else:
                self._buf.append(byte)
        return out


@dataclass(frozen=True)
class Msg:
    """One decoded NSP message."""

    dst: int
    src: int
    mcf: int
    data: bytes
    crc_ok: bool

    @property
    def code(self) -> int:
        return self.mcf & CODE_MASK

    @property
    def final(self) -> bool:
        return bool(self.mcf & FINAL)

    @property
    def b(self) -> bool:
        return bool(self.mcf & B_BIT)

    @property
    def ack(self) -> bool:
        return bool(self.mcf & ACK)

    @property
    def nack_reason(self) -> int:
        """The emulator's NACK data (ours): u16 reason, little-endian, then text."""
        return int.from_bytes(self.data[:2], "little")


def parse(payload: bytes) -> Msg:
    """A frame's payload as a message (``crc_ok`` says whether its CRC checks)."""
    if len(payload) < 5:
        raise ValueError(f"runt of {len(payload)} bytes")
    body, crc = payload[:-2], int.from_bytes(payload[-2:], "little")
    return Msg(body[0], body[1], body[2], bytes(body[3:]), crc16(body) == crc)


class Link:
    """The host side of the link on a pty (or any file descriptor pyserial opens raw)."""

    def __init__(self, port, *, device: int = DEVICE_ADDRESS, host: int = HOST_ADDRESS) -> None:
        self.port = port  # a pyserial Serial
        self.device = device
        self.host = host
        self._decoder = SlipDecoder()
        self._pending: list[Msg] = []
        self._b = False

    # -- raw bytes ----------------------------------------------------------------------------
    def write(self, raw: bytes) -> None:
        self.port.write(raw)
        self.port.flush()

    def _fill(self, deadline: float) -> None:
        """Reads what has arrived (waiting until ``deadline`` for the first byte)."""
        fd = self.port.fileno()
        wait = max(0.0, deadline - time.monotonic())
        ready, _, _ = select.select([fd], [], [], wait)
        if not ready:
            raise TimeoutError(f"no reply within the {HANG_S} s hang guard")
        chunk = os.read(fd, 65536)
        for payload, ok in self._decoder.feed(chunk):
            if ok and len(payload) >= 5:
                self._pending.append(parse(payload))

    def next_message(self) -> Msg:
        deadline = time.monotonic() + HANG_S
        while not self._pending:
            self._fill(deadline)
        return self._pending.pop(0)

    def drain(self) -> None:
        """Forgets anything already received."""
        self._pending.clear()
        fd = self.port.fileno()
        while select.select([fd], [], [], 0)[0]:
            if not os.read(fd, 65536):
                break

    # -- messages -----------------------------------------------------------------------------
    def mcf(self, code: int, *, poll: bool = True, b: bool | None = None, ack_bit: bool = False) -> int:
        if b is None:
            self._b = not self._b
            b = self._b
        return (POLL if poll else 0) | (B_BIT if b else 0) | (ACK if ack_bit else 0) | (code & CODE_MASK)

    def send(
        self,
        code: int,
        data: bytes = b"",
        *,
        poll: bool = True,
        b: bool | None = None,
        ack_bit: bool = False,
        dst: int | None = None,
        src: int | None = None,
    ) -> int:
        """Sends one command; returns its MCF."""
        mcf = self.mcf(code, poll=poll, b=b, ack_bit=ack_bit)
        dst = self.device if dst is None else dst
        src = self.host if src is None else src
        self.write(nsp_frame(dst, src, mcf, data))
        return mcf

    def replies(self) -> list[Msg]:
        """The messages of one reply: every message up to and including the first with Final."""
        out = [self.next_message()]
        while not out[-1].final:
            out.append(self.next_message())
        # 1-35910, "Message CRC": every message the tracker sends carries a CRC that checks
        assert all(m.crc_ok for m in out), "a reply whose CRC does not check"
        return out

    def request(self, code: int, data: bytes = b"", **kw) -> list[Msg]:
        """A polled command and all messages of its reply."""
        self.send(code, data, **kw)
        return self.replies()

    def one(self, code: int, data: bytes = b"", **kw) -> Msg:
        """A polled command whose reply is one message."""
        msgs = self.request(code, data, **kw)
        assert len(msgs) == 1, f"expected one message, got {len(msgs)}"
        return msgs[0]

    def before_sentinel(self, raw: bytes) -> list[Msg]:
        """Writes ``raw``, then a polled sentinel (READ EDAC of 4 bytes at 0, code 0x09); returns
        every message that arrived before the sentinel's reply. The device answers frames in the
        order they arrive, so an empty list proves ``raw`` got no reply, without waiting on a
        clock."""
        self.drain()
        self.write(raw)
        sentinel_b = not self._b
        self.send(0x09, (0).to_bytes(2, "little") + bytes((4,)), b=sentinel_b)
        self._b = sentinel_b
        before: list[Msg] = []
        while True:
            msg = self.next_message()
            if msg.code == 0x09 and msg.b == sentinel_b and msg.final and msg.src == self.device:
                return before
            before.append(msg)
