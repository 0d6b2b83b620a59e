"""``st16-ground database build|info``: the whole-sky pattern database (``ground.catalog.sky_database``)
that ``solve-file``, ``replay --offline`` and ``ground.api.solve_image`` search the field of view
against: built once (~15 s, a progress bar) into the user cache or ``--database FILE``."""

from __future__ import annotations

import sys
from pathlib import Path

from ground import json_text
from ground.arg_types import InputError, output_file, progress_on


def _build(args) -> int:
    from ground.catalog import sky_database

    path = Path(args.database) if args.database else sky_database.default_path()
    if path.exists() and not args.force:
        try:
            db = sky_database.load(path)
        except sky_database.DatabaseError as exc:
            print(f"st16-ground: {exc}: building it again", file=sys.stderr)
        else:
            _say(args, db, f"{db.summary()} (kept; --force builds it again)", built=False)
            return 0
    db = sky_database.build(progress=progress_on(args))
    try:
        sky_database.save(db, path)
    except OSError as exc:
        raise InputError(
            f"sky database {path} not written ({exc.strerror or exc}); the old file is as it was"
        ) from None
    _say(args, db, db.summary(), built=True)
    return 0


def _info(args) -> int:
    from ground.catalog import sky_database

    path = Path(args.database) if args.database else sky_database.default_path()
    try:
        db = sky_database.load(path)
    except sky_database.DatabaseError as exc:
        raise InputError(
            f"{exc}; build it with: st16-ground database build"
            + (f" --database {args.database}" if args.database else "")
        ) from None
    _say(args, db, db.summary())
    return 0


def database_doc(db) -> dict:
    """What a loaded database holds, for ``--json`` (``summary()`` says it in one line)."""
    m = db.meta
    size = db.path.stat().st_size if db.path is not None and db.path.exists() else None
    return {
        "path": str(db.path) if db.path is not None else None,
        "version": m["version"],
        "patterns": m["patterns"],
        "stars": m["stars"],
        "faintest_mag": m["faintest_mag"],
        "fov_deg": list(m["fov_deg"]),
        "bytes": size,
        "build_s": m["build_s"],
    }


def _say(args, db, line: str, **extra) -> None:
    """The command's answer: ``line``, or under ``--json`` one document (``extra`` members added)."""
    print(json_text.dumps({**database_doc(db), **extra}) if args.json else line)


def register(sub) -> None:
    p = sub.add_parser("database", help="the whole-sky pattern database the offline solves search")
    verbs = p.add_subparsers(dest="verb", required=True)
    b = verbs.add_parser("build", help="build it (once; ~15 s) into the user cache or --database FILE")
    b.add_argument("--database", type=output_file, help="file to write (default: the user cache's)")
    b.add_argument("--force", action="store_true", help="build again even when a good file is there")
    b.set_defaults(func=_build)
    i = verbs.add_parser("info", help="what a database file holds")
    i.add_argument("--database", help="file to read (default: the user cache's)")
    i.set_defaults(func=_info)
