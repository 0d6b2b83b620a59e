"""``st16-ground solve [--frame FILE]``: upload the frame (or let the device capture), GO, print the
decoded result (``--json`` for the full record) and append it to the results log; ``--offline``
solves in-process with the same pipeline and parameter file.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from ground import json_text
from ground.arg_types import InputError, progress_on
from ground.cli.offline_options import offline_solver

DEFAULT_RESULTS = "st16-results"


def _print_record(rec: dict, as_json: bool) -> None:
    from ground.link.solve_report import format_record

    print(json_text.dumps(rec) if as_json else format_record(rec))


def _solve(args) -> int:
    from firmware_model.pipeline.frame_readers import read_frame
    from ground.analysis.replay import Truth, score
    from ground.analysis.results_log import ResultsLog

    if args.offline and not (args.catalog and args.frame):
        raise InputError("solve --offline needs --frame FILE and --catalog IMAGE")
    if not args.offline and not args.port:
        raise InputError("--port URL is required for solve (or use --offline)")
    solver = offline_solver(args) if args.offline else None
    frame = None
    if args.frame:
        try:
            frame = read_frame(args.frame)
        except Exception as exc:
            print(f"st16-ground: {args.frame}: {exc}", file=sys.stderr)
            return 2
    t0 = time.perf_counter()
    if solver is not None:
        rec = solver.solve(frame)
    else:
        rec = _solve_on_device(args, frame)
    rec["exchange_s"] = time.perf_counter() - t0
    rec["solve_s"] = rec["timings_s"].get("total")
    rec["time_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    rec["frame"] = Path(args.frame).name if args.frame else "(capture)"
    if args.frame:
        rec.update(score(rec, Truth.for_frame(args.frame, frame)))
    ResultsLog(args.out).append(rec)
    _print_record(rec, args.json)
    if rec["q_icrs_to_sensor"] is None:
        return 3
    return 0 if rec["status"] == "OK" else 1  # an attitude that is not high confidence: use with care


def _solve_on_device(args, frame):
    from ground.analysis.replay import LinkSolver
    from ground.cli.link import client_kwargs

    bar = frame is not None and progress_on(args)  # a 10 MB frame is 15 min at 115 200 baud
    solver = LinkSolver(args.port, reconnect_timeout=args.reconnect_timeout, upload_progress=bar, **client_kwargs(args))
    try:  # a NACK (exit 5) or a device that does not come back (exit 4) ends in ground.cli.main.main
        return solver.solve(frame)  # a device that stops answering: warnings through logging
    finally:
        solver.close()


def register(sub) -> None:
    from ground.cli.offline_options import add_camera_options, add_params_option

    p = sub.add_parser("solve", help="command one lost-in-space solve (upload --frame, or capture)")
    p.add_argument("--frame", help="frame file to upload and solve (DNG/raw, FITS, TIFF, PNG/JPEG, .npy)")
    p.add_argument(
        "--offline", action="store_true", help="solve --frame in-process (needs --catalog) instead of on the device"
    )
    p.add_argument("--catalog", help="catalog image for --offline")
    add_camera_options(p)
    add_params_option(p)
    p.add_argument("--out", default=DEFAULT_RESULTS, help="results log directory (JSONL + CSV)")
    p.add_argument("--reconnect-timeout", type=float, default=30.0, help="wait this long for a silent device, s")
    p.set_defaults(func=_solve)
