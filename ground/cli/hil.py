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

#: The demo passes when its final pointing error is under this, deg, ...
PASS_MARK_DEG = 0.05
#: ... and the flight side used an OK answer of the tracker this recently (s of simulated time):
#: a pass needs the tracker, not the gyro alone (docs/hil.md "The flight side").
FRESH_FIX_S = 5.0


def tracker_failure(summary: dict) -> str | None:
    """Why the run fails for want of the tracker, or None."""
    off = summary.get("tracker_off_after_s")
    told = "" if off is None else f" (--tracker-off-after {off:g})"
    if summary.get("acquisition_s") is None:
        return f"the estimator never had a fix from the tracker{told}: no attitude, the controller only damped the rate"
    age = summary.get("last_fix_age_s")
    if age is None or age > FRESH_FIX_S:
        old = "of unknown age" if age is None else f"{age:.1f} s old"
        return f"the flight side's last tracker fix is {old} at the end, over {FRESH_FIX_S:g} s{told}"
    return None


def _demo(args) -> int:
    import contextlib

    from ground.hil.run import parse_epoch, run_hil
    from ground.sim.gyro import GyroSpec

    gyro = GyroSpec(args.gyro_bias_deg_h, args.gyro_arw_deg_rt_h, args.gyro_rrw_deg_h_rt_h, args.gyro_sf_ppm)
    problems = gyro.problems()
    if problems:
        print(f"st16-ground: {'; '.join(problems)}", file=sys.stderr)
        return 2
    parse_epoch(args.epoch)  # one line, exit 2, before the catalog is built
    # under --json the loop's own progress lines go to stderr: stdout is the one summary document
    with contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext():
        summary = run_hil(
            args.out,
            args.duration,
            args.dynamics,
            args.seed,
            progress=progress_on(args),
            scenario=args.scenario,
            epoch_utc=args.epoch,
            speed=args.speed,
            gyro_spec=gyro,
            tracker_off_after=args.tracker_off_after,
        )
    if args.json:
        print(json_text.dumps({**summary, "written": [f"{args.out}/{n}" for n in _WRITTEN]}))
    else:
        for key, value in summary.items():
            print(f"{key}: {value:.4g}" if isinstance(value, float) else f"{key}: {value}")
        print(f"written: {args.out}/{', '.join(_WRITTEN)}")
    why = tracker_failure(summary)
    if why is not None:
        print(f"st16-ground: hil demo failed: {why}", file=sys.stderr)
        return 1
    if args.scenario != "none":
        from ground.hil.run import parse_epoch
        from ground.hil.scenarios import plan

        why = plan(args.scenario, parse_epoch(args.epoch)).failure(summary, PASS_MARK_DEG, FRESH_FIX_S)
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


def _two_heads(args) -> int:
    from pathlib import Path

    from ground.hil import two_heads

    return 0 if two_heads.run_scenario(Path(args.out)) else 1


def register(sub) -> None:
    p = sub.add_parser("hil", help="hardware-in-the-loop: the tracker in a closed attitude loop")
    hsub = p.add_subparsers(dest="hil_command", metavar="ACTION")
    hsub.required = True
    t = hsub.add_parser(
        "two-heads",
        help="two heads on one line, one swept past the Sun: the flight side selects an OK head (docs/hil.md)",
    )
    t.add_argument("-o", "--output", "--out", dest="out", default="st16-two-heads", help="output folder")
    t.set_defaults(func=_two_heads)
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
        choices=("none", "eclipse-exit", "moon-slew", "two-heads"),
        default="none",
        help="none: a random target 4 deg off; eclipse-exit: sunrise, then a slew past the Sun; "
        "moon-slew: a slew through the Moon; two-heads: two heads, one swept past the Sun, the flight "
        "side selecting (docs/hil.md Scenarios)",
    )
    d.add_argument(
        "--dynamics",
        choices=("auto", "basilisk", "standin"),
        default="auto",
        help="auto: Basilisk when bsk is installed, else the numpy stand-in",
    )
    d.add_argument("--seed", type=int, default=15, help="target attitude and initial error; the gyro's noise")
    from ground.hil.run import DEFAULT_EPOCH_UTC
    from ground.sim.gyro import DEFAULT, LIMITS

    d.add_argument(
        "--epoch",
        default=DEFAULT_EPOCH_UTC,
        help=f"the run's simulated start, ISO-8601 UTC (default {DEFAULT_EPOCH_UTC}: fixed, so a run is the same any day)",
    )
    d.add_argument(
        "--speed",
        type=ranged(float, 0.0, 100.0, "a speed"),
        default=0.0,
        help="simulated s per real s (1: real time; default 0: as fast as the device answers; lockstep at any speed)",
    )
    d.add_argument(
        "--tracker-off-after",
        type=ranged(float, 0.0, 1e6, "a time in s"),
        default=None,
        help="withhold the tracker's answers from the flight side after this many s (0: never a fix; the control run)",
    )
    for name, unit in (
        ("bias_deg_h", "1-sigma turn-on bias, deg/h"),
        ("arw_deg_rt_h", "angle random walk, deg/sqrt(h)"),
        ("rrw_deg_h_rt_h", "rate random walk, deg/h/sqrt(h)"),
        ("sf_ppm", "1-sigma scale-factor error, ppm"),
    ):
        d.add_argument(
            f"--gyro-{name.split('_')[0]}",
            dest=f"gyro_{name}",
            type=float,
            default=getattr(DEFAULT, name),
            help=f"gyro {unit}, 0..{LIMITS[name]:g} (default {getattr(DEFAULT, name):g}: ground.sim.gyro)",
        )
    d.set_defaults(func=_demo)
