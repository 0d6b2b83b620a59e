"""``st16-ground`` lost-in-space commanding: solve, replay, table5, colour fit, params, demo.

* ``solve [--frame FILE]``: upload the frame (or let the device capture), GO, print the decoded
  result (``--json`` for the full record) and append it to the results log.
* ``replay DIR``: every frame of a directory over the link (or ``--offline`` in-process),
  scored against ``NAME.truth.json`` when present; log, summary and plots in ``--out``.
* ``table5 DIR``: Enright & McVittie table 5 (basic / ideal colour / chromatic / both) on frames with truth.
* ``colour fit RESULTS.jsonl``: the eq. 24 colour correction from matched stars of a run.
* ``params upload FILE``: send a device parameter set (JSON, slot 2), e.g. a colour correction.
* ``demo``: the end-to-end demonstration (README's first command).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from ground import json_text
from ground.arg_types import InputError, output_file, progress_on
from ground.atomic_write import write_text
from protocol.commands import Slot

DEFAULT_RESULTS = "st16-results"


def _load_catalog(path):
    from firmware_model.catalog.image_io import catalog_from_image

    return catalog_from_image(Path(path).read_bytes())


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
    solver = _offline_solver(args) if args.offline else None
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


def _offline_solver(args):
    """The in-process solver the offline options describe (camera, catalog, parameters, site)."""
    from ground.analysis.replay import OfflineSolver
    from ground.cli.offline_options import camera_for_frames, load_params

    if not args.catalog:
        raise InputError("the offline solver needs --catalog IMAGE")
    camera, params = camera_for_frames(args), load_params(args.params)
    site = None
    if getattr(args, "site", None):
        from ground.calibration.corrections import Site

        try:
            parts = [float(v) for v in args.site.split(",")]
            given = dict(zip(("lat_deg", "lon_deg", "height_m"), parts))  # a fourth value is ignored
            site = Site(**given, pressure_hpa=args.pressure, temperature_c=args.temperature)
        except (ValueError, TypeError):
            raise InputError(f"--site wants LAT,LON[,HEIGHT_M] in degrees/metres, got {args.site!r}") from None
    try:
        catalog = _load_catalog(args.catalog)
    except (OSError, ValueError) as exc:
        raise InputError(f"--catalog {args.catalog}: {exc}") from None
    return OfflineSolver(camera, catalog, params, site)


def _replay(args) -> int:
    from ground.analysis.replay import LinkSolver, replay
    from ground.cli.link import client_kwargs

    if args.offline:
        solver = _offline_solver(args)
    else:
        if not args.port:
            raise InputError("--port URL is required (or use --offline)")
        solver = LinkSolver(args.port, reconnect_timeout=args.reconnect_timeout, **client_kwargs(args))
    try:
        summary = replay(args.directory, solver, args.out, progress=progress_on(args), resume=args.resume)
    except (ValueError, TimeoutError) as exc:
        print(f"st16-ground: {exc}", file=sys.stderr)
        return 1
    finally:
        if isinstance(solver, LinkSolver):
            solver.close()
    summary["log"] = str(Path(args.out) / "results.jsonl")
    print(json_text.dumps(summary, indent=None if args.json else 2))
    return 0


def _table5(args) -> int:
    from firmware_model.device.cli import load_camera
    from firmware_model.pipeline.frame_readers import frame_files
    from ground.analysis.replay import TABLE5_MODES, table5

    out = table5(
        frame_files(args.directory), load_camera(args.camera), _load_catalog(args.catalog), progress=progress_on(args)
    )
    if args.json:
        print(json_text.dumps(out))
    else:
        print(f"{'corrections':<28}{'correct':>9}{'incorrect':>11}{'no match':>10}   ({out['frames']} frames)")
        for mode in TABLE5_MODES:
            c = out["table"][mode]
            print(f"{mode:<28}{c['correct']:>9}{c['incorrect']:>11}{c['no_match']:>10}")
    return 0


def _colour_fit(args) -> int:
    import numpy as np

    from ground.calibration.corrections import ColourCorrection

    cat = _load_catalog(args.catalog)
    index = {int(s): k for k, s in enumerate(cat.star_id)}
    obs, ref = [], []
    for line in Path(args.results).read_text().splitlines():
        if not line.strip():
            continue
        rec = json.loads(line)
        for s in rec.get("stars", []):
            k = index.get(s.get("catalog_id"))
            if k is not None and s.get("rg") is not None and s.get("bg") is not None:
                obs.append((s["rg"], s["bg"]))
                ref.append((float(cat.rg[k]), float(cat.bg[k])))
    try:
        fit = ColourCorrection.fit(np.array(obs).reshape(-1, 2), np.array(ref).reshape(-1, 2))
    except ValueError as exc:
        print(f"st16-ground: {exc}", file=sys.stderr)
        return 1
    fit.save(args.output)
    write_text(
        Path(args.output).with_suffix(".params.json"),
        json_text.dumps({"colour_correction": {"beta": [float(b) for b in fit.beta]}}, indent=2),
    )
    print(
        fit.to_json()
        if args.json
        else f"eq. 24 fit on {fit.n_used} stars ({fit.n_rejected} rejected): colour RMS {fit.rms_before:.3f} -> "
        f"{fit.rms_after:.3f}; wrote {args.output} and {Path(args.output).with_suffix('.params.json')}"
    )
    return 0


def _params_upload(args) -> int:
    from firmware_model.device.sensor_input import DeviceParams
    from ground.cli.link import open_client, report_error
    from ground.link.client import LinkError
    from protocol.commands import SlotRejected

    data = Path(args.file).read_bytes()
    try:
        DeviceParams.from_json(data)  # refuse locally what the device would refuse
    except SlotRejected as exc:
        print(f"st16-ground: {args.file}: {exc.message}", file=sys.stderr)
        return 2
    with open_client(args) as client:
        try:
            client.upload(Slot.PARAMS, data, progress=progress_on(args))
            info = client.slot_info(Slot.PARAMS)
        except LinkError as exc:
            return report_error(exc, args.json)
    print(json_text.dumps({"slot": 2, "active": info.active, "length": info.length, "crc32": f"0x{info.crc32:08X}"}))
    return 0


def _demo(args) -> int:
    from ground.cli.demo import run_demo

    return run_demo(args.out, n_frames=args.frames, seed=args.seed, progress=progress_on(args))


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

    p = sub.add_parser("replay", help="solve every frame of a directory and score against truth")
    p.add_argument("directory", help="frames (any supported format), with NAME.truth.json beside them to score")
    p.add_argument("--offline", action="store_true", help="run the pipeline in-process instead of over the link")
    p.add_argument("--catalog", help="catalog image for --offline")
    add_camera_options(p)
    add_params_option(p)
    p.add_argument("--site", help="with --offline: LAT,LON[,HEIGHT] (deg, m) of a ground site: correct refraction")
    p.add_argument("--pressure", type=float, default=1013.25, help="site pressure, hPa (with --site)")
    p.add_argument("--temperature", type=float, default=10.0, help="site temperature, deg C (with --site)")
    p.add_argument("--out", default=DEFAULT_RESULTS, help="output directory (log, summary, plots)")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run logged in --out (its frames are skipped); without it a --out that "
        "holds results is refused",
    )
    p.add_argument("--reconnect-timeout", type=float, default=120.0, help="wait this long for a silent device, s")
    p.set_defaults(func=_replay)

    p = sub.add_parser("table5", help="Enright & McVittie table 5 on frames with truth (offline)")
    p.add_argument("directory", help="frames with NAME.truth.json beside them")
    p.add_argument("--catalog", required=True, help="catalog image")
    p.add_argument("--camera", help="camera model JSON (default: the reference design)")
    p.set_defaults(func=_table5)

    colour = sub.add_parser("colour", help="field colour calibration (Enright & McVittie eq. 24)")
    csub = colour.add_subparsers(dest="colour_command", metavar="ACTION")
    csub.required = True
    p = csub.add_parser("fit", help="fit eq. 24 from the matched stars of a results log")
    p.add_argument("results", help="results.jsonl of a solve or replay run")
    p.add_argument("--catalog", required=True, help="catalog image the run used")
    p.add_argument(
        "-o",
        "--output",
        type=output_file,
        default="colour_correction.json",
        help="colour correction JSON to write (and its .params.json for params upload)",
    )
    p.set_defaults(func=_colour_fit)

    params = sub.add_parser("params", help="device parameter sets (slot 2)")
    psub = params.add_subparsers(dest="params_command", metavar="ACTION")
    psub.required = True
    p = psub.add_parser("upload", help="validate and upload a JSON parameter set")
    p.add_argument("file", help="parameter set JSON (e.g. colour fit's .params.json)")
    p.set_defaults(func=_params_upload)

    p = sub.add_parser("demo", help="end-to-end demo: device on a pty, catalog upload, solves over the link")
    p.add_argument("--out", default="st16-demo", help="output folder for logs, frames and plots")
    p.add_argument("--frames", type=int, default=6, help="frames to render and solve")
    p.add_argument("--seed", type=int, default=2026, help="render seed")
    p.set_defaults(func=_demo)
