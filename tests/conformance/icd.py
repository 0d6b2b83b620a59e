"""The commands the conformance suite sends, as the public ICD pages name them (codes from the
pages' headings: READ FILE (0x07), WRITE FILE (0x08), READ EDAC (0x09), WRITE EDAC (0x0A),
GO (0x0B), READ RESULT (0x0D), IMAGE (0x10), COMBINATION (0x12), TIME (0x13)). Where a page
shows only a heading and no byte layout, the layout is the emulator's docs/ICD.md one, and the
docstring says so. Nothing here comes from the project's packages."""

from __future__ import annotations

import struct
import time

from .nsp_min import HANG_S, Link, Msg

PING = 0x00  # docs/ICD.md (not on the public pages read)
INIT = 0x01  # docs/ICD.md: u32 start address, 0x00002000 enters the application
READ_FILE = 0x07
WRITE_FILE = 0x08
READ_EDAC = 0x09
WRITE_EDAC = 0x0A
GO = 0x0B
READ_RESULT = 0x0D
IMAGE = 0x10
COMBINATION = 0x12
TIME = 0x13
# the emulator's own extensions (issue 39: moved off the codes the ICD assigns)
XFER_DATA, XFER_STATUS, XFER_COMMIT, SLOT_INFO, XFER_ABORT, FAULT, XFER_BEGIN = range(0x14, 0x1B)

# GO bits (COSMOS names; bit 1 and bits 2, 5 are on 1-35916 / 1-35924)
GO_ON, GO_LOAD_NAND, GO_NOT_OFF, GO_COMMAND, GO_TEST, GO_NO_RESET, GO_INJECTED = (
    0x01,
    0x02,
    0x04,
    0x08,
    0x10,
    0x20,
    0x40,
)

# the emulator's NACK reasons (ours, docs/ICD.md section 4)
BAD_LENGTH = 0x0002
OUT_OF_RANGE = 0x000A

EDAC_SIZE = 512  # 1-35919
COUNTERS_ADDRESS = 0x0024  # ours: framing, runt, oversize, bad CRC, FIFO overflow, accepted, ...
COUNTER_NAMES = ("framing", "runt", "oversize", "bad_crc", "fifo", "accepted", "nacked", "silent", "other", "replies")
RESULT_LENGTH_ADDRESS = 0x004C  # EDAC: result length (COSMOS practice, RN section 6)
SCRATCH = 0x0100  # ours: user scratch, 0x0100-0x01FF

MATCHING = 0x7E8  # the result's matching telemetry, two of 176 bytes (COSMOS overlay)
MATCHING_SIZE = 176
HARDWARE = 0x048  # the result's hardware telemetry

SENSOR_ROWS_MAX = 0xFFFF


def read_edac(link: Link, address: int, count: int, *, long: bool = False) -> bytes:
    """READ EDAC short (u16 address, u8 count, 0 = 256) or long (u16 address, u16 count)
    [layout: docs/ICD.md; 1-35916 gives the headings]; the data of an ACK."""
    field = struct.pack("<HH", address, count) if long else struct.pack("<HB", address, count & 0xFF)
    msgs = link.request(READ_EDAC, field)
    assert all(m.ack for m in msgs), [m.data for m in msgs]
    data = b"".join(m.data[2:] for m in msgs)
    assert int.from_bytes(msgs[0].data[:2], "little") == address
    return data


def write_edac(link: Link, address: int, data: bytes) -> Msg:
    return link.one(WRITE_EDAC, struct.pack("<H", address) + data)


def counters(link: Link) -> dict[str, int]:
    """The link counters (EDAC 0x0024, ours; the counters themselves are on 1-35919)."""
    raw = read_edac(link, COUNTERS_ADDRESS, 40)
    return dict(zip(COUNTER_NAMES, struct.unpack("<10I", raw), strict=True))


def init_application(link: Link) -> Msg:
    """INIT 0x00002000 (docs/ICD.md, the COSMOS start address): the application mode."""
    return link.one(INIT, struct.pack("<I", 0x2000))


def result_length(link: Link) -> int:
    return struct.unpack("<I", read_edac(link, RESULT_LENGTH_ADDRESS, 4))[0]


def read_result(link: Link, address: int, count: int, *, long: bool = True) -> list[Msg]:
    """READ RESULT (1-35917): short = u16 address + u8 count (0 = 256), long = u16 address + u16
    count; every message of the reply."""
    field = struct.pack("<HH", address, count) if long else struct.pack("<HB", address, count & 0xFF)
    return link.request(READ_RESULT, field)


def result_bytes(link: Link, address: int, count: int) -> bytes:
    msgs = read_result(link, address, count)
    assert all(m.ack for m in msgs)
    return b"".join(m.data[2:] for m in msgs)


def time_us(link: Link) -> int:
    """TIME (1-35918): the 48-bit microsecond count, little-endian (the lead's spec)."""
    msg = link.one(TIME)
    assert msg.ack and len(msg.data) == 6, (msg.mcf, msg.data)
    return int.from_bytes(msg.data, "little")


def wait_result_ready(link: Link) -> None:
    """Polls the result length until it is non-zero (a hang guard of HANG_S, not a timing)."""
    deadline = time.monotonic() + HANG_S
    while result_length(link) == 0:
        assert time.monotonic() < deadline, f"no result within the {HANG_S} s hang guard"
        time.sleep(0.02)


def dark_window(
    buffer: int, row: int, col: int, rows: int, cols: int, darks: tuple[int, ...] = tuple(range(8))
) -> bytes:
    """IMAGE subcommand 0, Dark Window (1-35917: 26 bytes)."""
    return struct.pack("<BBHHHH8H", 0, buffer, row, col, rows, cols, *darks)


def rectangular_poke(buffer: int, row: int, col: int, rows: int, cols: int, pixels: list[int] | None = None) -> bytes:
    """IMAGE subcommand 1, Rectangular Poke (layout ours, issue 39): u8 1, u8 buffer, u16 first
    row, u16 first column, u16 rows, u16 columns, rows x columns u16 pixels row-major."""
    if pixels is None:
        pixels = [(7 * i) & 0xFFFF for i in range(rows * cols)]
    return struct.pack("<BBHHHH", 1, buffer, row, col, rows, cols) + struct.pack(f"<{len(pixels)}H", *pixels)
