"""NSP messages: addresses, message-control field (MCF), data field, CRC-16.

Unescaped layout: ``dst, src, MCF, data..., crc_lo, crc_hi``; the CRC (CRC-16/MCRF4XX) covers
dst, src, MCF and data. MCF bits: 0x80 Poll (command) / Final (reply), 0x40 B (copied from the
command into its reply), 0x20 ACK (reply only), 0x1F command code.
"""

from __future__ import annotations

from dataclasses import dataclass

from . import slip
from .crc import crc16_mcrf4xx

POLL = 0x80
FINAL = 0x80
B_BIT = 0x40
ACK = 0x20
CODE_MASK = 0x1F

DEVICE_ADDRESS = 0x0E  #: default tracker address (COSMOS)
HOST_ADDRESS = 0x11  #: default host address (COSMOS)

MIN_MESSAGE = 5  #: dst, src, MCF and two CRC bytes; shorter is a runt
MAX_DATA = 4160  #: largest data field the device accepts (ours: a 4096-byte upload chunk + header)
MAX_MESSAGE = MAX_DATA + MIN_MESSAGE


class MessageError(ValueError):
    """An unescaped frame that is not a valid NSP message; ``raw`` holds its bytes."""

    def __init__(self, message: str, raw: bytes):
        super().__init__(message)
        self.raw = raw


class Runt(MessageError):
    """Fewer than 5 bytes."""


class BadCrc(MessageError):
    """CRC mismatch."""


@dataclass(frozen=True)
class Message:
    """One NSP message. ``mcf`` is the full control byte; ``data`` the data field."""

    dst: int
    src: int
    mcf: int
    data: bytes = b""

    @property
    def code(self) -> int:
        return self.mcf & CODE_MASK

    @property
    def poll(self) -> bool:
        """Command: reply requested. Same bit as :attr:`final`."""
        return bool(self.mcf & POLL)

    @property
    def final(self) -> bool:
        """Reply: last message of the reply."""
        return bool(self.mcf & FINAL)

    @property
    def b(self) -> bool:
        return bool(self.mcf & B_BIT)

    @property
    def ack(self) -> bool:
        return bool(self.mcf & ACK)

    def encode(self) -> bytes:
        """Unescaped bytes including the CRC (low byte first)."""
        body = bytes((self.dst, self.src, self.mcf)) + bytes(self.data)
        crc = crc16_mcrf4xx(body)
        return body + bytes((crc & 0xFF, crc >> 8))

    def frame(self) -> bytes:
        """SLIP-framed bytes ready for the wire."""
        return slip.encode(self.encode())


def make_mcf(code: int, *, poll_or_final: bool = True, b: bool = False, ack: bool = False) -> int:
    """Compose an MCF from its fields."""
    if not 0 <= code <= CODE_MASK:
        raise ValueError(f"command code 0x{code:02X} outside 0x00-0x1F")
    return (POLL if poll_or_final else 0) | (B_BIT if b else 0) | (ACK if ack else 0) | code


def command(dst: int, src: int, code: int, data: bytes = b"", *, poll: bool = True, b: bool = False) -> Message:
    """A command message (ACK bit clear, as the host sends it)."""
    return Message(dst, src, make_mcf(code, poll_or_final=poll, b=b), bytes(data))


def reply_to(cmd: Message, data: bytes = b"", *, ack: bool = True, final: bool = True) -> Message:
    """The device's reply to ``cmd``: addresses swapped, code and B copied."""
    return Message(cmd.src, cmd.dst, make_mcf(cmd.code, poll_or_final=final, b=cmd.b, ack=ack), bytes(data))


def decode(raw: bytes) -> Message:
    """Parse an unescaped frame; raises :class:`Runt` or :class:`BadCrc`."""
    raw = bytes(raw)
    if len(raw) < MIN_MESSAGE:
        raise Runt(f"runt: {len(raw)} bytes, need at least {MIN_MESSAGE}", raw)
    if crc16_mcrf4xx(raw) != 0:
        got = raw[-2] | raw[-1] << 8
        want = crc16_mcrf4xx(raw[:-2])
        raise BadCrc(f"bad CRC: got 0x{got:04X}, computed 0x{want:04X}", raw)
    return Message(raw[0], raw[1], raw[2], raw[3:-2])
