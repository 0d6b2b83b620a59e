"""Why a device refuses a command: the NACK reason codes and the error a payload that cannot be
accepted raises (the device NACKs it with its reason, the client reports a malformed reply)."""

from __future__ import annotations

from enum import IntEnum


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
    CONFLICT = 0x0010  #: XFER DATA over received bytes with other bytes (received bytes are write-once)
    #: a read of a memory word holding an (injected) double-bit upset: detected, not correctable
    EDAC_UNCORRECTABLE = 0x0011
    INTERNAL = 0x00FF  #: unexpected device-side exception (a bug; the device keeps serving)
    #: 0x0100-0xFFFF: reasons raised by slot validators (:class:`SlotRejected` codes)
    VALIDATOR_BASE = 0x0100


class PayloadError(ValueError):
    """A data field that cannot be accepted; becomes a NACK with ``reason``."""

    def __init__(self, reason: NackReason | int, message: str):
        super().__init__(message)
        self.reason = int(reason)
        self.message = message
