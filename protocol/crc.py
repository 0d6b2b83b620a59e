"""Checksums of the link: CRC-16/MCRF4XX for NSP messages, CRC-32 for transferred images.

CRC-16/MCRF4XX: polynomial 0x1021 processed reflected (right-shifting constant 0x8408),
initial value 0xFFFF, no final XOR; check value 0x6F91 for ASCII ``123456789``. On the wire the
CRC follows the data low byte first, so running the CRC over a whole message including its two
CRC bytes gives 0x0000.

CRC-32 is zlib's (CRC-32/ISO-HDLC), used for slot images and transfers.
"""

from __future__ import annotations

import zlib


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_TABLE = _make_table()


def crc16_mcrf4xx(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/MCRF4XX of ``data``; pass a previous value as ``crc`` to continue a running CRC."""
    table = _TABLE
    for byte in data:
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


def crc32(data: bytes, crc: int = 0) -> int:
    """CRC-32 (zlib / ISO-HDLC) of ``data``, continuing from ``crc``."""
    return zlib.crc32(data, crc) & 0xFFFFFFFF
