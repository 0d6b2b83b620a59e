"""Link layer and message control field, against a device process on a pty: 1-35908 (addressing
on a shared bus), 1-35910 (message control field), 1-35919 (error counters).

Counters are read from EDAC 0x0024 (the emulator's place, docs/ICD.md section 8; the pages
describe the counters but their address is in a table not visible in the public copy)."""

import struct

import pytest

from .icd import GO, IMAGE, READ_EDAC, SCRATCH, WRITE_FILE, counters, dark_window, read_edac
from .nsp_min import DEVICE_ADDRESS, FEND, FESC, HOST_ADDRESS, nsp_frame, nsp_payload, slip_frame

pytestmark = pytest.mark.timeout(120)

READ4 = struct.pack("<HB", 0, 4)  # READ EDAC, 4 bytes at 0: a harmless polled command


def test_conf_runt_counted_only_when_byte0_is_the_trackers_address(app):
    """1-35919, "Runt Packet Count": "A runt packet is a NSP message that is less than 5 bytes
    long. [...] Runts are counted only if the first byte is equal to the star tracker's
    address"."""
    before = counters(app)
    assert app.before_sentinel(slip_frame(bytes((DEVICE_ADDRESS, HOST_ADDRESS, 0x80, 0x00)))) == []
    mid = counters(app)
    assert mid["runt"] == before["runt"] + 1
    assert app.before_sentinel(slip_frame(bytes((0x0F, HOST_ADDRESS, 0x80)))) == []
    assert counters(app)["runt"] == mid["runt"]


def test_conf_empty_frames_are_not_runts(app):
    """1-35919: "A zero-length NSP message is not considered a runt. For example, on an ASYNC or
    RS485 link two FEND characters back-to-back is a valid bus condition and not a runt."."""
    before = counters(app)
    assert app.before_sentinel(bytes((FEND,)) * 6) == []
    after = counters(app)
    assert (after["runt"], after["framing"]) == (before["runt"], before["framing"])


def test_conf_bad_escape_is_a_framing_error_and_gets_no_reply(app):
    """1-35919, "Framing Error Count": "any time a FESC character is seen that is not immediately
    followed by TFESC or TFEND"."""
    before = counters(app)
    good = nsp_payload(DEVICE_ADDRESS, HOST_ADDRESS, 0x80 | READ_EDAC, READ4)
    raw = bytes((FEND,)) + good[:3] + bytes((FESC, 0x41)) + good[3:] + bytes((FEND,))
    assert app.before_sentinel(raw) == []
    assert counters(app)["framing"] == before["framing"] + 1


def test_conf_bad_crc_counted_only_when_addressed_to_the_tracker(app):
    """1-35919, "Bad CRC Count": "incremented every time a properly formatted (in length and
    framing) NSP message is received where the CRC field does not match with the computed CRC,
    and where the first byte is equal to the NSP address of the star tracker"; no reply (the
    message cannot be trusted)."""
    before = counters(app)
    bad = nsp_payload(DEVICE_ADDRESS, HOST_ADDRESS, 0x80 | READ_EDAC, READ4, crc=0x1234)
    assert app.before_sentinel(slip_frame(bad)) == []
    mid = counters(app)
    assert mid["bad_crc"] == before["bad_crc"] + 1
    other = nsp_payload(0x0F, HOST_ADDRESS, 0x80 | READ_EDAC, READ4, crc=0x1234)
    assert app.before_sentinel(slip_frame(other)) == []
    assert counters(app)["bad_crc"] == mid["bad_crc"]


def test_conf_oversize_message_is_rejected(app):
    """1-35919, "Oversize Packet Count": "An oversize packet is one that has too many bytes in the
    data field. [...] they must be rejected." (the limit, section 5.2, is not in the public copy:
    64 KiB of data is beyond any NSP buffer)."""
    before = counters(app)
    huge = nsp_frame(DEVICE_ADDRESS, HOST_ADDRESS, 0x80 | READ_EDAC, bytes(65536))
    assert app.before_sentinel(huge) == []
    assert counters(app)["oversize"] == before["oversize"] + 1


def test_conf_fifo_overflow_never_counted_by_the_bootloader(boot):
    """1-35919, "FIFO Overflow Count": "The bootloader does not use FIFO buffers, and will never
    increment this counter."  (After a burst of traffic in bootloader mode it is still 0.)"""
    burst = b"".join(nsp_frame(DEVICE_ADDRESS, HOST_ADDRESS, READ_EDAC, READ4) for _ in range(200))
    assert boot.before_sentinel(burst) == []
    assert counters(boot)["fifo"] == 0


def test_conf_a_tracker_acts_only_on_its_own_address(app):
    """1-35908, 2.7 Command: "Star trackers will only interpret commands that are addressed to
    them. Thus, two star trackers with different NSP addresses can share a common Command link."
    A WRITE FILE addressed to 0x0F neither answers nor writes."""
    index = SCRATCH // 4
    assert app.one(WRITE_FILE, bytes((index,)) + b"\x00" * 4).ack
    other = nsp_frame(0x0F, HOST_ADDRESS, 0x80 | WRITE_FILE, bytes((index,)) + b"ABCD")
    assert app.before_sentinel(other) == []
    assert read_edac(app, SCRATCH, 4) == b"\x00" * 4


def test_conf_no_unsolicited_output(app):
    """1-35908, 2.8 Telemetry: "When there is no data to transmit the star tracker will
    three-state its outputs to allow another unit to drive the bus." On a pty: between replies
    the device sends nothing, even when commands are executed silently (Poll = 0)."""
    silent = b"".join(nsp_frame(DEVICE_ADDRESS, HOST_ADDRESS, READ_EDAC, READ4) for _ in range(5))
    assert app.before_sentinel(silent) == []


def test_conf_reply_echoes_code_and_addresses(app):
    """1-35910, Table 23: the reply's bits 4-0 carry the command code; the reply goes from the
    tracker to the sender (destination = the command's source, source = the tracker, address 0x0E
    by default [ours: docs/ICD.md section 3])."""
    app.send(READ_EDAC, READ4, src=0x22)
    (msg,) = app.replies()
    assert (msg.code, msg.dst, msg.src, msg.crc_ok) == (READ_EDAC, 0x22, DEVICE_ADDRESS, True)


@pytest.mark.parametrize("b", [False, True])
def test_conf_b_bit_copied_into_the_reply(app, b):
    """1-35910: "The "B" bit is copied unchanged from a command message into its reply message."""
    assert app.one(READ_EDAC, READ4, b=b).b is b


def test_conf_ack_bit_ignored_on_commands(app):
    """1-35910: "The "ACK" bit is ignored on commands coming into the star tracker." The same
    READ EDAC with and without it gets the same ACKed reply."""
    plain = app.one(READ_EDAC, READ4)
    with_ack = app.one(READ_EDAC, READ4, ack_bit=True)
    assert plain.ack and with_ack.ack and plain.data == with_ack.data


def test_conf_ack_set_on_success_cleared_when_not_executed(boot):
    """1-35910: the ACK bit of a reply "is set to indicate successful execution of the command, or
    cleared to indicate that the command cannot be executed." IMAGE is "allowed only in
    application mode" (1-35917): refused, ACK 0, in bootloader mode; READ EDAC is executed."""
    assert boot.one(READ_EDAC, READ4).ack
    refused = boot.one(IMAGE, dark_window(0, 0, 0, 1, 1))
    assert not refused.ack and refused.final and refused.code == IMAGE


def test_conf_poll_0_executes_without_reply(app):
    """1-35910: Poll "cleared to '0' then the command will be executed, but no response telemetry
    message will be sent." A WRITE FILE with Poll = 0 writes, and answers nothing."""
    index = SCRATCH // 4 + 1
    raw = nsp_frame(DEVICE_ADDRESS, HOST_ADDRESS, WRITE_FILE, bytes((index,)) + b"WXYZ")
    assert app.before_sentinel(raw) == []
    assert read_edac(app, SCRATCH + 4, 4) == b"WXYZ"


def test_conf_single_message_reply_has_final_set(app):
    """1-35910: "If a reply consists of a single telemetry message, then the bit is set to '1'."."""
    msg = app.one(GO, bytes((0x00,)))
    assert msg.final and msg.code == GO
