"""CRC-16/MCRF4XX and CRC-32 against catalogue check values and the research worked examples."""

import zlib

from hypothesis import given
from hypothesis import strategies as st

from protocol.crc import crc16_mcrf4xx, crc32


def test_check_value():
    assert crc16_mcrf4xx(b"123456789") == 0x6F91


def _bitwise(data: bytes) -> int:
    """The research notes' restatement of the COSMOS routine, bit by bit."""
    crc = 0xFFFF
    for byte in data:
        for _ in range(8):
            crc = (crc >> 1) ^ (0x8408 if (byte ^ crc) & 1 else 0)
            byte >>= 1
    return crc


@given(st.binary(max_size=300))
def test_matches_bitwise_reference(data):
    assert crc16_mcrf4xx(data) == _bitwise(data)


@given(st.binary(max_size=200), st.binary(max_size=200))
def test_running_crc_and_residue(a, b):
    assert crc16_mcrf4xx(b, crc16_mcrf4xx(a)) == crc16_mcrf4xx(a + b)
    c = crc16_mcrf4xx(a)
    assert crc16_mcrf4xx(a + bytes((c & 0xFF, c >> 8))) == 0


def test_worked_examples_crc_bytes():
    # research notes section 2.5: (unescaped message without CRC, CRC bytes low first)
    cases = [
        ("0E1180", "6921"),
        ("0E118100200000", "1F31"),
        ("0E11894C0004", "2ABF"),
        ("0E118D00004800", "B2CD"),
        ("0E118DC00010", "2C32"),
        ("0E118B0B", "9DA4"),
        ("110EA0", "60D9"),
    ]
    for body, want in cases:
        crc = crc16_mcrf4xx(bytes.fromhex(body))
        assert bytes((crc & 0xFF, crc >> 8)).hex().upper() == want


def test_crc32_is_zlib():
    assert crc32(b"123456789") == 0xCBF43926 == zlib.crc32(b"123456789")
