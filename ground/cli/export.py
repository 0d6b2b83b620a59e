"""``st16-ground export openc3 DIR`` and ``export xtce FILE`` (or ``-o PATH``): ground-system
definitions generated from ``protocol/`` (docs/ground_systems.md). An existing FILE is replaced
(docs/cli.md "Outputs"); a DIR that holds anything is written into only with ``--force``; the
OpenC3 target is written beside DIR first, parsed back with openc3's own ``PacketConfig``, and
moved into place only then."""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from pathlib import Path

from ground import json_text
from ground.arg_types import InputError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _output(args, positional: str) -> Path:
    """The output path: the positional or ``-o/--output`` (one of them)."""
    given = [v for v in (getattr(args, positional), args.output) if v]
    if len(given) != 1:
        raise InputError(f"give the output once: {positional.upper()} or -o/--output")
    return Path(given[0])


def _refuse_existing_directory(path: Path, force: bool) -> None:
    """docs/cli.md "Outputs": a file is replaced, a directory that holds anything is written into
    only with ``--force`` (files of the same name replaced, the others kept)."""
    if force or not path.exists() or (path.is_dir() and not any(path.iterdir())):
        return
    what = "is not an empty directory" if path.is_dir() else "is a file, not a directory"
    raise InputError(f"{path} {what}: add --force to write over it" if path.is_dir() else f"{path} {what}")


def _openc3(args) -> int:
    from ground.export import model, openc3

    root = _output(args, "dir")
    _refuse_existing_directory(root, args.force)
    version = openc3.check_openc3()
    root.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{root.name}.", dir=root.parent) as tmp:
        openc3.write_target(Path(tmp), model.build())
        n_cmd, n_tlm = openc3.validate(Path(tmp))
        Path(tmp).chmod(0o777 & ~_umask())  # TemporaryDirectory's 0700 would make the target private
        shutil.copytree(tmp, root, dirs_exist_ok=True)
    out = {"dir": str(root), "openc3": version, "commands": n_cmd, "telemetry": n_tlm}
    print(
        json_text.dumps(out)
        if args.json
        else f"wrote {root}: {n_cmd} commands, {n_tlm} telemetry packets (parsed by openc3 {version})"
    )
    return 0


def _xtce(args) -> int:
    from ground.atomic_write import write_text
    from ground.export import model, xtce

    path = _output(args, "file")
    if path.is_dir():
        raise InputError(f"{path} is a directory, not a file")
    text = xtce.dumps(model.build())
    write_text(path, text)
    out = {"file": str(path), "bytes": len(text.encode())}
    print(json_text.dumps(out) if args.json else f"wrote {path}: XTCE 1.2, {out['bytes']} bytes")
    return 0


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
        help="write into a non-empty directory (files of the same name are replaced, others kept)",
    )
    p.set_defaults(func=_openc3)
    p = esub.add_parser("xtce", help="the same space system as XTCE 1.2 (via yamcs-pymdb)")
    p.add_argument("file", nargs="?", help="XTCE file to write (an existing one is replaced); or -o FILE")
    p.add_argument("-o", "--output", help="the same as FILE")
    p.add_argument("--force", action="store_true", help=argparse.SUPPRESS)  # files are replaced: kept for old scripts
    p.set_defaults(func=_xtce)
