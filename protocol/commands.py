"""Command codes, NACK reasons and the typed data fields of every command and reply.

Layouts are little-endian. Documented ST-16 codes keep their research-note layouts; where the
notes are silent the layout is ours (see docs/ICD.md, where every such choice is marked).
Each payload class is declared once as a :class:`~protocol.layout.Layout` (struct head, wire
forms, tail), from which come ``pack() -> bytes`` and ``unpack(data) -> instance``; ``unpack``
raises :class:`PayloadError` (carrying a :class:`NackReason`, both from ``protocol.nack``) for a
data field it cannot accept. ``protocol.command_table`` says which payloads each code carries.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from protocol.layout import Form, Layout, le_int
from protocol.nack import NackReason as NackReason  # re-exported: shared by device and client
from protocol.nack import PayloadError as PayloadError
from protocol.nsp import MAX_DATA


class Code(IntEnum):
    """NSP command codes (0x00-0x13 the ICD's; 0x14-0x1A our extensions, on codes the ICD leaves
    unassigned: docs/ICD.md section 6)."""

    PING = 0x00
    INIT = 0x01
    PEEK = 0x02
    POKE = 0x03
    DIAGNOSTIC = 0x04
    CRC = 0x06
    READ_FILE = 0x07
    WRITE_FILE = 0x08
    READ_EDAC = 0x09
    WRITE_EDAC = 0x0A
    GO = 0x0B
    READ_RESULT = 0x0D
    IMAGE = 0x10
    COMBINATION = 0x12
    TIME = 0x13  #: the supervisor's clock (ICD page 1-35918)
    # --- extensions (ours) ---
    XFER_DATA = 0x14
    XFER_STATUS = 0x15
    XFER_COMMIT = 0x16
    SLOT_INFO = 0x17
    XFER_ABORT = 0x18
    FAULT = 0x19  #: scripted faults, only with ``st16-device --fault-injection`` (docs/ICD.md section 13)
    XFER_BEGIN = 0x1A  #: was 0x13 before TIME took that code (docs/ICD.md section 9)


#: Codes the emulator does not implement; always NACKed UNKNOWN_COMMAND.
UNASSIGNED = (0x05, 0x0C, 0x0E, 0x0F, 0x11, 0x1B, 0x1C, 0x1D, 0x1E, 0x1F)


APP_START_ADDRESS = 0x00002000  #: INIT address that starts the application (COSMOS)


class SlotRejected(Exception):
    """Raised by a slot validator: ``code`` (>= 0x0100) and ``message`` go into the NACK."""

    def __init__(self, code: int, message: str):
        if not NackReason.VALIDATOR_BASE <= code <= 0xFFFF:
            raise ValueError(f"validator reason code 0x{code:04X} outside 0x0100-0xFFFF")
        super().__init__(message)
        self.code = code
        self.message = message


# ----------------------------------------------------------------------------- NACK


@dataclass(frozen=True)
class NackInfo(Layout):
    reason: int
    text: str = ""

    HEAD = "<H"
    TAIL = "text"
    TAIL_MIN = 0
    TAIL_CODEC = (lambda text: text.encode("utf-8")[:200], lambda raw: raw.decode("utf-8", "replace"))
    NAME = "NACK"

    @classmethod
    def unpack(cls, data: bytes) -> NackInfo:
        return cls(0, data.hex()) if len(data) < 2 else cls._decode(data)

    @property
    def reason_name(self) -> str:
        try:
            return NackReason(self.reason).name
        except ValueError:
            return "VALIDATOR" if self.reason >= NackReason.VALIDATOR_BASE else f"0x{self.reason:04X}"


# ----------------------------------------------------------------------------- ST-16 commands


@dataclass(frozen=True)
class Init(Layout):
    address: int = APP_START_ADDRESS

    HEAD = "<I"
    NAME = "INIT"


@dataclass(frozen=True)
class Peek(Layout):
    """PEEK (ours): u32 address, u16 count -> reply u32 address + bytes."""

    address: int
    count: int

    HEAD = "<IH"
    NAME = "PEEK"


@dataclass(frozen=True)
class Poke(Layout):
    """POKE (ours): u32 address + bytes -> reply u32 address, u16 count."""

    address: int
    data: bytes

    HEAD = "<I"
    TAIL = "data"
    NAME = "POKE"


@dataclass(frozen=True)
class AddressedBytes(Layout):
    """Reply of PEEK / READ EDAC / READ RESULT parts: address echo + bytes (address width 2 or 4)."""

    address: int
    data: bytes
    width: int = 2

    FORMS = {2: Form("<H"), 4: Form("<I")}
    SELECT = "width"
    FORM_ARG = True
    TAIL = "data"
    TAIL_MIN = 0
    NAME = "addressed reply"

    @classmethod
    def unpack(cls, data: bytes, width: int = 2) -> AddressedBytes:
        return cls._decode(data, width)


@dataclass(frozen=True)
class WriteAck(Layout):
    """Reply of POKE / WRITE EDAC (ours): address echo + u16 count written."""

    address: int
    count: int
    width: int = 2

    FORMS = {2: Form("<HH"), 4: Form("<IH")}
    SELECT = "width"
    FORM_ARG = True
    NAME = "write reply"

    @classmethod
    def unpack(cls, data: bytes, width: int = 2) -> WriteAck:
        return cls._decode(data, width)


class MemorySpace(IntEnum):
    """Address spaces of the CRC command (ours)."""

    EDAC = 0
    MEMORY = 1
    RESULT = 2


@dataclass(frozen=True)
class CrcRequest(Layout):
    """CRC (ours): u8 space, u32 address, u32 length -> reply: same + u16 CRC-16/MCRF4XX."""

    space: int
    address: int
    length: int

    HEAD = "<BII"
    NAME = "CRC"


@dataclass(frozen=True)
class CrcReply(Layout):
    space: int
    address: int
    length: int
    crc: int

    HEAD = "<BIIH"
    NAME = "CRC reply"


_FILE_INDEX = (lambda a: a // 4, lambda i: i * 4)  #: file index = EDAC address / 4 (ICD page 1-35916)


@dataclass(frozen=True)
class ReadFile(Layout):
    """READ FILE: short form u8 file index, long form u16 file index; either is the EDAC address
    divided by 4 (ICD page 1-35916). ``address`` is the EDAC byte address. Reply: the same index
    field + the 4 bytes."""

    address: int
    long: bool = False

    FORMS = {False: Form("<B", {"address": _FILE_INDEX}), True: Form("<H", {"address": _FILE_INDEX})}
    SELECT = "long"
    NAME = "READ FILE"


@dataclass(frozen=True)
class WriteFile(Layout):
    """WRITE FILE: short form u8 index + 4 bytes, long form u16 index + 4 bytes; reply echoes it.
    The READ FILE reply has this layout too: the request's index/address field + the 4 bytes."""

    address: int
    value: bytes
    long: bool = False

    FORMS = ReadFile.FORMS
    SELECT = "long"
    TAIL = "value"
    TAIL_SIZE = 4
    NAME = "WRITE FILE"


@dataclass(frozen=True)
class ReadRange(Layout):
    """READ EDAC / READ RESULT: short form u16 address + u8 count (0 means 256), long form u16
    address + u16 count. Reply: u16 address + bytes (READ RESULT may split into parts)."""

    address: int
    count: int
    long: bool = True

    FORMS = {False: Form("<HB", {"count": (lambda n: n & 0xFF, lambda n: n or 256)}), True: Form("<HH")}
    SELECT = "long"
    NAME = "read"

    def pack(self) -> bytes:
        if not self.long and not 1 <= self.count <= 256:
            raise ValueError("short form count must be 1..256")
        return super().pack()


@dataclass(frozen=True)
class WriteEdac(Layout):
    """WRITE EDAC (ours): u16 address + bytes -> reply u16 address, u16 count."""

    address: int
    data: bytes

    HEAD = "<H"
    TAIL = "data"
    NAME = "WRITE EDAC"


class GoBits(IntEnum):
    """GO code bits (COSMOS names; INJECTED is ours)."""

    ON = 0x01
    LOAD_NAND = 0x02  #: boot the functional processor from NAND when it is not running (ICD page 1-35916)
    NOT_OFF = 0x04  #: with NO_RESET: use the cached triangle table (ICD page 1-35924)
    COMMAND = 0x08  #: start a sequence; a GO without it terminates a running one
    TEST = 0x10
    NO_RESET = 0x20
    INJECTED = 0x40  #: process image buffer 0 (IMAGE Rectangular Poke) instead of exposing (ours)


CACHED_TABLE_BITS = GoBits.NOT_OFF | GoBits.NO_RESET  #: both set: the triangle table may be cached


GO_OPERATIONAL = 0x0B  #: ON | LOAD_NAND | COMMAND, COSMOS routine attitude read


@dataclass(frozen=True)
class Go(Layout):
    code: int = GO_OPERATIONAL

    HEAD = "<B"
    NAME = "GO"


@dataclass(frozen=True)
class DarkWindow(Layout):
    """IMAGE subcommand 0 (26 bytes): buffer, first row/column, rows, columns, 8 dark values."""

    buffer: int
    row: int
    col: int
    rows: int
    cols: int
    values: tuple[int, ...] = (0,) * 8

    SUBCOMMAND = 0

    HEAD = "<BBHHHH8H"
    FIELDS = ("SUBCOMMAND", "buffer", "row", "col", "rows", "cols", "values")
    NAME = "IMAGE dark window"


@dataclass(frozen=True)
class RectangularPoke(Layout):
    """IMAGE subcommand 1 (ours: the ICD page shows no layout): buffer (0 or 1), first row and
    column, rows, columns, then rows x columns u16 pixel values, row by row (``pixels``, raw
    little-endian bytes). The reply echoes the 10-byte head (``pixels`` empty)."""

    buffer: int
    row: int
    col: int
    rows: int
    cols: int
    pixels: bytes = b""

    SUBCOMMAND = 1

    HEAD = "<BBHHHH"
    FIELDS = ("SUBCOMMAND", "buffer", "row", "col", "rows", "cols")
    TAIL = "pixels"
    TAIL_MIN = 0
    NAME = "IMAGE rectangular poke"

    def head(self) -> bytes:
        """The reply: this poke's 10-byte head."""
        return RectangularPoke(self.buffer, self.row, self.col, self.rows, self.cols).pack()


MAX_POKE_PIXELS = (MAX_DATA - struct.calcsize(RectangularPoke.HEAD)) // 2  #: pixels one poke carries


class _MaskForms(dict[int, Form]):
    """COMBINATION forms by mask width: u8 go code + the mask in ``n`` bytes (any ``n`` packs)."""

    @staticmethod
    def form(n: int) -> Form:
        return Form(f"<B{n}s", {"mask": le_int(n)})

    def __missing__(self, n: int) -> Form:
        return self.form(n)


@dataclass(frozen=True)
class Combination(Layout):
    """COMBINATION: u8 go code + section mask; 4 data bytes (24-bit mask, as COSMOS sends) or
    5 bytes (32-bit mask). Both accepted (ours)."""

    go_code: int
    mask: int
    mask_bytes: int = 4

    FORMS = _MaskForms({n: _MaskForms.form(n) for n in (3, 4)})  #: the two the device accepts
    SELECT = "mask_bytes"
    NAME = "COMBINATION"


class SequenceState(IntEnum):
    """Byte 0 of a COMBINATION failure reply (ICD page 1-35918 names the field; its table is not
    public, so these values are ours)."""

    IDLE = 0  #: no sequence has run since power-on or the last reset
    RUNNING = 1  #: a sequence is running (or the functional processor is booting)
    DONE = 2  #: the last sequence completed
    TERMINATED = 3  #: the last sequence was terminated by a GO, or abandoned by a reset


@dataclass(frozen=True)
class CombinationFailure(Layout):
    """COMBINATION failure reply (ICD page 1-35918): ACK 0, one message with Final set; u8
    sequence state (:class:`SequenceState`), then the error text, ASCII, truncated to fit."""

    state: int
    text: str = ""

    HEAD = "<B"
    TAIL = "text"
    TAIL_MIN = 0
    TAIL_CODEC = (
        lambda text: text.encode("ascii", "replace")[: MAX_DATA - 1],
        lambda raw: raw.decode("ascii", "replace"),
    )
    NAME = "COMBINATION failure"

    @property
    def state_name(self) -> str:
        try:
            return SequenceState(self.state).name
        except ValueError:
            return f"state {self.state}"


# ----------------------------------------------------------------------------- TIME

TIME_BITS = 48  #: width of the supervisor clock (ICD page 1-35918)


@dataclass(frozen=True)
class TimeReply(Layout):
    """TIME reply (ICD page 1-35918): the supervisor clock, an unsigned 48-bit count of
    microseconds whose least significant bit is 0, latched when the command's final FEND arrived.
    Little-endian, as every field of the link (ours: the page shows no byte order). TIME takes
    no data field."""

    micros: int

    FORMS = {None: Form("<6s", {"micros": le_int(6)})}
    NAME = "TIME reply"


# ----------------------------------------------------------------------------- DIAGNOSTIC

DIAG_ERROR_FIELDS = ("framing", "runt", "oversize", "bad_crc", "fifo_overflow")
DIAG_COUNT_FIELDS = ("accepted", "nacked", "silent", "other_address", "replies")


DIAG_CLEAR = 0x01  #: DIAGNOSTIC flag: clear the counters after reading


@dataclass(frozen=True)
class DiagnosticRequest(Layout):
    """DIAGNOSTIC command data: none, or u8 flags (bit 0 :data:`DIAG_CLEAR`); ``sent`` tells
    whether the flags byte is on the wire."""

    flags: int = 0
    sent: bool = False

    FORMS = {False: Form("<"), True: Form("<B")}
    SELECT = "sent"
    NAME = "DIAGNOSTIC"
    LENGTH_TEXT = "DIAGNOSTIC takes 0 or 1 data byte"

    @classmethod
    def clearing(cls, clear: bool) -> DiagnosticRequest:
        """The request a client sends: the clear flag, or no data field."""
        return cls(DIAG_CLEAR, True) if clear else cls()


@dataclass(frozen=True)
class Diagnostics(Layout):
    """DIAGNOSTIC reply (ours): 5 error counters, 5 traffic counters, 32 per-code counts, all u32.

    Command data: :class:`DiagnosticRequest`.
    """

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
    per_code: tuple[int, ...] = field(default=(0,) * 32)

    SIZE = 4 * (10 + 32)

    HEAD = "<" + "I" * len(DIAG_ERROR_FIELDS + DIAG_COUNT_FIELDS) + "32I"
    WRAP = True  #: counters are modulo 2**32
    NAME = "DIAGNOSTIC reply"

    def as_dict(self) -> dict[str, Any]:
        out = {name: getattr(self, name) for name in DIAG_ERROR_FIELDS + DIAG_COUNT_FIELDS}
        out["per_code"] = {f"0x{c:02X}": n for c, n in enumerate(self.per_code) if n}
        return out


# ----------------------------------------------------------------------------- extensions (ours)


class Slot(IntEnum):
    CATALOG = 0
    FRAME = 1
    PARAMS = 2
    CATALOG_PATCH = 3  #: a ``protocol.catalog_patch`` applied to slot 0's image at COMMIT


MAX_SLOT_BYTES = 64 * 1024 * 1024  #: largest image a slot accepts (ours)
UPLOAD_CHUNK = 4096  #: XFER DATA payload size the ground client uses


@dataclass(frozen=True)
class XferBegin(Layout):
    """XFER BEGIN: u8 slot, u32 total length, u32 CRC-32 of the whole image. Reply: XferStatus.
    Begin with the same length and CRC as a pending transfer resumes it."""

    slot: int
    length: int
    crc32: int

    HEAD = "<BII"
    NAME = "XFER BEGIN"


@dataclass(frozen=True)
class XferData(Layout):
    """XFER DATA: u8 slot, u32 offset, bytes. Reply (if polled): u8 slot, u32 contiguous bytes."""

    slot: int
    offset: int
    data: bytes

    HEAD = "<BI"
    TAIL = "data"
    NAME = "XFER DATA"


@dataclass(frozen=True)
class XferDataAck(Layout):
    slot: int
    contiguous: int

    HEAD = "<BI"
    NAME = "XFER DATA reply"


@dataclass(frozen=True)
class SlotRequest(Layout):
    """XFER STATUS / XFER COMMIT / SLOT INFO / XFER ABORT command data: u8 slot."""

    slot: int

    HEAD = "<B"
    NAME = "slot request"


class XferState(IntEnum):
    NONE = 0
    RECEIVING = 1
    COMPLETE = 2  #: every byte received, waiting for COMMIT


MAX_STATUS_RANGES = 64


@dataclass(frozen=True)
class XferStatus(Layout):
    """XFER STATUS reply: u8 slot, u8 state, u32 length, u32 CRC-32, u32 contiguous, u32 received,
    u16 number of missing ranges, then up to 64 missing ranges (u32 offset, u32 length)."""

    slot: int
    state: int
    length: int = 0
    crc32: int = 0
    contiguous: int = 0
    received: int = 0
    n_missing: int = 0
    missing: tuple[tuple[int, int], ...] = ()

    HEAD = "<BBIIIIH"
    TAIL = "missing"
    TAIL_MIN = 0
    ITEM = "<II"  #: one missing range: offset, length
    ITEMS_NAME = "ranges"
    MAX_ITEMS = MAX_STATUS_RANGES
    NAME = "XFER STATUS reply"


@dataclass(frozen=True)
class SlotImage(Layout):
    """XFER COMMIT reply and SLOT INFO reply: u8 slot, u8 active, u32 length, u32 CRC-32, then
    (SLOT INFO only) a slot-specific info blob (UTF-8 JSON for the built-in handlers)."""

    slot: int
    active: bool
    length: int
    crc32: int
    info: bytes = b""

    FORMS = {None: Form("<BBII", {"active": (int, bool)})}
    TAIL = "info"
    TAIL_MIN = 0
    NAME = "slot reply"


class FaultAction(IntEnum):
    """FAULT subcommands (ours, docs/ICD.md section 13)."""

    LOAD = 0  #: arm the fault script that follows (UTF-8 lines), replacing the armed one
    CLEAR = 1  #: disarm every fault
    STATUS = 2  #: report only


MAX_FAULT_SCRIPT = MAX_DATA - 1  #: bytes of script one FAULT load carries (one NSP data field)


@dataclass(frozen=True)
class FaultRequest(Layout):
    """FAULT command data: u8 subcommand (:class:`FaultAction`), then for LOAD the script as UTF-8
    text (the fault-file format, at most :data:`MAX_FAULT_SCRIPT` bytes; empty otherwise)."""

    action: int
    script: bytes = b""

    HEAD = "<B"
    TAIL = "script"
    TAIL_MIN = 0
    NAME = "FAULT"


@dataclass(frozen=True)
class FaultStatus(Layout):
    """FAULT reply: u8 subcommand echo, u32 faults armed now, then the nine fault counters
    (``protocol.edac.FAULT_COUNTERS`` order, u32 each, as at EDAC 0x009C)."""

    action: int
    armed: int
    counters: tuple[int, ...] = (0,) * 9

    HEAD = "<BI9I"
    WRAP = True  #: counters are modulo 2**32
    NAME = "FAULT reply"
