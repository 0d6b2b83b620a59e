"""``st16-ground solve [--frame FILE]``: upload the frame (or let the device capture), GO, print the
decoded result (``--json`` for the full record) and append it to the results log; ``--offline``
solves in-process with the same pipeline and parameter file. ``--wcs FILE`` writes the solved
frame's FITS WCS (TAN-SIP, docs/wcs.md).

``st16-ground solve-file FRAME``: one image offline, no device and no log. Without ``--camera`` the
field of view is searched against the whole-sky pattern database (``--fov-deg F`` a hint,
``--fov-range LO HI`` bounds, neither: blind over 5-60 deg; ``ground.catalog.sky_database``, built once
into the user cache); a catalog for the field found is built when ``--catalog`` is not given (once
per field: kept in the user's cache directory); ``--wcs`` and ``--overlay`` (a PNG naming each
identified star) as wanted. Its ``timings_s`` count the kernels' loading (``compile``), the
database's loading (``database``) and the catalog's building or loading (``catalog``) in their
``total``: the first run after install compiles the kernels (said on stderr).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from ground import json_text
from ground.arg_types import InputError, output_file, progress_on
from ground.cli.link import mark_cut_reason, solve_exit_code
from ground.cli.offline_options import offline_solver

DEFAULT_RESULTS = "st16-results"


def _print_record(rec: dict, as_json: bool) -> None:
    from ground.link.solve_report import format_record

    print(json_text.dumps(rec) if as_json else format_record(rec))


def _solve(args) -> int:
    from firmware_model.pipeline.frame_readers import FrameReadError, read_frame
    from ground.analysis.replay import Truth, score
    from ground.analysis.results_log import ResultsLog

    if args.offline and not (args.catalog and args.frame):
        raise InputError("solve --offline needs --frame FILE and --catalog IMAGE")
    if not args.offline and not args.port:
        raise InputError("--port URL is required for solve (or use --offline)")
    solver = offline_solver(args, search=False) if args.offline else None
    frame = None
    if args.frame:
        try:
            frame = read_frame(args.frame)
        except FrameReadError as exc:  # it names the file
            raise InputError(str(exc)) from None
    t0 = time.perf_counter()
    if solver is not None:
        rec = solver.solve(frame).record
    else:
        rec = mark_cut_reason(_solve_on_device(args, frame))
    rec["exchange_s"] = time.perf_counter() - t0
    rec["solve_s"] = rec["timings_s"].get("total")
    rec["time_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    rec["frame"] = Path(args.frame).name if args.frame else "(capture)"
    if args.frame:
        rec.update(score(rec, Truth.for_frame(args.frame, frame)))
    ResultsLog(args.out).append(rec)
    written = {}
    if args.wcs and frame is not None:
        written["wcs"] = _write_wcs(args.wcs, rec, frame, user_camera(args, frame))
    _print_outcome(rec, written, args.json)
    return solve_exit_code(rec)


def _print_outcome(rec: dict, written: dict, as_json: bool) -> None:
    """The record, and the files written beside it (``written``: kind -> a dict with ``path``, or
    None when not written, which was said on stderr): under ``--json`` one document, the files in
    its ``"written"`` member; else the record's text and a ``KIND: PATH (...)`` line per file."""
    if as_json:
        print(json_text.dumps({**rec, "written": written} if written else rec))
        return
    _print_record(rec, False)
    for kind, info in written.items():
        if info is not None:
            note = f" ({info['note']})" if info.get("note") else ""
            print(f"{kind}: {info['path']}{note}")


def user_camera(args, frame):
    """The camera the options name for this frame, ``--camera`` or ``solve``'s ``--pinhole-fov-deg``
    (None: the device's, or the one the record's search found, which the record reports)."""
    if not (getattr(args, "camera", None) or getattr(args, "pinhole_fov_deg", None)):
        return None
    from ground.cli.offline_options import camera_for_frames

    return camera_for_frames(args)(frame)


def _write_wcs(path, rec: dict, frame, camera) -> dict | None:
    """Write the frame's WCS (its path and a note returned), or say in one line why there is none
    and return None (the record is kept either way)."""
    from ground.analysis.wcs import WcsError, record_wcs, write_wcs

    try:
        wcs, err = record_wcs(rec, frame.width, frame.height, camera)
        write_wcs(path, wcs)
    except WcsError as exc:
        print(f"st16-ground: --wcs {path} not written: {exc}", file=sys.stderr)
        return None
    projection = f"TAN{'-SIP' if wcs.sip is not None else ''}"
    return {
        "path": str(path),
        "projection": projection,
        "model_error_px": err,
        "note": f"{projection}, {err:.3f} px from the camera model",
    }


def _solve_file(args) -> int:
    from firmware_model.pipeline.frame_readers import FrameReadError, read_frame

    try:  # the input first: a directory or a bad file is one line before any database is built
        frame = read_frame(args.frame)
    except FrameReadError as exc:
        raise InputError(str(exc)) from None
    # options checked; the database, --catalog and the kernels loaded (a line and a bar when they compile)
    solver = offline_solver(args, search=True)
    solver.every_star = True  # no result record in between: list every detection
    rec = solver.solve(frame).record
    rec["frame"] = Path(args.frame).name
    camera = user_camera(args, frame)
    written = {}
    if args.wcs:
        written["wcs"] = _write_wcs(args.wcs, rec, frame, camera)
    if args.overlay:
        from ground.analysis.frame_plot import plot_identified
        from ground.optional import MissingExtra

        catalog = solver.catalog
        label = "HR" if getattr(catalog, "meta", {}).get("source") == "bsc5" else "HIP"
        try:
            written["overlay"] = {"path": str(plot_identified(frame, rec, args.overlay, label=label))}
        except MissingExtra as exc:  # the solve is kept: only the drawing is missing
            print(f"st16-ground: --overlay {args.overlay} not written: {exc}", file=sys.stderr)
            written["overlay"] = None
    _print_outcome(rec, written, args.json)
    return solve_exit_code(rec)


def _solve_on_device(args, frame):
    from ground.cli.link import client_kwargs
    from ground.link_solver import LinkSolver

    bar = frame is not None and progress_on(args)  # a 10 MB frame is 15 min at 115 200 baud
    solver = LinkSolver(args.port, reconnect_timeout=args.reconnect_timeout, upload_progress=bar, **client_kwargs(args))
    try:  # a NACK (exit 5) or a device that does not come back (exit 4) ends in ground.cli.main.main
        return solver.solve(frame).record  # a device that stops answering: warnings through logging
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
    p.add_argument(
        "-o", "--output", "--out", dest="out", default=DEFAULT_RESULTS, help="results log directory (JSONL + CSV)"
    )
    p.add_argument("--reconnect-timeout", type=float, default=30.0, help="wait this long for a silent device, s")
    p.add_argument("--wcs", type=output_file, help="write the solved frame's FITS WCS (TAN-SIP) here")
    p.set_defaults(func=_solve)

    p = sub.add_parser("solve-file", help="solve one image offline (no device): attitude, WCS, labelled overlay")
    p.add_argument("frame", help="image file (DNG/raw, FITS, TIFF, PNG/JPEG, .npy)")
    p.add_argument("--catalog", help="catalog image (default: built for the field found, kept in the user cache)")
    add_camera_options(p, search=True)
    add_params_option(p)
    p.add_argument("--wcs", type=output_file, help="write the FITS WCS (TAN-SIP) here")
    p.add_argument("--overlay", type=output_file, help="write a PNG with each identified star labelled")
    p.set_defaults(func=_solve_file)
