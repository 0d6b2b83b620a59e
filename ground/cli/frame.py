"""``st16-ground frame ...``: render simulated raw frames with truth, inspect frames.

* ``frame render --out F.dng [sky] [camera] [detector]``: writes the frame (.dng, .fits or
  .npy) and ``F.truth.json`` beside it. The sky is either an on-board catalog image
  (``--catalog IMAGE --ra --dec --roll``, degrees) or ``--random N`` synthetic stars.
* ``frame inspect FRAME [--plot PNG] [--truth JSON] [--params FILE]``: the measured PSF, detections (x, y, rg, bg, flags,
  fit residual) and the time per stage; ``--json`` (global) for machine output. With a
  truth file (default ``FRAME.truth.json`` when present) each detection is matched to the
  nearest true star and the errors are reported.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import NoReturn

from ground import json_text
from ground.arg_types import ANGLE_DEG, DEC_DEG, RA_DEG, SECONDS, SEED, SENSOR_PX, InputError, output_file, ranged

log = logging.getLogger(__name__)


def _fail(message: str) -> NoReturn:
    """Bad input: one line, exit 2 (``ground.cli.main``; under ``--json`` its error document too)."""
    raise InputError(message)


def register(sub) -> None:
    frame = sub.add_parser("frame", help="render simulated raw frames, inspect frames")
    fsub = frame.add_subparsers(dest="frame_command", metavar="ACTION")
    fsub.required = True

    p = fsub.add_parser("render", help="render a raw frame with truth from a catalog or random stars")
    p.add_argument(
        "-o", "--output", "--out", dest="out", type=output_file, required=True, help="output frame: .dng, .fits or .npy"
    )
    sky = p.add_argument_group("sky")
    sky.add_argument("--catalog", help="on-board catalog image (st16-ground catalog build)")
    sky.add_argument("--ra", type=RA_DEG, default=83.8, help="boresight RA, deg")
    sky.add_argument("--dec", type=DEC_DEG, default=-5.4, help="boresight Dec, deg")
    sky.add_argument("--roll", type=ANGLE_DEG, default=0.0, help="roll, deg")
    sky.add_argument(
        "--random",
        type=ranged(int, 0, 100_000, "a star count"),
        default=20,
        help="synthetic stars when no --catalog is given",
    )
    sky.add_argument(
        "--mag-range",
        type=float,
        nargs=2,
        default=(2.0, 6.0),
        metavar=("BRIGHT", "FAINT"),
        help="V magnitudes of the random stars",
    )
    cam = p.add_argument_group("camera (default: Enright & McVittie reference design)")
    cam.add_argument("--camera", help="CameraModel JSON (to_dict keys)")
    cam.add_argument("--width", type=SENSOR_PX, help="sensor width, px (default: the reference design's)")
    cam.add_argument("--height", type=SENSOR_PX, help="sensor height, px (default: the reference design's)")
    cam.add_argument("--fov", type=float, help="half field of view on the minor axis, deg (default: 7.5)")
    det = p.add_argument_group("detector (defaults in docs/pipeline.md)")
    det.add_argument("--pattern", default="RGGB", help="RGGB, BGGR, GRBG, GBRG or MONO")
    det.add_argument("--exposure", type=SECONDS, default=0.1, help="s")
    det.add_argument("--psf-sigma", type=float, default=1.0, help="Gaussian PSF sigma, px")
    det.add_argument("--defocus", type=float, default=0.0, help="defocus disc radius, px")
    det.add_argument("--read-noise", type=float, default=3.0, help="e-")
    det.add_argument("--dark", type=float, default=25.0, help="dark current, e-/s")
    det.add_argument("--sky", type=float, default=10.0, help="sky background, e-/s per pixel")
    det.add_argument("--hot-fraction", type=float, default=2e-5, help="fraction of hot pixels")
    det.add_argument("--gain", type=float, default=1.6, help="e-/DN")
    det.add_argument("--bits", type=int, default=12, help="ADC bit depth")
    det.add_argument("--black", type=float, default=64.0, help="black level, DN")
    det.add_argument("--sensor-seed", type=int, default=1, help="fixed-pattern noise seed")
    p.add_argument("--cosmics", type=int, default=0, help="number of cosmic-ray hits")
    p.add_argument("--satellite", action="store_true", help="add one satellite streak")
    p.add_argument("--planet", action="store_true", help="add one bright planet-like source")
    p.add_argument("--seed", type=SEED, default=0, help="noise and random-star seed")
    p.add_argument("--timestamp", help="UTC ISO-8601 time to record")
    p.set_defaults(func=cmd_render)

    p = fsub.add_parser("inspect", help="detect and fit stars in a frame; list them with timings")
    p.add_argument("frame", help="frame file: DNG/raw, FITS, TIFF, PNG/JPEG, .npy")
    p.add_argument("--camera", help="CameraModel JSON for unit vectors (default: the frame's own, if any)")
    p.add_argument("--params", help="parameter set JSON, the schema of the device's slot 2 (params upload)")
    p.add_argument("--truth", help="truth JSON (default FRAME.truth.json when present)")
    p.add_argument("--plot", help="write an overlay PNG here")
    p.add_argument("--k-sigma", type=float, help="detection threshold (default: the --params set's, else the device's)")
    p.add_argument(
        "--max-stars",
        type=int,
        help="candidates kept, brightest first (default: the --params set's, else the device's)",
    )
    p.add_argument(
        "--psf-sigma", type=float, help="PSF Gaussian sigma, px (an override: measured on the frame by default)"
    )
    p.add_argument("--gain", type=float, help="e-/DN for fit weights (default: the --params set's, else the device's)")
    p.set_defaults(func=cmd_inspect)


def _camera_from_args(args):
    from firmware_model.camera import CameraModel
    from firmware_model.device.cli import load_camera

    if args.camera:
        try:  # a FIFO refused, the size and the JSON depth bounded (one line naming the file)
            return load_camera(args.camera)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    ref = CameraModel.reference_design()
    if args.width or args.height or args.fov:
        return CameraModel.from_fov(args.width or ref.width, args.height or ref.height, args.fov or 7.5)
    return ref


def cmd_render(args) -> int:
    import numpy as np

    from firmware_model.reference_frames import attitude_from_radec_roll
    from ground.sim.frame_writer import truth_path_for, write_rendered
    from ground.sim.sensor_sim import DetectorModel, FalseObject, Stars, random_star_field, render_frame

    try:
        camera = _camera_from_args(args)
        detector = DetectorModel(
            pattern=args.pattern,
            exposure_s=args.exposure,
            psf_sigma_px=args.psf_sigma,
            defocus_radius_px=args.defocus,
            read_noise_e=args.read_noise,
            dark_e_per_s=args.dark,
            sky_e_per_s=args.sky,
            hot_pixel_fraction=args.hot_fraction,
            gain_e_per_dn=args.gain,
            bit_depth=args.bits,
            black_level_dn=args.black,
            sensor_seed=args.sensor_seed,
        )
    except (ValueError, OSError, json.JSONDecodeError) as exc:
        return _fail(str(exc))
    attitude = attitude_from_radec_roll(*np.radians([args.ra, args.dec, args.roll]))
    if args.catalog:
        from firmware_model.catalog.image_io import catalog_from_image

        try:
            cat = catalog_from_image(Path(args.catalog).read_bytes())
        except (OSError, ValueError) as exc:
            return _fail(f"cannot load catalog {args.catalog}: {exc}")
        if not cat.has_colour:
            return _fail("catalog has no colour ratios; build it with colour")
        stars = Stars(cat.star_id, cat.vec, cat.mag, cat.rg, cat.bg)
    else:
        stars = random_star_field(camera, attitude, args.random, tuple(args.mag_range), seed=args.seed)
    rng = np.random.default_rng(args.seed + 7919)
    objs = []
    for _ in range(args.cosmics):
        cx, cy = rng.uniform([0, 0], [camera.width - 1, camera.height - 1])
        objs.append(FalseObject("cosmic", cx, cy, rng.uniform(500, 5000)))
    if args.satellite:
        x, y = rng.uniform([0, 0], [camera.width - 1, camera.height - 1])
        ang = rng.uniform(0, np.pi)
        objs.append(FalseObject("satellite", x, y, 2e4, x2=x + 300 * np.cos(ang), y2=y + 300 * np.sin(ang)))
    if args.planet:
        x, y = rng.uniform([50, 50], [camera.width - 51, camera.height - 51])
        objs.append(FalseObject("planet", x, y, 2e5, rg=1.3, bg=0.6))
    try:
        res = render_frame(
            stars, attitude, camera, detector, seed=args.seed, false_objects=objs, timestamp=args.timestamp
        )
        out = write_rendered(res, args.out)
    except (ValueError, OSError) as exc:
        return _fail(str(exc))
    truth_file = truth_path_for(out)
    summary = {
        "frame": str(out),
        "truth": str(truth_file),
        "stars_in_frame": len(res.truth["stars"]),
        "false_objects": len(objs),
        "pattern": res.frame.pattern,
        "size": [res.frame.width, res.frame.height],
    }
    print(
        json_text.dumps(summary)
        if args.json
        else f"wrote {out} ({res.frame.width} x {res.frame.height} {res.frame.pattern}, "
        f"{summary['stars_in_frame']} stars, {len(objs)} false objects) and {truth_file}"
    )
    return 0


def _match_truth(stars, truth: dict) -> list[dict | None]:
    import numpy as np

    ts = truth.get("stars", [])
    if not ts:
        return [None] * len(stars)
    tx = np.array([s["x"] for s in ts])
    ty = np.array([s["y"] for s in ts])
    out: list[dict | None] = []
    for i in range(len(stars)):
        d = np.hypot(tx - stars.x[i], ty - stars.y[i])
        j = int(np.argmin(d))
        if d[j] > 3.0:
            out.append(None)
            continue
        t = ts[j]
        out.append(
            {
                "id": t["id"],
                "vmag": t["vmag"],
                "dx": float(stars.x[i] - t["x"]),
                "dy": float(stars.y[i] - t["y"]),
                "drg": float(stars.rg[i] - t["rg"]),
                "dbg": float(stars.bg[i] - t["bg"]),
            }
        )
    return out


def _fmt(value, spec: str) -> str:
    return "nan" if value is None else format(value, spec)


def cmd_inspect(args) -> int:
    from dataclasses import replace

    import numpy as np

    from firmware_model import user_files
    from firmware_model.device.cli import load_camera
    from firmware_model.pipeline.extract import PSF_SIGMA_RANGE_PX, extract_stars
    from firmware_model.pipeline.frame_readers import FrameReadError, read_frame
    from ground.cli.offline_options import load_params
    from ground.sim.frame_writer import truth_path_for

    try:
        frame = read_frame(args.frame)
        camera = load_camera(args.camera) if args.camera else None
    except (FrameReadError, ValueError, OSError) as exc:
        return _fail(str(exc))
    log.debug("%s: %d x %d %s frame", args.frame, frame.width, frame.height, frame.pattern)

    lo, hi = PSF_SIGMA_RANGE_PX
    if args.psf_sigma is not None and not lo <= args.psf_sigma < hi:
        return _fail(f"--psf-sigma must be in [{lo:g}, {hi:g}) px, got {args.psf_sigma}")

    base = load_params(args.params).extract

    def given(value, default):
        return default if value is None else value

    params = replace(
        base,
        detect=replace(
            base.detect,
            k_sigma=given(args.k_sigma, base.detect.k_sigma),
            max_candidates=given(args.max_stars, base.detect.max_candidates),
        ),
        fit=replace(base.fit, gain_e_per_dn=given(args.gain, base.fit.gain_e_per_dn)),
        psf_sigma_px=given(args.psf_sigma, base.psf_sigma_px),
    )
    try:
        stars = extract_stars(frame, camera, params)
    except ValueError as exc:
        return _fail(str(exc))
    truth, matches = None, None
    tpath = Path(args.truth) if args.truth else truth_path_for(args.frame)
    if args.truth or tpath.is_file():
        try:
            truth = user_files.load_json_file(tpath, max_bytes=64 << 20)
            if not isinstance(truth, dict):
                raise ValueError("not a JSON object")
            matches = _match_truth(stars, truth)
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:  # a star without "y" too
            why = f"{type(exc).__name__}: {exc}" if isinstance(exc, (KeyError, TypeError, AttributeError)) else exc
            if isinstance(exc, user_files.UserFileError):  # it names the file: said once
                why = str(exc).removeprefix(f"{tpath}: ")
            if args.truth:  # asked for: an error
                return _fail(f"--truth {args.truth}: not a readable truth file ({why})")
            log.warning("st16-ground: %s is not a readable truth file (%s); ignored", tpath.name, why)
            truth, matches = None, None
    records = stars.to_records()
    if matches is not None:
        for rec, m in zip(records, matches):
            rec["truth"] = m
        log.debug(
            "%s: truth for %d of %d stars", tpath.name, sum(r.get("truth") is not None for r in records), len(records)
        )
    timings_ms = {k.replace("_s", "_ms"): round(v * 1e3, 3) for k, v in stars.timings.items()}
    psf = {
        "sigma_px": stars.psf_sigma_px,
        "measured_px": stars.psf_measured_px if np.isfinite(stars.psf_measured_px) else None,
        "source": stars.psf_source,
        "passes": stars.psf_passes,
    }
    report = {
        "frame": str(args.frame),
        "size": [frame.width, frame.height],
        "pattern": frame.pattern,
        "n_stars": len(stars),
        "reason": stars.reason,
        "psf": psf,
        "timings_ms": timings_ms,
        "stars": records,
    }
    if args.plot:
        from ground.analysis.frame_plot import plot_detections

        report["plot"] = str(plot_detections(frame, stars, args.plot, truth))
    if args.json:
        print(json_text.dumps(report, indent=1))
        return 0
    print(
        f"{args.frame}: {frame.width} x {frame.height} {frame.pattern}, {len(stars)} stars"
        + (f" ({stars.reason})" if stars.reason else "")
    )
    print(f"PSF sigma {stars.psf_sigma_px:.3f} px ({stars.psf_source}, {stars.psf_passes} pass(es))")
    print("timings ms: " + ", ".join(f"{k} {v:.1f}" for k, v in timings_ms.items()))
    print(f"{'#':>3} {'x':>9} {'y':>9} {'rg':>6} {'bg':>6} {'snr':>7} {'chi2r':>6}  flags")
    for i, r in enumerate(records):
        print(
            f"{i:>3} {_fmt(r['x'], '9.3f')} {_fmt(r['y'], '9.3f')} {_fmt(r['rg'], '6.3f')} {_fmt(r['bg'], '6.3f')} "
            f"{_fmt(r['snr'], '7.1f')} {_fmt(r['reduced_chi2'], '6.2f')}  {','.join(r['flag_names']) or '-'}"
        )
    if "plot" in report:
        print(f"overlay: {report['plot']}")
    return 0
