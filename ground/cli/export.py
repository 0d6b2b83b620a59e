"""``st16-ground export openc3 DIR`` and ``export xtce FILE`` (or ``-o PATH``): ground-system
definitions generated from ``protocol/`` (docs/ground_systems.md). An existing FILE is replaced
(docs/cli.md "Outputs"); a DIR that holds anything is replaced (whole, never merged into) only
with ``--force``. Both are written beside their target first (the OpenC3 target parsed back with
openc3's own ``PacketConfig``, the XTCE validated against the XTCE 1.2 schema when it is found)
and renamed into place only then (``ground.export.staging``): a killed export leaves no output or
a whole one."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ground import json_text
from ground.arg_types import InputError


def _output(args, positional: str) -> Path:
    """The output path: the positional or ``-o/--output`` (one of them)."""
    given = [v for v in (getattr(args, positional), args.output) if v]
    if len(given) != 1:
        raise InputError(f"give the output once: {positional.upper()} or -o/--output")
    return Path(given[0])


def _refuse_existing_directory(path: Path, force: bool) -> None:
    """docs/cli.md "Outputs": a file is replaced, a directory that holds anything is replaced
    (whole, never merged into) only with ``--force``."""
    if force or not path.exists() or (path.is_dir() and not any(path.iterdir())):
        return
    what = "is not an empty directory" if path.is_dir() else "is a file, not a directory"
    raise InputError(f"{path} {what}: add --force to write over it" if path.is_dir() else f"{path} {what}")


def _openc3(args) -> int:
    from ground.export import model, openc3, staging

    root = _output(args, "dir")
    _refuse_existing_directory(root, args.force)
    version = openc3.check_openc3()
    with staging.staged(root, args.force, directory=True) as tmp:
        if args.heads:  # one target per head on one line (ground.export.heads)
            from ground.export import heads

            heads.write_targets(tmp, model.build(), args.heads)
            n_cmd, n_tlm = heads.validate(tmp, args.heads)
        else:
            openc3.write_target(tmp, model.build())
            n_cmd, n_tlm = openc3.validate(tmp)
    out = {"dir": str(root), "openc3": version, "commands": n_cmd, "telemetry": n_tlm}
    print(
        json_text.dumps(out)
        if args.json
        else f"wrote {root}: {n_cmd} commands, {n_tlm} telemetry packets (parsed by openc3 {version})"
    )
    return 0


SHOWN_ERRORS = 3  #: schema errors a refused XTCE export names


def _xtce(args) -> int:
    from ground.export import model, staging, xtce

    path = _output(args, "file")
    if path.is_dir():
        raise InputError(f"{path} is a directory, not a file")
    try:
        schema = xtce.find_schema(args.schema)
    except FileNotFoundError as exc:
        raise InputError(str(exc)) from None
    if args.heads:  # one subsystem per head (ground.export.heads)
        from ground.export import heads

        text = heads.xtce_dumps(model.build(), args.heads)
    else:
        text = xtce.dumps(model.build())
    if schema is not None:
        errors = xtce.schema_errors(text, schema)
        if errors:  # a bug of the exporter, not bad input: exit 1, nothing written
            first = "; ".join(errors[:SHOWN_ERRORS])
            message = f"XTCE not written: {len(errors)} errors against {schema}; first: {first}"
            print(f"st16-ground: {message}", file=sys.stderr)
            if args.json:
                print(json_text.dumps({"error": "XtceInvalid", "message": message, "exit_code": 1}))
            return 1
    with staging.staged(path, True, directory=False) as tmp:
        tmp.write_text(text, encoding="utf-8")
    out = {
        "file": str(path),
        "bytes": len(text.encode()),
        "schema": str(schema) if schema else None,
        "schema_errors": 0 if schema else None,
    }
    checked = f"0 errors against {schema.name}" if schema else "not validated: no XTCE schema found (--schema XSD)"
    print(json_text.dumps(out) if args.json else f"wrote {path}: XTCE 1.2, {out['bytes']} bytes, {checked}")
    return 0


HEADS_HELP = "several heads on one line (st16-device --heads): their NSP addresses, e.g. 0x0E,0x0F; one target each"


def _addresses(text: str) -> list[int]:
    """``--heads 0x0E,0x0F``: 1-4 distinct addresses 0x00-0xFF."""
    try:
        addresses = [int(a, 0) for a in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text[:40]!r}: comma-separated addresses, e.g. 0x0E,0x0F") from None
    from ground.export.heads import check_addresses

    try:
        check_addresses(addresses)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return addresses


def register(sub) -> None:
    """Called by ``ground.cli.main``: ``export openc3`` and ``export xtce``."""
    export = sub.add_parser("export", help="ground-system definitions from protocol/: OpenC3 COSMOS target, XTCE")
    esub = export.add_subparsers(dest="export_command", metavar="FORMAT")
    esub.required = True
    p = esub.add_parser("openc3", help="an OpenC3 COSMOS plugin tree: target, command/telemetry files, interface")
    p.add_argument("dir", nargs="?", help="directory to write (created; a non-empty one needs --force); or -o DIR")
    p.add_argument("-o", "--output", help="the same as DIR")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace a non-empty directory (whole: nothing of it is kept)",
    )
    p.add_argument("--heads", type=_addresses, help=HEADS_HELP)
    p.set_defaults(func=_openc3)
    p = esub.add_parser("xtce", help="the same space system as XTCE 1.2 (via yamcs-pymdb)")
    p.add_argument("file", nargs="?", help="XTCE file to write (an existing one is replaced); or -o FILE")
    p.add_argument("-o", "--output", help="the same as FILE")
    p.add_argument("--force", action="store_true", help=argparse.SUPPRESS)  # files are replaced: kept for old scripts
    p.add_argument(
        "--schema",
        metavar="XSD",
        help="XTCE 1.2 schema to validate against before writing (default: ../shared/data/xtce/"
        "SpaceSystemV1.2.xsd of a checkout, when there); an invalid export is refused",
    )
    p.add_argument("--heads", type=_addresses, help=HEADS_HELP)
    p.set_defaults(func=_xtce)
