"""The tracker's 512-byte EDAC memory as READ EDAC reads it (docs/ICD.md section 8), declared once:
the device builds a record of :data:`EDAC_DTYPE`, the client reads fields at their offsets."""

from __future__ import annotations

import numpy as np

SIZE = 512  #: bytes
SCRATCH = (0x0100, 0x0200)  #: writable user scratch [start, end)
#: Status word bits at 0x0000.
STATUS_APP_MODE, STATUS_BUSY, STATUS_RESULT_READY = 0x1, 0x2, 0x4
#: The ten link counters at 0x0024, in order.
COUNTERS = (
    "framing",
    "runt",
    "oversize",
    "bad_crc",
    "fifo_overflow",
    "accepted",
    "nacked",
    "silent",
    "other_address",
    "replies",
)
#: The nine fault counters at 0x009C, in order (docs/ICD.md section 13, ours): what the emulator's
#: scripted faults (``firmware_model.device.faults``) did; a scripted reset keeps them.
FAULT_COUNTERS = (
    "delayed_replies",
    "dropped_replies",
    "corrupted_crcs",
    "stuck_results",
    "resets",
    "edac_corrected",
    "edac_uncorrectable",
    "frozen_frames",
    "catalog_reloads",
)
FAULT_COUNTERS_AT = 0x009C  #: EDAC address of the first fault counter (u32 LE each)
#: EDAC address of the functional processor's boot message (ASCII, NUL padded, 64 bytes): the ASIC
#: ID message a GO with LOAD_NAND leaves (ICD page 1-35916; the place and text are ours)
BOOT_MESSAGE_AT = 0x00C0

EDAC_DTYPE = np.dtype(
    {
        "names": [
            "status",
            "analog",
            *COUNTERS,
            "result_length",
            "total_length",
            "sequence",
            "address",
            "app_mode",
            "busy",
            "spare",
            "banner",
            *FAULT_COUNTERS,
            "boot_message",
            "scratch",
        ],
        "formats": [
            "<u4",
            "<8f4",
            *["<u4"] * len(COUNTERS),
            "<u4",
            "<u4",
            "<u4",
            "u1",
            "u1",
            "u1",
            "u1",
            "S64",
            *["<u4"] * len(FAULT_COUNTERS),
            "S64",
            f"{SCRATCH[1] - SCRATCH[0]}u1",
        ],
        "offsets": [
            0x00,
            0x04,
            *range(0x24, 0x4C, 4),
            0x4C,
            0x50,
            0x54,
            0x58,
            0x59,
            0x5A,
            0x5B,
            0x5C,
            *range(FAULT_COUNTERS_AT, FAULT_COUNTERS_AT + 4 * len(FAULT_COUNTERS), 4),
            BOOT_MESSAGE_AT,
            SCRATCH[0],
        ],
        "itemsize": SIZE,
    }
)


def offset(field: str) -> int:
    """EDAC address of ``field``."""
    return int(EDAC_DTYPE.fields[field][1])  # type: ignore[index]


RESULT_LENGTH = offset("result_length")  #: 0x004C: 2616 when a result is ready, else 0
TOTAL_LENGTH = offset("total_length")  #: 0x0050: 4120 when ready (ours)
