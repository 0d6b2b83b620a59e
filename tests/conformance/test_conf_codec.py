"""The suite's own codec against the ICD's definitions (no device): if these fail, every other
conformance test speaks the wrong protocol."""

import pytest

from .nsp_min import FEND, FESC, TFEND, TFESC, SlipDecoder, crc16, nsp_frame, parse, slip_frame

pytestmark = pytest.mark.timeout(30)


def test_conf_crc_is_the_ccitt_polynomial_reflected_with_check_value_0x6f91():
    """1-35910, "Message CRC": "The 16-bit CCITT polynomial is used: x^16 + x^12 + x^5 + 1. The
    initial shift register value i[s ...]" (cut off in the public copy). Completed as
    CRC-16/MCRF4XX (reflected 0x8408, init 0xFFFF, no final XOR), whose check value over ASCII
    "123456789" is 0x6F91; the emulator's worked example PING 0E 11 80 carries 69 21."""
    assert crc16(b"123456789") == 0x6F91
    assert nsp_frame(0x0E, 0x11, 0x80) == bytes.fromhex("C00E118069 21C0".replace(" ", ""))


def test_conf_slip_escapes_fend_and_fesc():
    """1-35919, "Framing Error Count": a FESC must be "immediately followed by TFESC or TFEND":
    FEND and FESC inside a message travel as FESC TFEND and FESC TFESC."""
    payload = bytes((1, FEND, 2, FESC, 3))
    framed = slip_frame(payload)
    assert framed == bytes((FEND, 1, FESC, TFEND, 2, FESC, TFESC, 3, FEND))
    assert SlipDecoder().feed(framed) == [(payload, True)]


def test_conf_slip_decoder_flags_a_bad_escape_and_skips_empty_frames():
    """1-35919: a FESC not followed by TFESC or TFEND is a framing error; two FENDs back to back
    are "a valid bus condition", not a message."""
    dec = SlipDecoder()
    assert dec.feed(bytes((FEND, FEND, FEND))) == []
    assert dec.feed(bytes((FEND, 1, FESC, 0x00, 2, FEND))) == [(bytes((1, 2)), False)]


def test_conf_message_layout_and_mcf_bits():
    """1-35910, Table 23: bit 7 Poll/Final, bit 6 B, bit 5 ACK, bits 4-0 the command code."""
    msg = parse(nsp_frame(0x11, 0x0E, 0x80 | 0x40 | 0x20 | 0x13, b"\x01\x02")[1:-1])
    assert (msg.dst, msg.src, msg.code, msg.final, msg.b, msg.ack, msg.data) == (
        0x11,
        0x0E,
        0x13,
        True,
        True,
        True,
        b"\x01\x02",
    )
    assert msg.crc_ok
