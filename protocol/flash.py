"""The FLASH command (code 0x06 in maintenance mode; docs/ICD.md section 15): its subcommands, their
data fields and replies, as far as the ICD pages 1-35913 to 1-35915 show them; the rest is ours.

Code 0x06 is the supervisor's CRC and the functional processor's FLASH (page 1-35912): the
emulator reads it as FLASH while the tracker is in maintenance mode, as CRC otherwise. Every
integer is little-endian. A successful subcommand is ACKed with its reply; a failed one is NACKed
with a failure reply: the command's own fields echoed (byte 0 the subcommand), then **[ours]** a
u8 failure kind (:class:`Failure`) and a u32 page (the page at fault; 0 when none).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

PAGE_BYTES = 2048  #: data bytes of a NAND page (ours; the pages give 64 pages a block)
PAGES_PER_BLOCK = 64  #: page 1-35923: "each flash block contains 64 pages"
BLOCKS = 0x10000  #: ours: the application image lives at block 0x8000 (page 1-35916)
PAGES = BLOCKS * PAGES_PER_BLOCK
BOOT_PAGES = (0, 64, 128, 192)  #: the boot block and its backups (page 1-35914 prints 196: a slip for 192)
BOOT_BYTES = 32 * 1024  #: Make Boot Block copies 32 kB from SRAM (page 1-35914)
MAX_DISTURB_PAGES = 16 * 1024 * 1024 // PAGE_BYTES  #: "approximately 16 MB" at one time (page 1-35915)
MAX_READ_BUFFER = 2048  #: bytes one Read Page Buffer returns (a page)


class Sub(IntEnum):
    """FLASH subcommands (byte 0). 0-3, 6-8 and 13 are numbered on the pages; 4, 9, 10 and 14 ours."""

    READ_BUFFER = 0
    WRITE_BUFFER = 1
    ERASE_BLOCK = 2
    WRITE_PAGE = 3
    READ_PAGE = 4  #: ours: a NAND page into the page buffer (the pages' number 4 is not visible)
    FIND_BAD_BLOCKS = 6
    CRC_BUFFER = 7
    CRC_NAND = 8
    CRC_RAM = 9  #: number ours (the page names it after CRC NAND)
    MAKE_BOOT_BLOCK = 10  #: number ours
    READ_DISTURB_TEST = 13
    REWRITE_NAND = 14  #: number and layout ours


class Failure(IntEnum):
    """The failure replies the pages name (the kind byte is ours)."""

    SYNTAX = 1  #: parameters out of range (e.g. a page beyond the NAND, final before start)
    ECC = 2  #: an uncorrectable ECC error (the page is given)
    OPERATION = 3  #: the NAND refused an erase or program (no spare block left to relocate to)


#: Each subcommand's fields after byte 0 (struct format), for the command and for the failure echo.
FIELDS: dict[Sub, str] = {
    Sub.READ_BUFFER: "<HB",  # short form; the long form is "<HH"
    Sub.WRITE_BUFFER: "<H",  # then the bytes
    Sub.ERASE_BLOCK: "<I",
    Sub.WRITE_PAGE: "<I",
    Sub.READ_PAGE: "<I",
    Sub.FIND_BAD_BLOCKS: "<II",
    Sub.CRC_BUFFER: "<",
    Sub.CRC_NAND: "<II",
    Sub.CRC_RAM: "<II",  # address, length
    Sub.MAKE_BOOT_BLOCK: "<I",
    Sub.READ_DISTURB_TEST: "<III",  # start page, final page, maximum read cycles
    Sub.REWRITE_NAND: "<II",  # first page, last page (whole blocks)
}


@dataclass
class FlashFailure(Exception):
    """A FLASH subcommand that failed: NACKed with :meth:`pack`."""

    sub: int
    echo: bytes  #: the command's fields after byte 0, as sent (cut to their declared length)
    kind: Failure
    page: int
    text: str

    def pack(self) -> bytes:
        return bytes([self.sub]) + self.echo + struct.pack("<BI", int(self.kind), self.page & 0xFFFFFFFF)


def unpack_failure(data: bytes) -> tuple[int, bytes, Failure, int]:
    """(subcommand, echoed fields, kind, page) of a failure reply."""
    if len(data) < 6:
        raise ValueError(f"FLASH failure reply of {len(data)} bytes: at least 6")
    kind, page = struct.unpack_from("<BI", data, len(data) - 5)
    return data[0], data[1:-5], Failure(kind), page


def command(sub: Sub, *fields: int, data: bytes = b"", long: bool = False) -> bytes:
    """The data field of a FLASH subcommand: byte 0, the fields, then ``data`` (Write Page Buffer)."""
    fmt = "<HH" if sub == Sub.READ_BUFFER and long else FIELDS[sub]
    return bytes([sub]) + struct.pack(fmt, *fields) + data
