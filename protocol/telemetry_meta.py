"""What ground systems show next to the raw values: units, named states, bit fields and limits of
the fields that :mod:`protocol.result`, :mod:`protocol.edac` and :mod:`protocol.commands` declare.

Keys are field paths: dotted names into a structured dtype with array indices left out
(``"omega"``, ``"ext.stars.x"``), or a payload field's name (``"slot"``). ``ground.export``
turns these into OpenC3 COSMOS and XTCE definitions; nothing here changes the wire.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum

from protocol import edac, result
from protocol.commands import MemorySpace, NackReason, Slot, XferState

#: Full names of the unit abbreviations used below.
UNIT_NAMES: Mapping[str, str] = {
    "s": "seconds",
    "rad": "radians",
    "rad/s": "radians per second",
    "px": "pixels",
    "DN": "digital numbers",
    "A": "amperes",
    "V": "volts",
    "degC": "degrees Celsius",
    "B": "bytes",
}

#: Units of result fields (docs/ICD.md section 10, protocol.result docstrings).
RESULT_UNITS: Mapping[str, str] = {
    "omega": "rad/s",
    "epoch": "s",
    "image.capture_time": "s",
    "centroid.centroids": "px",
    "ext.solve_time": "s",
    "ext.sigma": "rad",
    "ext.residual_rms": "rad",
    "ext.stage_times": "s",
    "ext.psf_sigma": "px",
    "ext.focal_px": "px",
    "ext.focal_sigma": "px",
    "ext.optics_rms": "px",
    "ext.stars.x": "px",
    "ext.stars.y": "px",
    "ext.stars.flux": "DN",
    "ext.stars.residual": "rad",
}

#: Result fields whose value is one member of an enum.
RESULT_STATES: Mapping[str, type[IntEnum]] = {"ext.method": result.MethodCode}

#: Payload fields (any command or reply) whose value is one member of an enum, by field name.
PAYLOAD_STATES: Mapping[str, type[IntEnum]] = {
    "slot": Slot,
    "space": MemorySpace,
    "state": XferState,
    "reason": NackReason,
}


@dataclass(frozen=True)
class BitField:
    """``bits`` bits from bit ``shift`` (0 = least significant) of an unsigned field; ``states``
    names its values (a one-bit flag without states reads 0 or 1)."""

    name: str
    shift: int
    bits: int = 1
    states: Mapping[str, int] = field(default_factory=dict)


def _flags(enum: type[IntEnum]) -> tuple[BitField, ...]:
    """One one-bit field per member of a single-bit enum."""
    return tuple(BitField(m.name.lower(), m.value.bit_length() - 1) for m in enum)


_QUATERNION_ORDER_BIT = result.HW_QUATERNION_SCALAR_LAST.bit_length() - 1

#: Bit fields of result fields: the return bits and our status (bits 8-15), the status mirror,
#: quaternion order and bright bodies inside their exclusion angles in ``hardware.status``, the optics flags, and each star's flags (bit 0
#: matched, 1 saturated, 2 on a body, 8-11 which body).
RESULT_BITS: Mapping[str, tuple[BitField, ...]] = {
    "return_code": (
        *_flags(result.ReturnBits),
        BitField("status", 8, 8, {s.name: s.value for s in result.Status}),
    ),
    "hardware.status": (
        BitField("status", 0, result.HW_STATUS_MIRROR.bit_length(), {s.name: s.value for s in result.Status}),
        BitField(
            "quaternion_order",
            _QUATERNION_ORDER_BIT,
            1,
            {result.QuaternionOrder.of_hardware_status(v << _QUATERNION_ORDER_BIT).name: v for v in (0, 1)},
        ),
        *_flags(result.ExclusionBits),
    ),
    "ext.optics_flags": (
        BitField("optics_fitted", result.OPTICS_FITTED.bit_length() - 1),
        BitField("optics_searched", result.OPTICS_SEARCHED.bit_length() - 1),
        BitField("psf_measured", result.PSF_MEASURED.bit_length() - 1),
    ),
    "ext.search_flags": (
        BitField("search_budget_reached", result.SEARCH_BUDGET_REACHED.bit_length() - 1),
        BitField("deadline_missed", result.DEADLINE_MISSED.bit_length() - 1),
    ),
    "ext.stars.flags": (
        BitField("matched", 0),
        BitField("saturated", 1),
        BitField("on_body", 2),
        BitField("body", 8, 4, {"NONE": 0, **{b.upper(): i + 1 for i, b in enumerate(result.BODIES)}}),
    ),
}


@dataclass(frozen=True)
class Analog:
    """One channel of the EDAC analog frame: name, unit, nominal value."""

    name: str
    unit: str
    nominal: float


#: The analog frame at EDAC 0x0004 (8 x f32), in order, with the nominal values an idle emulator
#: reports (firmware_model.device.housekeeping: noise, and the current and temperature with activity).
ANALOG: tuple[Analog, ...] = (
    Analog("current", "A", 0.25),
    Analog("bus", "V", 5.0),
    Analog("vdd_core", "V", 1.2),
    Analog("vdd_mpu", "V", 1.8),
    Analog("vdd_io", "V", 3.3),
    Analog("supervisor_temp", "degC", 20.0),
    Analog("vdd_supervisor", "V", 3.3),
    Analog("vdd_detector", "V", 2.8),
)
#: Limits of an analog channel as fractions of its nominal value (ours): yellow beyond +-5 %,
#: red beyond +-10 %.
ANALOG_YELLOW, ANALOG_RED = 0.05, 0.10


def analog_limits(channel: Analog) -> tuple[float, float, float, float]:
    """(red low, yellow low, yellow high, red high) of ``channel``."""
    n = channel.nominal
    return (n * (1 - ANALOG_RED), n * (1 - ANALOG_YELLOW), n * (1 + ANALOG_YELLOW), n * (1 + ANALOG_RED))


#: EDAC fields in bytes, and the status word's bits.
EDAC_UNITS: Mapping[str, str] = {"result_length": "B", "total_length": "B"}
EDAC_BITS: Mapping[str, tuple[BitField, ...]] = {
    "status": (
        BitField("app_mode", edac.STATUS_APP_MODE.bit_length() - 1),
        BitField("busy", edac.STATUS_BUSY.bit_length() - 1),
        BitField("result_ready", edac.STATUS_RESULT_READY.bit_length() - 1),
    ),
}
