"""The space system of :func:`ground.export.model.build` as XTCE 1.2, through ``yamcs-pymdb``.

Telemetry: an abstract ``NSP_REPLY`` container holds the header (dst, src, Final, B, ACK, code);
each reply packet extends it on a condition on ACK and the code; a packet told apart by its
address too (a result section, an EDAC field) extends its code's generic reply on a condition on
that reply's ``ADDRESS``. Parameters are named ``PACKET_ITEM`` (the header ones by themselves),
entries are placed at absolute bit positions from the message start. Commands carry every field
as an argument at its position, the header's with their defaults and the code fixed.

Left out: the ``COMBINATION_<SECTION>`` packets (:func:`wire_telemetry`: on the wire a COMBINATION
reply's bytes 0-1 are a running byte count, ICD page 1-35918, not the section address that
identifies them in the OpenC3 target after its ``NspProtocol``). Left out, because XTCE 1.2 has no
"rest of the message" size: the variable-length tails (PING
banner, NACK text, data of PEEK / READ EDAC / READ RESULT parts, upload data). The CRC and SLIP
framing are the link's, as in the OpenC3 target.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ground.export import model
from ground.optional import MissingExtra

SYSTEM = "ST16"
SCHEMA_NAME = "SpaceSystemV1.2.xsd"
#: The OMG XTCE 1.2 schema where a checkout of this project finds it (../shared beside the clone)
CHECKOUT_SCHEMA = Path(__file__).resolve().parents[3] / "shared" / "data" / "xtce" / SCHEMA_NAME


def _encoding(pymdb: Any, f: model.Field) -> Any:
    little = f.endian == model.LITTLE and f.bits > 8
    if f.kind == "FLOAT":
        return pymdb.FloatEncoding(bits=f.bits, little_endian=little)
    if f.kind == "STRING":
        return pymdb.StringEncoding(bits=f.bits, termination=None)
    if f.kind == "BLOCK":
        return pymdb.BinaryEncoding(bits=f.bits)
    scheme = pymdb.IntegerEncodingScheme.TWOS_COMPLEMENT if f.kind == "INT" else pymdb.IntegerEncodingScheme.UNSIGNED
    return pymdb.IntegerEncoding(bits=f.bits, little_endian=little, scheme=scheme)


def _choices(f: model.Field) -> list[tuple[int, str]]:
    return [(value, state) for state, value in f.states.items()]


def _parameter(pymdb: Any, system: Any, name: str, f: model.Field) -> Any:
    common = {"short_description": f.description or None, "units": f.unit, "encoding": _encoding(pymdb, f)}
    if f.states:
        return pymdb.EnumeratedParameter(system, name, choices=_choices(f), **common)
    if f.kind == "FLOAT":
        alarm = None
        if f.limits:
            red_lo, yellow_lo, yellow_hi, red_hi = f.limits
            alarm = pymdb.ThresholdAlarm(
                warning_low=yellow_lo, warning_high=yellow_hi, critical_low=red_lo, critical_high=red_hi
            )
        return pymdb.FloatParameter(system, name, bits=f.bits, alarm=alarm, **common)
    if f.kind == "STRING":
        return pymdb.StringParameter(system, name, **common)
    if f.kind == "BLOCK":
        return pymdb.BinaryParameter(system, name, **common)
    return pymdb.IntegerParameter(system, name, signed=f.kind == "INT", bits=f.bits, **common)


def _argument(pymdb: Any, f: model.Field) -> Any:
    common = {"short_description": f.description or None, "units": f.unit, "encoding": _encoding(pymdb, f)}
    if f.kind == "BLOCK":
        return pymdb.BinaryArgument(f.name, default=bytes(f.default or b""), **common)
    if f.kind == "STRING":
        return pymdb.StringArgument(f.name, default=str(f.default or ""), **common)
    if f.states:
        default = next((s for s, v in f.states.items() if v == f.default), None)
        return pymdb.EnumeratedArgument(f.name, choices=_choices(f), default=default, **common)
    lo, hi = model.value_range(f.kind, f.bits)
    if f.id_value is not None:
        lo = hi = f.id_value
    if f.kind == "FLOAT":
        return pymdb.FloatArgument(f.name, bits=f.bits, default=f.default, **common)
    return pymdb.IntegerArgument(
        f.name, signed=f.kind == "INT", bits=f.bits, minimum=int(lo), maximum=int(hi), default=f.default, **common
    )


def pymdb_module() -> Any:
    """``yamcs.pymdb`` (the ground-systems extra)."""
    try:
        from yamcs import pymdb
    except ImportError:
        raise MissingExtra("export xtce needs yamcs-pymdb: pip install 'colour-st16[ground-systems]'") from None
    return pymdb


def space_system(system: model.SpaceSystem, name: str = SYSTEM, parent: Any = None) -> Any:
    """The ``yamcs.pymdb.System`` of ``system`` (a ``Subsystem`` of ``parent`` when given: one
    head of several, ``ground.export.heads``)."""
    pymdb = pymdb_module()

    about = "ST-16-style colour star tracker, NSP link (docs/ICD.md)"
    root = (
        pymdb.System(name, short_description=about)
        if parent is None
        else pymdb.Subsystem(parent, name, short_description=about)
    )
    head = model.header(0, False)
    params = {f.name: _parameter(pymdb, root, f.name, f) for f in head}
    base = pymdb.Container(
        root,
        "NSP_REPLY",
        [pymdb.ParameterEntry(params[f.name], bitpos=f.offset) for f in head],
        abstract=True,
        short_description="NSP reply header: dst, src, MCF",
    )
    generic: dict[tuple[Any, ...], tuple[Any, dict[str, Any]]] = {}  # header ids -> container, its params
    # generic replies first: a packet told apart by its address extends its code's generic reply
    ordered = sorted(wire_telemetry(system), key=lambda p: any(f.id_value is not None for f in p.fields[len(head) :]))
    for packet in ordered:
        ids = tuple((f.name, f.id_value) for f in packet.fields if f.name in params and f.id_value is not None)
        extra_ids = [f for f in packet.fields if f.name not in params and f.id_value is not None]
        parent, parent_params = generic.get(ids, (None, {}))
        own: dict[str, Any] = {}
        entries = []
        for f in packet.fields:
            if f.name in params or f.bits == 0:
                continue
            if f.name in parent_params:
                continue
            own[f.name] = _parameter(pymdb, root, f"{packet.name}_{f.name}", f)
            entries.append(pymdb.ParameterEntry(own[f.name], bitpos=f.offset))
        if extra_ids and parent is not None:
            condition = _all(pymdb, [pymdb.eq(parent_params[f.name], f.id_value) for f in extra_ids])
            pymdb.Container(
                root, packet.name, entries, base=parent, condition=condition, short_description=packet.description
            )
            continue
        condition = _all(pymdb, [pymdb.eq(params[n], v) for n, v in ids])
        container = pymdb.Container(
            root, packet.name, entries, base=base, condition=condition, short_description=packet.description
        )
        if not extra_ids:
            generic.setdefault(ids, (container, own))
    _commands(pymdb, root, system)
    return root


def wire_telemetry(system: model.SpaceSystem) -> list[model.Packet]:
    """The telemetry packets a message as it comes off the wire can be identified as: all but the
    ``COMBINATION_<SECTION>`` ones. A COMBINATION reply's bytes 0-1 count the result bytes already
    transmitted (ICD page 1-35918), not a section's address: only the OpenC3 target's
    ``NspProtocol`` re-emits one message per section with its address, and a Yamcs link has no such
    step here, so the reply is the generic ``COMBINATION_REPLY`` (its ``ADDRESS`` is that count)."""
    return [p for p in system.telemetry if not (p.name.startswith("COMBINATION_") and _has_extra_id(p))]


def _has_extra_id(packet: model.Packet) -> bool:
    head = {f.name for f in model.header(0, False)}
    return any(f.id_value is not None and f.name not in head for f in packet.fields)


def _all(pymdb: Any, conditions: list[Any]) -> Any:
    return conditions[0] if len(conditions) == 1 else pymdb.all_of(*conditions)


def _commands(pymdb: Any, root: Any, system: model.SpaceSystem) -> None:
    for packet in system.commands:
        fields = [f for f in packet.fields if f.bits]
        arguments = [_argument(pymdb, f) for f in fields]
        pymdb.Command(
            root,
            packet.name,
            short_description=packet.description,
            arguments=arguments,
            entries=[pymdb.ArgumentEntry(a, bitpos=f.offset) for a, f in zip(arguments, fields)],
        )


def dumps(system: model.SpaceSystem, name: str = SYSTEM) -> str:
    """XTCE 1.2 text."""
    return str(space_system(system, name).dumps(top_comment="Generated by st16-ground export xtce from protocol/"))


def find_schema(given: str | Path | None = None) -> Path | None:
    """The XTCE 1.2 schema to validate against: ``given`` (must exist), else the checkout's
    ``../shared/data/xtce/SpaceSystemV1.2.xsd`` when it is there, else None."""
    if given is not None:
        path = Path(given)
        if not path.is_file():
            raise FileNotFoundError(f"XTCE schema {path}: no such file")
        return path
    return CHECKOUT_SCHEMA if CHECKOUT_SCHEMA.is_file() else None


def schema_errors(text: str, schema: str | Path, limit: int | None = None) -> list[str]:
    """The schema errors of the XTCE ``text`` against ``schema`` (xmlschema, no network: it
    ships the ``xml.xsd`` the schema imports), each ``path: reason``; at most ``limit``."""
    try:
        import xmlschema
    except ImportError:
        raise MissingExtra("validating XTCE needs xmlschema: pip install 'colour-st16[ground-systems]'") from None
    import re
    from xml.etree import ElementTree

    xsd = xmlschema.XMLSchema(str(schema))
    out = []
    for error in xsd.iter_errors(ElementTree.fromstring(text)):
        where = re.sub(r"\{[^}]*\}", "", error.path or "")
        name = error.elem.get("name") if error.elem is not None else None
        out.append(f"{where}{f' ({name})' if name else ''}: {error.reason}")
        if limit is not None and len(out) >= limit:
            break
    return out
