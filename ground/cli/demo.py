"""``st16-ground demo``: the end-to-end demonstration (the README's first command; what it runs is
``ground.cli.end_to_end``). It first loads the pipeline's compiled kernels, which the first run
after install compiles (about a minute on 2 cores, said on stderr with a bar), so that the device
it starts loads them from numba's cache in a fraction of a second.

``st16-ground warm-up``: that step alone (after install, say, or in an image build), and the
whole-sky pattern database the offline solves search (``ground.catalog.sky_database``: built once,
~15 s, a bar, when the user cache has none).
"""

from __future__ import annotations

import sys

from ground import json_text
from ground.arg_types import progress_on


def _kernels(progress: bool) -> dict:
    """Load (or compile) the kernels: how long it took and where they are cached."""
    from firmware_model import kernel_cache_dir
    from ground.kernels import warm_up_kernels

    seconds = warm_up_kernels(progress=progress)
    where, _ = kernel_cache_dir()
    return {"seconds": seconds, "cache": str(where) if where else None}


def _kernels_line(kernels: dict) -> str:
    where = kernels["cache"] or "beside the modules, in __pycache__"
    return f"kernels: ready in {kernels['seconds']:.1f} s (numba's cache: {where})"


def _steps_to_stderr(args):
    """Under ``--json`` the steps' lines go to stderr: stdout is the one document."""
    import contextlib

    return contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext()


def _demo(args) -> int:
    import errno
    import os
    from pathlib import Path

    from ground.cli.end_to_end import demo_exit_code, print_demo, run_demo

    if Path(args.out).exists() and not Path(args.out).is_dir():  # said before any wait
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), args.out)
    with _steps_to_stderr(args):
        kernels = _kernels(progress_on(args))
        print(_kernels_line(kernels), flush=True)
        result = run_demo(args.out, n_frames=args.frames, seed=args.seed, progress=progress_on(args))
    if args.json:
        print(json_text.dumps({**result, "kernels": kernels}))
    else:
        print_demo(result)
    return demo_exit_code(result)


def _warm_up(args) -> int:
    from ground.catalog.sky_database import sky_database
    from ground.cli.database import database_doc

    with _steps_to_stderr(args):
        kernels = _kernels(progress_on(args))
        print(_kernels_line(kernels), flush=True)
        db = sky_database(progress=progress_on(args))
    print(json_text.dumps({"kernels": kernels, "database": database_doc(db)}) if args.json else db.summary())
    return 0


def register(sub) -> None:
    p = sub.add_parser("demo", help="end-to-end demo: device on a pty, catalog upload, solves over the link")
    p.add_argument(
        "-o", "--output", "--out", dest="out", default="st16-demo", help="output folder for logs, frames and plots"
    )
    p.add_argument("--frames", type=int, default=6, help="frames to render and solve")
    p.add_argument("--seed", type=int, default=2026, help="render seed")
    p.set_defaults(func=_demo)

    p = sub.add_parser(
        "warm-up",
        help="load the pipeline's compiled kernels (compiled on the first run after install, about a minute) "
        "and the sky database (built once, ~15 s)",
    )
    p.set_defaults(func=_warm_up)
