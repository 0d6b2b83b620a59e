"""``st16-ground replay DIR``: every frame of a directory over the link (or ``--offline``
in-process), scored against ``NAME.truth.json`` when present; log, summary and plots in ``--out``
(``--wcs``: each solved frame's FITS WCS in ``--out``/wcs).
``st16-ground table5 DIR``: Enright & McVittie table 5 (basic / ideal colour / chromatic / both) on
frames with truth.
"""

from __future__ import annotations

import sys
from pathlib import Path

from ground import json_text
from ground.arg_types import InputError, progress_on
from ground.cli.offline_options import load_catalog, offline_solver
from ground.cli.solve import DEFAULT_RESULTS, user_camera


def _replay(args) -> int:
    from firmware_model.pipeline.frame_readers import frame_files
    from ground.analysis.replay import replay
    from ground.cli.link import client_kwargs
    from ground.link_solver import LinkSolver
    from ground.solver import Solver

    # the input first: no database built, catalog loaded or port opened for a directory without frames
    where = Path(args.directory)
    if not where.is_dir():
        raise InputError(f"{where}: {'not a directory' if where.exists() else 'no such directory'}")
    if not frame_files(where):
        raise InputError(f"{where}: no frame files (DNG/raw, FITS, TIFF, PNG, JPEG, .npy) in the directory")
    solver: Solver
    if args.offline:
        solver = offline_solver(args, search=True)
    else:
        if not args.port:
            raise InputError("--port URL is required (or use --offline)")
        solver = LinkSolver(args.port, reconnect_timeout=args.reconnect_timeout, **client_kwargs(args))
    try:
        summary = replay(
            args.directory,
            solver,
            args.out,
            progress=progress_on(args),
            resume=args.resume,
            wcs_camera=(lambda frame: user_camera(args, frame)) if args.wcs else None,
        )
    except TimeoutError as exc:  # the device did not come back: a link failure
        print(f"st16-ground: {exc}", file=sys.stderr)
        return 4
    finally:
        solver.close()
    summary["log"] = str(Path(args.out) / "results.jsonl")
    print(json_text.dumps(summary) if args.json else _summary_text(summary))
    return 0


def _summary_text(summary: dict) -> str:
    """The summary for a reader: one ``key: value`` line each (nested values as JSON)."""
    from ground.link.commands import render

    return render(summary)


def _table5(args) -> int:
    from firmware_model.device.cli import load_camera
    from firmware_model.pipeline.frame_readers import frame_files
    from ground.analysis.table5 import TABLE5_MODES, table5

    out = table5(
        frame_files(args.directory), load_camera(args.camera), load_catalog(args.catalog), progress=progress_on(args)
    )
    if args.json:
        print(json_text.dumps(out))
    else:
        print(f"{'corrections':<28}{'correct':>9}{'incorrect':>11}{'no match':>10}   ({out['frames']} frames)")
        for mode in TABLE5_MODES:
            c = out["table"][mode]
            print(f"{mode:<28}{c['correct']:>9}{c['incorrect']:>11}{c['no_match']:>10}")
    return 0


def register(sub) -> None:
    from ground.cli.offline_options import add_camera_options, add_params_option

    p = sub.add_parser("replay", help="solve every frame of a directory and score against truth")
    p.add_argument("directory", help="frames (any supported format), with NAME.truth.json beside them to score")
    p.add_argument("--offline", action="store_true", help="run the pipeline in-process instead of over the link")
    p.add_argument("--catalog", help="catalog image for --offline (default: each field's, from the sky database)")
    add_camera_options(p, search=True)
    add_params_option(p)
    p.add_argument("--site", help="with --offline: LAT,LON[,HEIGHT] (deg, m) of a ground site: correct refraction")
    p.add_argument("--pressure", type=float, default=1013.25, help="site pressure, hPa (with --site)")
    p.add_argument("--temperature", type=float, default=10.0, help="site temperature, deg C (with --site)")
    p.add_argument(
        "-o", "--output", "--out", dest="out", default=DEFAULT_RESULTS, help="output directory (log, summary, plots)"
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run logged in --out (its frames are skipped); without it a --out that "
        "holds results is refused",
    )
    p.add_argument("--reconnect-timeout", type=float, default=120.0, help="wait this long for a silent device, s")
    p.add_argument("--wcs", action="store_true", help="write each solved frame's FITS WCS to OUT/wcs/NAME.wcs")
    p.set_defaults(func=_replay)

    p = sub.add_parser("table5", help="Enright & McVittie table 5 on frames with truth (offline)")
    p.add_argument("directory", help="frames with NAME.truth.json beside them")
    p.add_argument("--catalog", required=True, help="catalog image")
    p.add_argument("--camera", help="camera model JSON (default: the reference design)")
    p.set_defaults(func=_table5)
