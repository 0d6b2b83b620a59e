"""What the device adds to every result so the public COSMOS driver reads it right (docs/ICD.md
section 10.2): the standard structure's quaternions in the configured order with the order flagged,
the return code's bit 7 and its status mirrored into ``hardware.status``; and the encodings of
the hardware temperatures COSMOS converts (``housekeeping`` supplies the values, so COSMOS no
longer shows a zero as -50 degC)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from protocol import result

#: Quaternions of the standard structure (the extension's stay scalar first).
STANDARD_QUATERNIONS = ("quaternion", "matching.0.quaternion", "matching.1.quaternion")


def detector_temp_raw(temp_c: float) -> int:
    """``hardware.detector_temp_raw`` that COSMOS's ``(raw >> 4) / 16`` converts to ``temp_c`` (degC)."""
    return round(temp_c * 16) << 4


def processor_temp_raw(temp_c: float) -> int:
    """``hardware.processor_temp_raw`` that COSMOS's ``25 + (raw - 0x32) * 1.5`` converts to
    ``temp_c`` (degC, to the nearest 1.5 degC step)."""
    return 0x32 + round((temp_c - 25.0) / 1.5)


def finish(fields: Mapping[str, Any], order: result.QuaternionOrder) -> dict[str, Any]:
    """``fields`` (result paths, quaternions scalar first, ``return_code`` set) as the device writes
    them: standard quaternions in ``order``, bit 7 and the status mirror from the status, the order
    flag."""
    out = dict(fields)
    rc = int(out["return_code"])
    status = result.status_of(rc)
    out["return_code"] = result.make_return_code(status, rc)
    ours = result.HW_STATUS_MIRROR | result.HW_QUATERNION_SCALAR_LAST
    flag = result.HW_QUATERNION_SCALAR_LAST if order is result.QuaternionOrder.SCALAR_LAST else 0
    out["hardware.status"] = int(out.get("hardware.status", 0)) & ~ours | int(status) & result.HW_STATUS_MIRROR | flag
    for path in STANDARD_QUATERNIONS:
        if path in out:
            out[path] = order.to_wire(out[path])
    return out
