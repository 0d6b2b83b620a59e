"""``st16-ground hil demo``: the tracker in a closed attitude loop (docs/hil.md); the loop itself
is ``ground.hil.run``. It writes ``hil_log.jsonl``, ``summary.json`` and ``hil.png`` into its
folder and prints the summary; it fails (exit 1) when the final pointing error is over the pass
mark, and a scenario (``--scenario``, docs/hil.md "Scenarios") also when a high-confidence attitude
came with a body inside its exclusion angle or no exclusion status came at all.
"""

from __future__ import annotations

import sys

from ground import json_text
from ground.arg_types import progress_on, ranged

#: The demo passes when its final pointing error is under this, deg.
PASS_MARK_DEG = 0.05


def _demo(args) -> int:
    import contextlib

    from ground.hil.run import run_hil

    # under --json the loop's own progress lines go to stderr: stdout is the one summary document
    with contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext():
        summary = run_hil(
            args.out, args.duration, args.dynamics, args.seed, progress=progress_on(args), scenario=args.scenario
        )
    if args.json:
        print(json_text.dumps({**summary, "written": [f"{args.out}/{n}" for n in _WRITTEN]}))
    else:
        for key, value in summary.items():
            print(f"{key}: {value:.4g}" if isinstance(value, float) else f"{key}: {value}")
        print(f"written: {args.out}/{', '.join(_WRITTEN)}")
    if args.scenario != "none":
        from ground.hil.scenario_report import scenario_failure

        why = scenario_failure(summary, PASS_MARK_DEG)
        if why is not None:
            print(f"st16-ground: hil demo failed: {why}", file=sys.stderr)
            return 1
        return 0
    last = summary["pointing_error_deg_last"]
    if last is None:
        print("st16-ground: hil demo failed: no pointing error measured (no solve answered)", file=sys.stderr)
        return 1
    if not last < PASS_MARK_DEG:
        print(
            f"st16-ground: hil demo failed: final pointing error {last:.3g} deg is over the {PASS_MARK_DEG} deg pass mark",
            file=sys.stderr,
        )
        return 1
    return 0


_WRITTEN = ("hil_log.jsonl", "summary.json", "hil.png")


def register(sub) -> None:
    p = sub.add_parser("hil", help="hardware-in-the-loop: the tracker in a closed attitude loop")
    hsub = p.add_subparsers(dest="hil_command", metavar="ACTION")
    hsub.required = True
    d = hsub.add_parser("demo", help="Basilisk (or a numpy stand-in) slews to a target on the tracker's attitude")
    d.add_argument(
        "-o", "--output", "--out", dest="out", default="st16-hil", help="output folder for the log, summary and plot"
    )
    d.add_argument(
        "--duration",
        type=ranged(float, 2.0, 3600.0, "a duration in s"),
        default=None,
        help="seconds of loop (default 30, or the scenario's own length)",
    )
    d.add_argument(
        "--scenario",
        choices=("none", "eclipse-exit", "moon-slew"),
        default="none",
        help="none: a random target 4 deg off; eclipse-exit: sunrise, then a slew past the Sun; "
        "moon-slew: a slew through the Moon (docs/hil.md Scenarios)",
    )
    d.add_argument(
        "--dynamics",
        choices=("auto", "basilisk", "standin"),
        default="auto",
        help="auto: Basilisk when bsk is installed, else the numpy stand-in",
    )
    d.add_argument("--seed", type=int, default=15, help="target attitude and initial error")
    d.set_defaults(func=_demo)
