"""Checksums of the link: CRC-16/MCRF4XX for NSP messages, CRC-32 for transferred images.

CRC-16/MCRF4XX: polynomial 0x1021 processed reflected (right-shifting constant 0x8408),
initial value 0xFFFF, no final XOR; check value 0x6F91 for ASCII ``123456789``. On the wire the
CRC follows the data low byte first, so running the CRC over a whole message including its two
CRC bytes gives 0x0000.

CRC-32 is zlib's (CRC-32/ISO-HDLC), used for slot images and transfers. Any message followed by
its own CRC-32, little-endian, has the CRC-32 :data:`CRC32_RESIDUE`, whatever the message: such a
CRC-32 names no content.
"""

from __future__ import annotations

import binascii
import zlib

CRC32_RESIDUE = 0x2144DF1C  #: CRC-32 of any message followed by its own CRC-32, little-endian

#: Bit-reversal of every byte value.
_REVERSE8 = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))


def _reverse16(x: int) -> int:
    return int(f"{x:016b}"[::-1], 2)


def crc16_mcrf4xx(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/MCRF4XX of ``data``; pass a previous value as ``crc`` to continue a running CRC.

    A reflected CRC equals the bit-reversed non-reflected CRC of the bit-reversed input, so the
    work is done by ``binascii.crc_hqx`` (CRC-CCITT, polynomial 0x1021, MSB first, in C) on the
    byte-reversed data, with the register reversed on the way in and out.
    """
    return _reverse16(binascii.crc_hqx(bytes(data).translate(_REVERSE8), _reverse16(crc)))


def crc32(data: bytes, crc: int = 0) -> int:
    """CRC-32 (zlib / ISO-HDLC) of ``data``, continuing from ``crc``."""
    return zlib.crc32(data, crc) & 0xFFFFFFFF
