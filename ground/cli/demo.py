"""``st16-ground demo``: the end-to-end demonstration (the README's first command; what it runs is
``ground.cli.end_to_end``)."""

from __future__ import annotations

from ground.arg_types import progress_on


def _demo(args) -> int:
    from ground.cli.end_to_end import run_demo

    return run_demo(args.out, n_frames=args.frames, seed=args.seed, progress=progress_on(args))


def register(sub) -> None:
    p = sub.add_parser("demo", help="end-to-end demo: device on a pty, catalog upload, solves over the link")
    p.add_argument("--out", default="st16-demo", help="output folder for logs, frames and plots")
    p.add_argument("--frames", type=int, default=6, help="frames to render and solve")
    p.add_argument("--seed", type=int, default=2026, help="render seed")
    p.set_defaults(func=_demo)
