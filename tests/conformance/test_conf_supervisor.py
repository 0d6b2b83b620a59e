"""The supervisor's commands: EDAC memory (1-35916, 1-35919) and TIME (1-35918)."""

import struct
import time

import pytest

from .icd import (
    BAD_LENGTH,
    EDAC_SIZE,
    READ_EDAC,
    READ_FILE,
    RESULT_LENGTH_ADDRESS,
    SCRATCH,
    TIME,
    WRITE_FILE,
    XFER_ABORT,
    XFER_BEGIN,
    XFER_STATUS,
    init_application,
    read_edac,
    time_us,
    write_edac,
)
from .nsp_min import DEVICE_ADDRESS, FEND, HOST_ADDRESS, nsp_payload, slip_escape

pytestmark = pytest.mark.timeout(120)


# -- EDAC memory, READ/WRITE FILE, READ/WRITE EDAC ------------------------------------------------


def test_conf_edac_memory_is_512_bytes(app):
    """1-35919, "EDAC Memory": "The supervisor processor supports 512 bytes of EDAC protected
    memory." All 512 are readable in one long READ EDAC; a read beyond them is not executed
    (ACK 0)."""
    assert len(read_edac(app, 0, EDAC_SIZE, long=True)) == EDAC_SIZE
    beyond = app.one(READ_EDAC, struct.pack("<HB", EDAC_SIZE - 2, 4))
    assert not beyond.ack


def test_conf_read_edac_short_and_long_forms_agree(app):
    """1-35916, READ EDAC (0x09): "The Read EDAC command returns bytes from EDAC memory. [...] Long
    and short command formats are available." [layouts: docs/ICD.md, u16 address + u8 count or
    u16 count; the public copy shows only the headings]."""
    write_edac(app, SCRATCH + 16, bytes(range(40, 72)))
    assert read_edac(app, SCRATCH + 16, 32) == read_edac(app, SCRATCH + 16, 32, long=True) == bytes(range(40, 72))


def test_conf_write_edac_writes_bytes(app):
    """1-35916, WRITE EDAC (0x0A): "The Write EDAC command writes bytes into EDAC memory."."""
    assert write_edac(app, SCRATCH + 48, b"conformance").ack
    assert read_edac(app, SCRATCH + 48, 11) == b"conformance"


def test_conf_read_file_short_form_returns_four_bytes_of_edac(app):
    """1-35916, READ FILE (0x07): "returns four consecutive bytes of EDAC protected memory [...]
    two command formats available: short and long. These return corresponding short and long
    replies. These can be distinguished by their lengths." Short form: a 1-byte index, the EDAC
    address divided by 4 (st16_icd_vs_emulator.md row 2); reply: the index + 4 bytes."""
    write_edac(app, SCRATCH + 8, b"\x11\x22\x33\x44")
    msg = app.one(READ_FILE, bytes(((SCRATCH + 8) // 4,)))
    assert msg.ack and msg.data == bytes(((SCRATCH + 8) // 4,)) + b"\x11\x22\x33\x44"


def test_conf_read_file_long_form_index_is_edac_address_over_4(app):
    """1-35916, READ FILE long form: a 2-byte index, "EDAC address divided by 4" (0-65535;
    st16_icd_vs_emulator.md row 2, the table cells of the http copy); reply: the 2-byte index + 4
    bytes. Index 0x13 is EDAC 0x4C, the result length; index 0x40 is EDAC 0x100."""
    msg = app.one(READ_FILE, struct.pack("<H", RESULT_LENGTH_ADDRESS // 4))
    assert msg.ack, msg.data
    assert msg.data == struct.pack("<H", 0x13) + read_edac(app, RESULT_LENGTH_ADDRESS, 4)
    write_edac(app, SCRATCH, b"LONG")
    msg = app.one(READ_FILE, struct.pack("<H", SCRATCH // 4))
    assert msg.ack and msg.data == struct.pack("<H", SCRATCH // 4) + b"LONG"


def test_conf_write_file_short_form_writes_and_echoes(app):
    """1-35916, WRITE FILE (0x08): "writes four consecutive bytes to EDAC memory [...] short and
    long [...] corresponding short and long replies": short = 1-byte index (address / 4) + 4
    bytes; the reply echoes them."""
    field = bytes(((SCRATCH + 12) // 4,)) + b"shrt"
    msg = app.one(WRITE_FILE, field)
    assert msg.ack and msg.data == field
    assert read_edac(app, SCRATCH + 12, 4) == b"shrt"


def test_conf_write_file_long_form_writes_and_echoes(app):
    """1-35916, WRITE FILE long form: 2-byte index (address / 4) + 4 bytes; the reply echoes."""
    field = struct.pack("<H", (SCRATCH + 20) // 4) + b"lng!"
    msg = app.one(WRITE_FILE, field)
    assert msg.ack and msg.data == field
    assert read_edac(app, SCRATCH + 20, 4) == b"lng!"


# -- TIME -----------------------------------------------------------------------------------------


def test_conf_time_is_48_bits_of_microseconds_lsb_zero(app):
    """1-35918, TIME (0x13): "The data is returned as a 48-bit unsigned integer count of
    microseconds. The least significant bit of the count will always be zero". Six bytes
    (little-endian: the lead's spec; the page's format table is not visible), every one of 40
    polls even, and never decreasing."""
    values = [time_us(app) for _ in range(40)]
    assert all(v % 2 == 0 for v in values), values
    assert all(b >= a for a, b in zip(values, values[1:], strict=False)), values
    assert all(v < 1 << 48 for v in values)


def test_conf_time_works_in_bootloader_mode(boot):
    """1-35918: TIME "returns the supervisor's realtime clock": the supervisor answers in both
    modes (lead's spec). In bootloader mode, then in application mode, the count goes on."""
    first = time_us(boot)
    assert init_application(boot).ack
    assert time_us(boot) >= first


def test_conf_time_polls_track_the_host_clock(app):
    """1-35918: "By sending several TIME commands, separated by minutes or hours, an accurate
    comparison can be made between the star tracker clock and the spacecraft computer clock."
    Two polls 0.5 s apart differ by the interval as bracketed by the host's clock (send of one,
    reply of the other), within 0.1 % (the clock's drift bound) and 2 ms (jitter). A comparison
    of two clocks, not a speed: a loaded machine widens the bracket, it cannot fail it."""
    s0 = time.monotonic()
    t0 = time_us(app)
    r0 = time.monotonic()
    time.sleep(0.5)
    s1 = time.monotonic()
    t1 = time_us(app)
    r1 = time.monotonic()
    device_s = (t1 - t0) / 1e6
    assert (s1 - r0) * 0.999 - 0.002 <= device_s <= (r1 - s0) * 1.001 + 0.002, (device_s, s1 - r0, r1 - s0)


def test_conf_time_latched_at_the_final_fend(app):
    """1-35918: "The TIME command returns the supervisor's realtime clock, latched at the moment
    the final FEND character of the command is received." A TIME whose closing FEND is held back
    0.3 s reads a clock at least that much later than a TIME just before its first byte."""
    body = slip_escape(nsp_payload(DEVICE_ADDRESS, HOST_ADDRESS, 0x80 | TIME))
    before = time_us(app)
    after_before = time.monotonic()
    app.write(bytes((FEND,)) + body)
    time.sleep(0.3)
    fend_at = time.monotonic()
    app.write(bytes((FEND,)))
    msg = app.next_message()
    assert msg.code == TIME and msg.ack and len(msg.data) == 6
    latched = int.from_bytes(msg.data, "little")
    assert (latched - before) / 1e6 >= (fend_at - after_before) * 0.999 - 0.002


def test_conf_time_with_a_data_field_is_nacked_bad_length(app):
    """1-35918 shows a TIME command format with no data (the lead's spec: none). A data field is
    refused: ACK 0, reason BAD_LENGTH (0x0002, the emulator's NACK layout: u16 reason + text)."""
    msg = app.one(TIME, b"\x00")
    assert not msg.ack and msg.final and msg.nack_reason == BAD_LENGTH


def test_conf_old_xfer_begin_on_0x13_starts_nothing(app):
    """1-35918 assigns 0x13 to TIME, so the emulator's XFER BEGIN moved to 0x1A (issue 39). An old
    client's 9-byte XFER BEGIN on 0x13 is NACKed BAD_LENGTH and opens no transfer (XFER STATUS
    0x15 of slot 2 says state 0); the same field on 0x1A opens one (then aborted, 0x18)."""
    begin = struct.pack("<BII", 2, 16, 0x12345678)
    msg = app.one(TIME, begin)
    assert not msg.ack and msg.nack_reason == BAD_LENGTH
    status = app.one(XFER_STATUS, bytes((2,)))
    assert status.ack and status.data[:2] == bytes((2, 0)), status.data
    opened = app.one(XFER_BEGIN, begin)
    assert opened.ack and opened.data[:2] == bytes((2, 1)), opened.data
    assert app.one(XFER_ABORT, bytes((2,))).ack
