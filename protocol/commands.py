"""Command codes, NACK reasons and the typed data fields of every command and reply.

Layouts are little-endian. Documented ST-16 codes keep their research-note layouts; where the
notes are silent the layout is ours (see docs/ICD.md, where every such choice is marked).
Each payload class has ``pack() -> bytes`` and ``unpack(data) -> instance``; ``unpack`` raises
:class:`PayloadError` (carrying a :class:`NackReason`) for a data field it cannot accept.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field, fields
from enum import IntEnum
from typing import Any, ClassVar, TypeVar


class Code(IntEnum):
    """NSP command codes (0x00-0x12 ST-16; 0x13-0x19 our extensions)."""

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
    # --- extensions (ours) ---
    XFER_BEGIN = 0x13
    XFER_DATA = 0x14
    XFER_STATUS = 0x15
    XFER_COMMIT = 0x16
    SLOT_INFO = 0x17
    XFER_ABORT = 0x18


#: Codes the research does not document, plus 0x1F; always NACKed (as are unused 0x19-0x1E).
UNASSIGNED = (0x05, 0x0C, 0x0E, 0x0F, 0x11, 0x19, 0x1A, 0x1B, 0x1C, 0x1D, 0x1E, 0x1F)

APP_START_ADDRESS = 0x00002000  #: INIT address that starts the application (COSMOS)


class NackReason(IntEnum):
    """First two bytes (u16 LE) of a NACK's data field, followed by UTF-8 text (ours)."""

    UNKNOWN_COMMAND = 0x0001
    BAD_LENGTH = 0x0002
    BAD_ADDRESS = 0x0003
    READ_ONLY = 0x0004
    WRONG_MODE = 0x0005
    BUSY = 0x0006
    BAD_PARAMETER = 0x0007
    BAD_SLOT = 0x0008
    NO_TRANSFER = 0x0009
    OUT_OF_RANGE = 0x000A
    INCOMPLETE = 0x000B
    CRC_MISMATCH = 0x000C
    NOT_SUPPORTED = 0x000D
    STORAGE_ERROR = 0x000E
    TOO_LARGE = 0x000F
    INTERNAL = 0x00FF  #: unexpected device-side exception (a bug; the device keeps serving)
    #: 0x0100-0xFFFF: reasons raised by slot validators (:class:`SlotRejected` codes)
    VALIDATOR_BASE = 0x0100


class PayloadError(ValueError):
    """A data field that cannot be accepted; becomes a NACK with ``reason``."""

    def __init__(self, reason: NackReason | int, message: str):
        super().__init__(message)
        self.reason = int(reason)
        self.message = message


class SlotRejected(Exception):
    """Raised by a slot validator: ``code`` (>= 0x0100) and ``message`` go into the NACK."""

    def __init__(self, code: int, message: str):
        if not NackReason.VALIDATOR_BASE <= code <= 0xFFFF:
            raise ValueError(f"validator reason code 0x{code:04X} outside 0x0100-0xFFFF")
        super().__init__(message)
        self.code = code
        self.message = message


def _need(data: bytes, sizes: tuple[int, ...], what: str) -> None:
    if len(data) not in sizes:
        allowed = " or ".join(str(s) for s in sizes)
        raise PayloadError(NackReason.BAD_LENGTH, f"{what}: {len(data)} data bytes, expected {allowed}")


def _at_least(data: bytes, size: int, what: str) -> None:
    if len(data) < size:
        raise PayloadError(NackReason.BAD_LENGTH, f"{what}: {len(data)} data bytes, expected at least {size}")


_L = TypeVar("_L", bound="_Layout")


class _Layout:
    """A payload declared once: ``HEAD`` (a struct format) packs the dataclass's leading fields in
    declaration order, one item each; ``TAIL``, when set, names a final ``bytes`` field carried
    raw after the head (at least one byte). ``NAME`` labels length errors. ``pack`` and
    ``unpack`` both come from this declaration."""

    HEAD: ClassVar[str]
    TAIL: ClassVar[str | None] = None
    NAME: ClassVar[str]

    @classmethod
    def _head_names(cls) -> list[str]:
        n = len(struct.unpack(cls.HEAD, bytes(struct.calcsize(cls.HEAD))))
        return [f.name for f in fields(cls) if f.name != cls.TAIL][:n]  # type: ignore[arg-type]

    def pack(self) -> bytes:
        head = struct.pack(self.HEAD, *(getattr(self, name) for name in self._head_names()))
        return head + bytes(getattr(self, self.TAIL)) if self.TAIL else head

    @classmethod
    def unpack(cls: type[_L], data: bytes) -> _L:
        size = struct.calcsize(cls.HEAD)
        if cls.TAIL:
            _at_least(data, size + 1, cls.NAME)
        else:
            _need(data, (size,), cls.NAME)
        values: dict[str, Any] = dict(zip(cls._head_names(), struct.unpack_from(cls.HEAD, data)))
        if cls.TAIL:
            values[cls.TAIL] = bytes(data[size:])
        return cls(**values)


# ----------------------------------------------------------------------------- NACK


@dataclass(frozen=True)
class NackInfo:
    reason: int
    text: str = ""

    def pack(self) -> bytes:
        return struct.pack("<H", self.reason) + self.text.encode("utf-8")[:200]

    @classmethod
    def unpack(cls, data: bytes) -> NackInfo:
        if len(data) < 2:
            return cls(0, data.hex())
        return cls(struct.unpack_from("<H", data)[0], bytes(data[2:]).decode("utf-8", "replace"))

    @property
    def reason_name(self) -> str:
        try:
            return NackReason(self.reason).name
        except ValueError:
            return "VALIDATOR" if self.reason >= NackReason.VALIDATOR_BASE else f"0x{self.reason:04X}"


# ----------------------------------------------------------------------------- ST-16 commands


@dataclass(frozen=True)
class Init(_Layout):
    address: int = APP_START_ADDRESS

    HEAD = "<I"
    NAME = "INIT"


@dataclass(frozen=True)
class Peek(_Layout):
    """PEEK (ours): u32 address, u16 count -> reply u32 address + bytes."""

    address: int
    count: int

    HEAD = "<IH"
    NAME = "PEEK"


@dataclass(frozen=True)
class Poke(_Layout):
    """POKE (ours): u32 address + bytes -> reply u32 address, u16 count."""

    address: int
    data: bytes

    HEAD = "<I"
    TAIL = "data"
    NAME = "POKE"


@dataclass(frozen=True)
class AddressedBytes:
    """Reply of PEEK / READ EDAC / READ RESULT parts: address echo + bytes (address width 2 or 4)."""

    address: int
    data: bytes
    width: int = 2

    def pack(self) -> bytes:
        return self.address.to_bytes(self.width, "little") + bytes(self.data)

    @classmethod
    def unpack(cls, data: bytes, width: int = 2) -> AddressedBytes:
        _at_least(data, width, "addressed reply")
        return cls(int.from_bytes(data[:width], "little"), bytes(data[width:]), width)


@dataclass(frozen=True)
class WriteAck:
    """Reply of POKE / WRITE EDAC (ours): address echo + u16 count written."""

    address: int
    count: int
    width: int = 2

    def pack(self) -> bytes:
        return self.address.to_bytes(self.width, "little") + struct.pack("<H", self.count)

    @classmethod
    def unpack(cls, data: bytes, width: int = 2) -> WriteAck:
        _need(data, (width + 2,), "write reply")
        return cls(int.from_bytes(data[:width], "little"), struct.unpack_from("<H", data, width)[0], width)


class MemorySpace(IntEnum):
    """Address spaces of the CRC command (ours)."""

    EDAC = 0
    MEMORY = 1
    RESULT = 2


@dataclass(frozen=True)
class CrcRequest(_Layout):
    """CRC (ours): u8 space, u32 address, u32 length -> reply: same + u16 CRC-16/MCRF4XX."""

    space: int
    address: int
    length: int

    HEAD = "<BII"
    NAME = "CRC"


@dataclass(frozen=True)
class CrcReply(_Layout):
    space: int
    address: int
    length: int
    crc: int

    HEAD = "<BIIH"
    NAME = "CRC reply"


@dataclass(frozen=True)
class ReadFile:
    """READ FILE: short form u8 file index (EDAC address = 4 * index, ours), long form u16 EDAC
    address (multiple of 4). Reply: the same index/address field + the 4 bytes."""

    address: int
    long: bool = False

    def pack(self) -> bytes:
        return struct.pack("<H", self.address) if self.long else struct.pack("<B", self.address // 4)

    @classmethod
    def unpack(cls, data: bytes) -> ReadFile:
        _need(data, (1, 2), "READ FILE")
        if len(data) == 1:
            return cls(data[0] * 4, False)
        return cls(struct.unpack("<H", data)[0], True)


@dataclass(frozen=True)
class WriteFile:
    """WRITE FILE: short form u8 index + 4 bytes, long form u16 address + 4 bytes; reply echoes it."""

    address: int
    value: bytes
    long: bool = False

    def pack(self) -> bytes:
        head = struct.pack("<H", self.address) if self.long else struct.pack("<B", self.address // 4)
        return head + bytes(self.value)

    @classmethod
    def unpack(cls, data: bytes) -> WriteFile:
        _need(data, (5, 6), "WRITE FILE")
        if len(data) == 5:
            return cls(data[0] * 4, bytes(data[1:]), False)
        return cls(struct.unpack_from("<H", data)[0], bytes(data[2:]), True)


@dataclass(frozen=True)
class ReadRange:
    """READ EDAC / READ RESULT: short form u16 address + u8 count (0 means 256), long form u16
    address + u16 count. Reply: u16 address + bytes (READ RESULT may split into parts)."""

    address: int
    count: int
    long: bool = True

    def pack(self) -> bytes:
        if self.long:
            return struct.pack("<HH", self.address, self.count)
        if not 1 <= self.count <= 256:
            raise ValueError("short form count must be 1..256")
        return struct.pack("<HB", self.address, self.count & 0xFF)

    @classmethod
    def unpack(cls, data: bytes) -> ReadRange:
        _need(data, (3, 4), "read")
        if len(data) == 3:
            address, count = struct.unpack("<HB", data)
            return cls(address, count or 256, False)
        address, count = struct.unpack("<HH", data)
        return cls(address, count, True)


@dataclass(frozen=True)
class WriteEdac(_Layout):
    """WRITE EDAC (ours): u16 address + bytes -> reply u16 address, u16 count."""

    address: int
    data: bytes

    HEAD = "<H"
    TAIL = "data"
    NAME = "WRITE EDAC"


class GoBits(IntEnum):
    """GO code bits (COSMOS names)."""

    ON = 0x01
    LOAD_NAND = 0x02
    NOT_OFF = 0x04
    COMMAND = 0x08
    TEST = 0x10
    NO_RESET = 0x20


GO_OPERATIONAL = 0x0B  #: ON | LOAD_NAND | COMMAND, COSMOS routine attitude read


@dataclass(frozen=True)
class Go:
    code: int = GO_OPERATIONAL

    def pack(self) -> bytes:
        return bytes([self.code])

    @classmethod
    def unpack(cls, data: bytes) -> Go:
        _need(data, (1,), "GO")
        return cls(data[0])


@dataclass(frozen=True)
class DarkWindow:
    """IMAGE subcommand 0 (26 bytes): buffer, first row/column, rows, columns, 8 dark values."""

    buffer: int
    row: int
    col: int
    rows: int
    cols: int
    values: tuple[int, ...] = (0,) * 8

    SUBCOMMAND = 0

    def pack(self) -> bytes:
        return struct.pack("<BBHHHH8H", 0, self.buffer, self.row, self.col, self.rows, self.cols, *self.values)

    @classmethod
    def unpack(cls, data: bytes) -> DarkWindow:
        _need(data, (26,), "IMAGE dark window")
        sub, buf, row, col, rows, cols, *values = struct.unpack("<BBHHHH8H", data)
        return cls(buf, row, col, rows, cols, tuple(values))


@dataclass(frozen=True)
class Combination:
    """COMBINATION: u8 go code + section mask; 4 data bytes (24-bit mask, as COSMOS sends) or
    5 bytes (32-bit mask). Both accepted (ours)."""

    go_code: int
    mask: int
    mask_bytes: int = 4

    def pack(self) -> bytes:
        return bytes([self.go_code]) + self.mask.to_bytes(self.mask_bytes, "little")

    @classmethod
    def unpack(cls, data: bytes) -> Combination:
        _need(data, (4, 5), "COMBINATION")
        return cls(data[0], int.from_bytes(data[1:], "little"), len(data) - 1)


# ----------------------------------------------------------------------------- DIAGNOSTIC

DIAG_ERROR_FIELDS = ("framing", "runt", "oversize", "bad_crc", "fifo_overflow")
DIAG_COUNT_FIELDS = ("accepted", "nacked", "silent", "other_address", "replies")


@dataclass(frozen=True)
class Diagnostics:
    """DIAGNOSTIC reply (ours): 5 error counters, 5 traffic counters, 32 per-code counts, all u32.

    Command data: empty, or one byte whose bit 0 asks to clear the counters after reading.
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

    def pack(self) -> bytes:
        values = [getattr(self, name) for name in DIAG_ERROR_FIELDS + DIAG_COUNT_FIELDS]
        return struct.pack("<10I32I", *(v & 0xFFFFFFFF for v in values), *(v & 0xFFFFFFFF for v in self.per_code))

    @classmethod
    def unpack(cls, data: bytes) -> Diagnostics:
        _need(data, (cls.SIZE,), "DIAGNOSTIC reply")
        values = struct.unpack("<10I32I", data)
        counters = dict(zip(DIAG_ERROR_FIELDS + DIAG_COUNT_FIELDS, values[:10]))
        return cls(**counters, per_code=tuple(values[10:]))

    def as_dict(self) -> dict[str, Any]:
        out = {name: getattr(self, name) for name in DIAG_ERROR_FIELDS + DIAG_COUNT_FIELDS}
        out["per_code"] = {f"0x{c:02X}": n for c, n in enumerate(self.per_code) if n}
        return out


# ----------------------------------------------------------------------------- extensions (ours)


class Slot(IntEnum):
    CATALOG = 0
    FRAME = 1
    PARAMS = 2


MAX_SLOT_BYTES = 64 * 1024 * 1024  #: largest image a slot accepts (ours)
UPLOAD_CHUNK = 4096  #: XFER DATA payload size the ground client uses


@dataclass(frozen=True)
class XferBegin(_Layout):
    """XFER BEGIN: u8 slot, u32 total length, u32 CRC-32 of the whole image. Reply: XferStatus.
    Begin with the same length and CRC as a pending transfer resumes it."""

    slot: int
    length: int
    crc32: int

    HEAD = "<BII"
    NAME = "XFER BEGIN"


@dataclass(frozen=True)
class XferData(_Layout):
    """XFER DATA: u8 slot, u32 offset, bytes. Reply (if polled): u8 slot, u32 contiguous bytes."""

    slot: int
    offset: int
    data: bytes

    HEAD = "<BI"
    TAIL = "data"
    NAME = "XFER DATA"


@dataclass(frozen=True)
class XferDataAck(_Layout):
    slot: int
    contiguous: int

    HEAD = "<BI"
    NAME = "XFER DATA reply"


@dataclass(frozen=True)
class SlotRequest:
    """XFER STATUS / XFER COMMIT / SLOT INFO / XFER ABORT command data: u8 slot."""

    slot: int

    def pack(self) -> bytes:
        return bytes([self.slot])

    @classmethod
    def unpack(cls, data: bytes) -> SlotRequest:
        _need(data, (1,), "slot request")
        return cls(data[0])


class XferState(IntEnum):
    NONE = 0
    RECEIVING = 1
    COMPLETE = 2  #: every byte received, waiting for COMMIT


MAX_STATUS_RANGES = 64


@dataclass(frozen=True)
class XferStatus:
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

    def pack(self) -> bytes:
        head = struct.pack(
            "<BBIIIIH", self.slot, self.state, self.length, self.crc32, self.contiguous, self.received, self.n_missing
        )
        shown = self.missing[:MAX_STATUS_RANGES]
        return head + b"".join(struct.pack("<II", o, n) for o, n in shown)

    @classmethod
    def unpack(cls, data: bytes) -> XferStatus:
        _at_least(data, 20, "XFER STATUS reply")
        slot, state, length, crc, contiguous, received, n_missing = struct.unpack_from("<BBIIIIH", data)
        rest = data[20:]
        if len(rest) % 8:
            raise PayloadError(NackReason.BAD_LENGTH, "XFER STATUS reply: ranges not a multiple of 8 bytes")
        ranges = tuple(struct.unpack_from("<II", rest, i) for i in range(0, len(rest), 8))
        return cls(slot, state, length, crc, contiguous, received, n_missing, missing=ranges)


@dataclass(frozen=True)
class SlotImage:
    """XFER COMMIT reply and SLOT INFO reply: u8 slot, u8 active, u32 length, u32 CRC-32, then
    (SLOT INFO only) a slot-specific info blob (UTF-8 JSON for the built-in handlers)."""

    slot: int
    active: bool
    length: int
    crc32: int
    info: bytes = b""

    def pack(self) -> bytes:
        return struct.pack("<BBII", self.slot, int(self.active), self.length, self.crc32) + bytes(self.info)

    @classmethod
    def unpack(cls, data: bytes) -> SlotImage:
        _at_least(data, 10, "slot reply")
        slot, active, length, crc = struct.unpack_from("<BBII", data)
        return cls(slot, bool(active), length, crc, bytes(data[10:]))
