"""The command table: one entry per NSP command code, the single source of what each command
carries. The device dispatches through it (``firmware_model.device.dispatch``), the ground client
takes its payload types and retry rule from it (``ground.link.client``), the ground's link
subcommands and console take their one-line help from it (``ground.link.commands``), and the
command rows of docs/ICD.md §6, §9 and §13 are :meth:`Command.icd_row` of its entries (checked by
``tests/test_icd_tables.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

from protocol.commands import (
    AddressedBytes,
    Code,
    Combination,
    CombinationFailure,
    CrcReply,
    CrcRequest,
    DarkWindow,
    DiagnosticRequest,
    Diagnostics,
    FaultRequest,
    FaultStatus,
    Go,
    Init,
    Peek,
    Poke,
    ReadFile,
    ReadRange,
    RectangularPoke,
    SlotImage,
    SlotRequest,
    TimeReply,
    WriteAck,
    WriteEdac,
    WriteFile,
    XferBegin,
    XferData,
    XferDataAck,
    XferStatus,
)
from protocol.layout import Layout

OURS = " **[ours]**"


@dataclass(frozen=True)
class Command:
    """One command: its code, the payload types of its data field (``request``) and of its ACK
    reply (``reply``; for a multi-part reply, of each part), both None for no data / raw bytes;
    ``help``, one line for people; ``send``, ``answer`` and ``nacks``, its ICD cells (``nacks``
    None for an extension, whose NACKs the ICD states as rules); ``mark``, the ICD's marker after
    the name; ``idempotent``, a client may repeat it on a timeout; ``parts``, the reply may span
    several messages; ``decode_first``, the device decodes the data field before anything else
    (IMAGE checks mode and subcommand first, FAULT whether fault injection is on); ``failure``, the
    layout of a refusal when the ICD gives the command its own (COMBINATION's failure reply; None:
    our NACK, :class:`~protocol.commands.NackInfo`); ``also``, further layouts of the data field
    (IMAGE's Rectangular Poke beside its Dark Window)."""

    code: Code
    request: type[Layout] | None
    reply: type[Layout] | None
    help: str
    send: str
    answer: str
    nacks: str | None
    mark: str = ""
    idempotent: bool = False
    parts: bool = False
    decode_first: bool = True
    failure: type[CombinationFailure] | None = None
    also: tuple[type[Layout], ...] = ()

    @property
    def requests(self) -> tuple[type[Layout], ...]:
        """Every layout the data field may have: ``request``, then ``also`` (IMAGE's subcommands)."""
        return ((self.request,) if self.request is not None else ()) + self.also

    @property
    def name(self) -> str:
        """The name on the wire documents: ``READ FILE``."""
        return self.code.name.replace("_", " ")

    def icd_row(self) -> str:
        """This command's row in docs/ICD.md (§6, or §9 and §13 for an extension)."""
        cells = [f"0x{self.code:02X}", self.name + self.mark, self.send, self.answer]
        if self.nacks is not None:
            cells.append(self.nacks)
        return "| " + " | ".join(cells) + " |"


_READ_RANGE = "short: u16 address, u8 count (0 = 256); long: u16 address, u16 count"
_STATUS = "STATUS reply"

TABLE: tuple[Command, ...] = (
    Command(
        Code.PING,
        None,
        None,
        "PING: identification banner (bootloader or application)",
        "none",
        "ASCII banner (§5)",
        "BAD_LENGTH if data",
        idempotent=True,
    ),
    Command(
        Code.INIT,
        Init,
        None,
        "INIT: start the application",
        "u32 start address",
        "none",
        "BAD_ADDRESS (≠ 0x2000; 0x4000 enters maintenance mode, §15), WRONG_MODE",
    ),
    Command(
        Code.PEEK,
        Peek,
        AddressedBytes,
        "PEEK ADDRESS COUNT from the memory map",
        "u32 address, u16 count (1-1024)",
        "u32 address, bytes",
        "BAD_LENGTH, BAD_ADDRESS",
        OURS,
        idempotent=True,
    ),
    Command(
        Code.POKE,
        Poke,
        WriteAck,
        "POKE ADDRESS HEX into the memory map",
        "u32 address, bytes (≥ 1)",
        "u32 address, u16 count",
        "BAD_ADDRESS, READ_ONLY",
        OURS,
    ),
    Command(
        Code.DIAGNOSTIC,
        DiagnosticRequest,
        Diagnostics,
        "DIAGNOSTIC: error counters and command counts",
        "none, or u8 flags (bit 0: clear after read)",
        "§8",
        "BAD_LENGTH, BAD_PARAMETER",
        OURS,
        idempotent=True,  # unless it clears
    ),
    Command(
        Code.CRC,
        CrcRequest,
        CrcReply,
        "CRC: CRC-16 of a device memory span",
        "u8 space (0 EDAC, 1 memory map, 2 result), u32 address, u32 length (1-2^20)",
        "same 9 bytes + u16 CRC-16/MCRF4XX",
        "syntax: BAD_LENGTH / BAD_PARAMETER; operation: BAD_ADDRESS; WRONG_MODE: a FLASH subcommand "
        "outside maintenance mode (in it, 0x06 is FLASH, §15)",
        OURS,
        idempotent=True,
        decode_first=False,  # in maintenance mode 0x06 is FLASH (docs/ICD.md §15)
    ),
    Command(
        Code.READ_FILE,
        ReadFile,
        WriteFile,
        "READ FILE: 4 EDAC bytes",
        "short: u8 file index; long: u16 file index (either: EDAC address / 4)",
        "the same index field + 4 bytes",
        "BAD_ADDRESS (past the 128 words of EDAC)",
        idempotent=True,
    ),
    Command(
        Code.WRITE_FILE,
        WriteFile,
        WriteFile,
        "WRITE FILE: 4 EDAC bytes",
        "short: u8 index + 4 bytes; long: u16 index + 4 bytes",
        "echo of the command data",
        "BAD_ADDRESS, READ_ONLY",
    ),
    Command(
        Code.READ_EDAC,
        ReadRange,
        AddressedBytes,
        "READ EDAC ADDRESS COUNT",
        _READ_RANGE,
        "u16 address, bytes",
        "BAD_ADDRESS, BAD_LENGTH",
        idempotent=True,
    ),
    Command(
        Code.WRITE_EDAC,
        WriteEdac,
        WriteAck,
        "WRITE EDAC ADDRESS HEX (scratch 0x0100-0x01FF)",
        "u16 address, bytes (≥ 1)",
        "u16 address, u16 count" + OURS,
        "READ_ONLY (< 0x0100), BAD_ADDRESS",
    ),
    Command(
        Code.GO, Go, Go, "GO [CODE]: start a sequence (--wait prints the result)", "u8 go code", "u8 go code", "§7"
    ),
    Command(
        Code.READ_RESULT,
        ReadRange,
        AddressedBytes,
        "READ RESULT: decoded summary, or raw bytes with --count",
        _READ_RANGE,
        "parts: u16 address, bytes",
        "WRONG_MODE, BAD_ADDRESS (beyond 4120 bytes)",
        idempotent=True,
        parts=True,
    ),
    Command(
        Code.IMAGE,
        DarkWindow,
        DarkWindow,
        "IMAGE: a dark window, or a rectangular poke of pixel values into an image buffer",
        "u8 subcommand; 0 = Dark Window (26 bytes), 1 = Rectangular Poke (10 bytes + pixels), below",
        "echo of the 26 bytes; of the poke's 10-byte head",
        "WRONG_MODE, BAD_LENGTH, BAD_PARAMETER, OUT_OF_RANGE, TOO_LARGE",
        decode_first=False,
        also=(RectangularPoke,),
    ),
    Command(
        Code.COMBINATION,
        Combination,
        AddressedBytes,
        "COMBINATION GO_CODE MASK: sequence + selected result sections",
        "u8 go code, section mask: 3 bytes (4-byte field, as COSMOS sends) or 4 bytes (5-byte field) **[ours: both]**",
        "parts: u16 result bytes already sent, bytes (§6, ICD page 1-35918)",
        "failure reply (§7): u8 sequence state + text, for every refusal",
        parts=True,
        failure=CombinationFailure,
    ),
    Command(
        Code.TIME,
        None,
        TimeReply,
        "TIME: the device clock (u48 microseconds, latched at the command's last FEND)",
        "none",
        "u48 microseconds, least significant bit 0",
        "BAD_LENGTH if data (an old XFER BEGIN: now 0x1A)",
        idempotent=True,
    ),
    Command(
        Code.XFER_DATA,
        XferData,
        XferDataAck,
        "XFER DATA: bytes of a transfer at an offset (st16-ground upload)",
        "u8 slot, u32 offset, bytes (≤ 4 155; the client sends 4 096)",
        "u8 slot, u32 contiguous bytes",
        None,
        idempotent=True,
    ),
    Command(
        Code.XFER_STATUS,
        SlotRequest,
        XferStatus,
        "transfer status of SLOT",
        "u8 slot",
        _STATUS,
        None,
        idempotent=True,
    ),
    Command(
        Code.XFER_COMMIT,
        SlotRequest,
        SlotImage,
        "XFER COMMIT: check and activate a complete transfer (st16-ground upload)",
        "u8 slot",
        "u8 slot, u8 active (1), u32 length, u32 CRC-32",
        None,
    ),
    Command(
        Code.SLOT_INFO,
        SlotRequest,
        SlotImage,
        "active image of SLOT",
        "u8 slot",
        "u8 slot, u8 active, u32 length, u32 CRC-32, info blob (slot-specific, UTF-8 JSON)",
        None,
        idempotent=True,
    ),
    Command(
        Code.XFER_ABORT,
        SlotRequest,
        XferStatus,
        "discard the pending transfer of SLOT",
        "u8 slot",
        _STATUS + " (state 0)",
        None,
        idempotent=True,
    ),
    Command(
        Code.FAULT,
        FaultRequest,
        FaultStatus,
        "FAULT load FILE | clear | status: scripted device faults (st16-device --fault-injection)",
        "u8 subcommand (0 load, 1 clear, 2 status); load: the fault script, UTF-8 lines (§13)",
        "u8 subcommand, u32 faults armed, 9 × u32 fault counters (§13)",
        None,
        decode_first=False,
    ),
    Command(
        Code.XFER_BEGIN,
        XferBegin,
        XferStatus,
        "XFER BEGIN: open or resume a transfer into a slot (st16-ground upload)",
        "u8 slot, u32 length, u32 CRC-32 of the whole image",
        _STATUS,
        None,
        idempotent=True,
    ),
)

#: the table by code
COMMANDS: dict[int, Command] = {c.code: c for c in TABLE}


def command(code: int) -> Command:
    """The entry of ``code`` (KeyError for an unassigned code)."""
    return COMMANDS[code]
