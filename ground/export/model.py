"""The space-system description both exporters render, built from ``protocol/``'s declarations
only: every command of :data:`protocol.command_table.TABLE` (one packet per wire form of its
payload), every reply, the NACK, the result structure (:data:`protocol.result.RESULT`, whole and
per COMBINATION section) and the EDAC fields (:data:`protocol.edac.EDAC_DTYPE`), with the units,
states, bit fields and limits of :mod:`protocol.telemetry_meta`.

Offsets are bits from the first byte of the NSP message (``dst``); the CRC and SLIP framing are
the link's (stripped before a packet is decoded, appended after it is encoded). Integers and
floats are little-endian; bit fields inside one byte are given MSB-first (``BIG_ENDIAN``), as
OpenC3 and XTCE count bits.
"""

from __future__ import annotations

import enum
import re
import struct
from collections.abc import Iterator, Mapping
from dataclasses import MISSING, dataclass, field, fields, replace
from typing import Any

import numpy as np

from protocol import edac, nsp, result, telemetry_meta
from protocol.command_table import TABLE, Command
from protocol.commands import Code, NackInfo
from protocol.layout import Form, Layout

LITTLE, BIG = "LITTLE_ENDIAN", "BIG_ENDIAN"
HEADER_BYTES = 3  #: dst, src, MCF
ADDRESS_BITS = 16  #: the u16 address that starts every result and EDAC reply part


@dataclass(frozen=True)
class Field:
    """One item: ``bits`` 0 means the rest of the message (a variable-length tail)."""

    name: str
    offset: int  #: bits from the start of the message
    bits: int
    kind: str  #: UINT, INT, FLOAT, STRING or BLOCK
    description: str = ""
    endian: str = LITTLE
    unit: str | None = None
    states: Mapping[str, int] = field(default_factory=dict)
    limits: tuple[float, float, float, float] | None = None
    id_value: int | None = None  #: identifies the packet
    overlap: bool = False  #: a bit field inside another field
    default: Any = None  #: commands: the value sent unless given

    def __post_init__(self) -> None:
        # Plain numbers only: a writer may spell an enum member by its name (yamcs-pymdb wrote
        # the code ``Code.PING`` as initialValue="PING", which the XTCE schema refuses).
        for name in ("id_value", "default"):
            value = getattr(self, name)
            if isinstance(value, enum.Enum):
                object.__setattr__(self, name, value.value)
        if any(isinstance(v, enum.Enum) for v in self.states.values()):
            object.__setattr__(self, "states", {k: int(v) for k, v in self.states.items()})


@dataclass(frozen=True)
class Packet:
    name: str
    description: str
    fields: tuple[Field, ...]


def packet(name: str, description: str, head: list[Field], body: list[Field], prefix: str) -> Packet:
    """A packet of ``head`` then ``body``; a body field named like a header field gets ``prefix``
    (GO's go code: ``GO_CODE``; EDAC's device address: ``EDAC_ADDRESS``)."""
    taken = {f.name for f in head}
    body = [replace(f, name=f"{prefix}_{f.name}") if f.name in taken else f for f in body]
    return Packet(name, description, (*head, *body))


@dataclass(frozen=True)
class SpaceSystem:
    commands: tuple[Packet, ...]
    telemetry: tuple[Packet, ...]  #: most specific identification first


# ----------------------------------------------------------------------------- header


def _byte_bits(byte: int, shift: int, width: int) -> int:
    """MSB-first bit offset of ``width`` bits from bit ``shift`` (LSB = 0) of byte ``byte``."""
    if shift % 8 + width > 8:
        raise ValueError(f"bit field of {width} bits at bit {shift} crosses a byte")
    return (byte + shift // 8) * 8 + 8 - shift % 8 - width


def _mask_field(name: str, mask: int, description: str, **kw: Any) -> Field:
    shift, width = (mask & -mask).bit_length() - 1, bin(mask).count("1")
    return Field(name, _byte_bits(2, shift, width), width, "UINT", description, BIG, **kw)


def header(code: int, command: bool, ack: int | None = 1) -> list[Field]:
    """dst, src and the MCF's bits; ``code`` (and ``ack`` for a reply, unless None) identify."""
    if command:
        return [
            Field("DST", 0, 8, "UINT", "destination address (the device)", default=nsp.DEVICE_ADDRESS),
            Field("SRC", 8, 8, "UINT", "source address (the host)", default=nsp.HOST_ADDRESS),
            _mask_field("POLL", nsp.POLL, "1: reply requested", default=1),
            _mask_field("B", nsp.B_BIT, "copied into the reply", default=0),
            _mask_field("ACK", nsp.ACK, "clear in a command", default=0),
            _mask_field("CODE", nsp.CODE_MASK, "command code", id_value=code, default=code),
        ]
    return [
        Field("DST", 0, 8, "UINT", "destination address (the host)"),
        Field("SRC", 8, 8, "UINT", "source address (the device)"),
        _mask_field("FINAL", nsp.FINAL, "1: last message of the reply"),
        _mask_field("B", nsp.B_BIT, "copied from the command"),
        _mask_field("ACK", nsp.ACK, "1: executed, 0: NACK", id_value=ack),
        _mask_field("CODE", nsp.CODE_MASK, "command code echoed", id_value=None if ack == 0 else code),
    ]


# ----------------------------------------------------------------------------- payloads

_STRUCT_KINDS = {"b": "INT", "h": "INT", "i": "INT", "q": "INT", "f": "FLOAT", "d": "FLOAT"}
_ITEM = re.compile(r"(\d*)([a-zA-Z?])")


def _kind(code: str) -> str:
    return _STRUCT_KINDS.get(code, "UINT")


def value_range(kind: str, bits: int) -> tuple[float, float]:
    """Smallest and largest value of a field (a command parameter's range)."""
    if kind == "UINT":
        return 0, (1 << bits) - 1
    if kind == "INT":
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    big = float(np.finfo(np.float32 if bits == 32 else np.float64).max)
    return -big, big


def _default(cls: type[Layout], name: str) -> Any:
    for f in fields(cls):  # type: ignore[arg-type]
        if f.name == name:
            return 0 if f.default is MISSING else f.default
    return getattr(cls, name)  # a class constant in FIELDS (DarkWindow.SUBCOMMAND)


def layout_fields(cls: type[Layout], form: Form, start: int, command: bool) -> list[Field]:
    """The fields of one wire form of a payload, from bit ``start``; a repeated struct code
    gives ``NAME_0``...; an ``Ns`` item with a wire codec is an N-byte integer (the COMBINATION
    mask), without one a block. Values are the wire values (``protocol.commands`` converts)."""
    out: list[Field] = []
    at = start
    names = iter(cls._names(form.head))
    for count, code in _ITEM.findall(form.head):
        if code == "x":
            at += 8 * int(count or 1)
            continue
        name = next(names)
        n = int(count or 1)
        converted = name in form.wire
        note = f"{cls.NAME}: {name}" + (" (wire value)" if converted else "")
        if code == "s":
            kind = "UINT" if converted else "BLOCK"
            out.append(_payload_field(cls, name, name, at, 8 * n, kind, note, command))
            at += 8 * n
            continue
        bits = 8 * struct.calcsize("<" + code)
        for i in range(n):
            label = f"{name}_{i}" if n > 1 else name
            out.append(_payload_field(cls, name, label, at, bits, _kind(code), note, command, i if n > 1 else None))
            at += bits
    if cls.TAIL:
        size = 8 * (cls.TAIL_SIZE or 0)
        kind = "STRING" if cls.TAIL_CODEC else "BLOCK"
        note = f"{cls.NAME}: {cls.TAIL}" + (f" (records of {cls.ITEM})" if cls.ITEM else "")
        out.append(Field(cls.TAIL.upper(), at, size, kind, note, default=b"" if kind == "BLOCK" else ""))
    return out


def _payload_field(
    cls: type[Layout], name: str, label: str, at: int, bits: int, kind: str, note: str, command: bool, index=None
) -> Field:
    states = telemetry_meta.PAYLOAD_STATES.get(name)
    default = None
    if command:
        default = _default(cls, name)
        if index is not None:
            default = default[index]
        if kind == "BLOCK":
            default = bytes(default)
    return Field(
        label.upper(),
        at,
        bits,
        kind,
        note,
        states={s.name: s.value for s in states} if states else {},
        default=default,
    )


def _form_suffix(cls: type[Layout], key: Any) -> str:
    """The packet-name suffix of one form of a payload with several: ``_LONG1``, ``_MASK_BYTES3``."""
    return f"_{(cls.SELECT or 'form').upper()}{int(key)}" if len(cls.forms()) > 1 else ""


def _reply_form(cmd: Command) -> tuple[type[Layout], Form] | None:
    """The form of ``cmd``'s reply: an echoed address as wide as the request's (PEEK, POKE: 4
    bytes), else the form of the payload's default selector (READ/WRITE FILE: the short form)."""
    cls = cmd.reply
    if cls is None:
        return None
    forms = cls.forms()
    if len(forms) == 1:
        return cls, next(iter(forms.values()))
    key = next(f.default for f in fields(cls) if f.name == cls.SELECT)  # type: ignore[arg-type]
    request = cmd.request
    if cls.SELECT == "width" and request is not None and request.FORMS is None:
        first_name, (first_code,) = request._names(request.HEAD)[0], _ITEM.findall(request.HEAD)[:1]
        if first_name == "address":
            key = struct.calcsize("<" + first_code[1])
    return cls, forms[key]


# ----------------------------------------------------------------------------- structured dtypes


def _name(parts: list[str]) -> str:
    return "_".join(parts).upper()


def dtype_fields(
    dt: np.dtype[Any],
    start: int,
    units: Mapping[str, str],
    states: Mapping[str, Any],
    bits: Mapping[str, tuple[telemetry_meta.BitField, ...]],
    prefix: tuple[str, ...] = (),
    path: tuple[str, ...] = (),
) -> Iterator[Field]:
    """Scalar items of a structured dtype at bit ``start``: arrays of numbers are spelt out
    (``QUATERNION_0``...), arrays of bytes are one block, ``S`` fields strings; ``path`` is the
    field path without indices that :mod:`protocol.telemetry_meta` is keyed by."""
    for fname in dt.names or ():
        sub, offset = dt.fields[fname][:2]  # type: ignore[index]
        at = start + 8 * offset
        key = (*path, fname)
        if sub.subdtype is not None and not (sub.base.kind == "u" and sub.base.itemsize == 1):
            base, shape = sub.subdtype
            for index in np.ndindex(shape):
                flat = int(np.ravel_multi_index(index, shape))
                name = (*prefix, fname, *(str(i) for i in index))
                at_i = at + 8 * base.itemsize * flat
                if base.names:
                    yield from dtype_fields(base, at_i, units, states, bits, name, key)
                else:
                    yield from _leaf(base, at_i, name, key, units, states, bits)
        elif sub.names:
            yield from dtype_fields(sub, at, units, states, bits, (*prefix, fname), key)
        else:
            yield from _leaf(sub, at, (*prefix, fname), key, units, states, bits)


def _leaf(dt, at, name, key, units, states, bits) -> Iterator[Field]:
    dotted = ".".join(key)
    label = _name(list(name))
    if dt.subdtype is not None:  # bytes
        yield Field(label, at, 8 * dt.itemsize, "BLOCK", dotted)
        return
    kind = {"u": "UINT", "i": "INT", "f": "FLOAT", "S": "STRING"}[dt.kind]
    enum = states.get(dotted)
    yield Field(
        label,
        at,
        8 * dt.itemsize,
        kind,
        dotted,
        unit=units.get(dotted),
        states={m.name: m.value for m in enum} if enum else {},
    )
    for bf in bits.get(dotted, ()):
        yield Field(
            f"{label}_{bf.name.upper()}",
            _byte_bits(at // 8, bf.shift, bf.bits),
            bf.bits,
            "UINT",
            f"{dotted} bit {bf.shift}" if bf.bits == 1 else f"{dotted} bits {bf.shift}-{bf.shift + bf.bits - 1}",
            BIG,
            states=dict(bf.states),
            overlap=True,
        )


def result_fields(start: int, lo: int = 0, hi: int = result.TOTAL_LENGTH) -> list[Field]:
    """Items of the result structure whose bytes lie in [lo, hi), placed at ``start`` + their
    offset - ``lo``."""
    out = dtype_fields(
        result.RESULT,
        start - 8 * lo,
        telemetry_meta.RESULT_UNITS,
        telemetry_meta.RESULT_STATES,
        telemetry_meta.RESULT_BITS,
    )
    return [f for f in out if 8 * lo <= f.offset - start + 8 * lo < 8 * hi]


def _edac_fields(fname: str, start: int) -> list[Field]:
    sub = edac.EDAC_DTYPE.fields[fname][0]  # type: ignore[index]
    if fname == "analog":
        if sub.shape != (len(telemetry_meta.ANALOG),):
            raise ValueError("telemetry_meta.ANALOG does not match the EDAC analog frame")
        return [
            Field(
                f"ANALOG_{a.name.upper()}",
                start + 32 * i,
                32,
                "FLOAT",
                f"analog frame: {a.name} (nominal {a.nominal} {a.unit})",
                unit=a.unit,
                limits=telemetry_meta.analog_limits(a),
            )
            for i, a in enumerate(telemetry_meta.ANALOG)
        ]
    one = np.dtype({"names": [fname], "formats": [sub], "offsets": [0], "itemsize": sub.itemsize})
    return list(dtype_fields(one, start, telemetry_meta.EDAC_UNITS, {}, telemetry_meta.EDAC_BITS))


# ----------------------------------------------------------------------------- packets


def _address_id(start: int, address: int) -> Field:
    return Field("ADDRESS", start, ADDRESS_BITS, "UINT", "address of the first byte", id_value=address)


def _section_name(address: int) -> str:
    """The result field a COMBINATION section starts with."""
    offsets: Mapping[str, Any] = result.RESULT.fields or {}
    return next(n for n, spec in offsets.items() if spec[1] == address).upper()


def _specific_replies() -> list[Packet]:
    """Replies told apart by their address too: the whole result (READ RESULT from 0, its parts
    joined by the target's NSP protocol), each COMBINATION section, each EDAC field."""
    body = 8 * HEADER_BYTES
    data = body + ADDRESS_BITS
    out = [
        Packet(
            "RESULT",
            f"READ RESULT from address 0: the result structure ({result.TOTAL_LENGTH} bytes, parts joined)",
            (*header(Code.READ_RESULT, False), _address_id(body, 0), *result_fields(data)),
        )
    ]
    for mask, (address, length) in sorted(result.SECTIONS.items()):
        out.append(
            Packet(
                f"COMBINATION_{_section_name(address)}",
                f"COMBINATION section 0x{mask:04X}: result bytes 0x{address:03X}+{length}",
                (
                    *header(Code.COMBINATION, False),
                    _address_id(body, address),
                    *result_fields(data, address, address + length),
                ),
            )
        )
    for fname in edac.EDAC_DTYPE.names or ():
        address = edac.offset(fname)
        out.append(
            packet(
                f"EDAC_{fname.upper()}",
                f"READ EDAC at 0x{address:04X}: {fname}",
                [*header(Code.READ_EDAC, False), _address_id(body, address)],
                _edac_fields(fname, data),
                "EDAC",
            )
        )
    return out


def _command_packets(cmd: Command) -> Iterator[Packet]:
    head = header(cmd.code, True)
    if cmd.request is None:
        yield Packet(cmd.code.name, cmd.help, tuple(head))
        return
    for key, form in cmd.request.forms().items():
        yield packet(
            cmd.code.name + _form_suffix(cmd.request, key),
            f"{cmd.help}; data: {cmd.send}",
            head,
            layout_fields(cmd.request, form, 8 * HEADER_BYTES, True),
            cmd.code.name,
        )


def _reply_packet(cmd: Command) -> Packet:
    head = header(cmd.code, False)
    reply = _reply_form(cmd)
    if reply is None:
        body = [Field("DATA", 8 * HEADER_BYTES, 0, "STRING", f"{cmd.name} reply: {cmd.answer}")]
    else:
        body = layout_fields(reply[0], reply[1], 8 * HEADER_BYTES, False)
    return packet(f"{cmd.code.name}_REPLY", f"{cmd.name} ACK: {cmd.answer}", head, body, cmd.code.name)


def build() -> SpaceSystem:
    """The whole description."""
    commands = tuple(p for cmd in TABLE for p in _command_packets(cmd))
    nack = Packet(
        "NACK",
        "a refused command: u16 reason + UTF-8 text (docs/ICD.md section 4)",
        (*header(0, False, ack=0), *layout_fields(NackInfo, NackInfo.forms()[None], 8 * HEADER_BYTES, False)),
    )
    telemetry = (*_specific_replies(), *(_reply_packet(cmd) for cmd in TABLE), nack)
    names = [p.name for p in commands] + [p.name for p in telemetry]
    if len(set(names)) != len(names):
        raise ValueError("two packets with one name")
    for p in (*commands, *telemetry):
        if len({f.name for f in p.fields}) != len(p.fields):
            raise ValueError(f"{p.name}: two items with one name")
    return SpaceSystem(commands, telemetry)
