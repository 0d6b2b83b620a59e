"""``st16-ground camera calibrate``: fit the camera model to real sky frames.

Stars are identified with the device pipeline over a focal-length search around the initial
camera, then the camera parameters (``--fit``) and one attitude per frame are fitted to them
(``ground.calibration.optics``). Writes the camera model JSON the device takes (``--camera``).
"""

from __future__ import annotations

import sys
from pathlib import Path

from ground import json_text
from ground.arg_types import InputError, output_file, progress_on
from ground.atomic_write import write_text


def _calibrate(args) -> int:
    import numpy as np

    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_from_image
    from firmware_model.device.cli import load_camera
    from firmware_model.pipeline.frame_readers import read_frame
    from firmware_model.pipeline.solve_types import PipelineParams, with_psf_sigma
    from ground.calibration.optics import calibrate_from_frames

    if args.camera:
        initial = load_camera(args.camera)
    elif args.focal_mm and args.pixel_um:
        first = read_frame(args.frames[0])
        initial = CameraModel.from_focal(first.width, first.height, args.focal_mm, args.pixel_um)
    else:
        raise InputError("give --camera JSON or both --focal-mm and --pixel-um")
    frames = [read_frame(p) for p in args.frames]
    params = PipelineParams() if args.psf_sigma is None else with_psf_sigma(PipelineParams(), args.psf_sigma)
    catalog = catalog_from_image(Path(args.catalog).read_bytes())
    try:
        cal = calibrate_from_frames(
            frames,
            catalog,
            initial,
            params,
            fit=tuple(args.fit.split(",")),
            focal_search=args.focal_search,
            progress=progress_on(args),
        )
    except ValueError as exc:
        print(f"st16-ground: {exc}", file=sys.stderr)
        return 1
    cam = cal.result.camera
    write_text(
        args.output,
        json_text.dumps({k: float(v) if isinstance(v, float) else v for k, v in cam.to_dict().items()}, indent=2),
    )
    report = {
        "camera": args.output,
        "focal_scale_searched": cal.focal_scale,
        "residual_rms_px": cal.result.residual_rms_px,
        "stars": cal.result.n_observations,
        "sigmas": cal.result.sigmas,
        "frames_solved": int(sum(cal.solved)),
        "frames": len(frames),
        "fov_major_deg": float(2 * np.degrees(cam.fov_half_angle_major)),
        "fov_minor_deg": float(2 * np.degrees(cam.fov_half_angle_minor)),
    }
    if args.json:
        print(json_text.dumps(report))
    else:
        from ground.link.commands import render

        print(render(report))
    return 0


def register(sub) -> None:
    cam = sub.add_parser("camera", help="camera model calibration from real frames")
    csub = cam.add_subparsers(dest="camera_command", metavar="ACTION")
    csub.required = True
    p = csub.add_parser("calibrate", help="identify stars in sky frames and fit the camera model")
    p.add_argument("frames", nargs="+", help="frame files (any supported format)")
    p.add_argument("--catalog", required=True, help="catalog image covering the field of view")
    p.add_argument("--camera", help="initial camera model JSON")
    p.add_argument("--focal-mm", type=float, help="nominal focal length (instead of --camera)")
    p.add_argument("--pixel-um", type=float, help="pixel pitch (instead of --camera)")
    p.add_argument(
        "--psf-sigma", type=float, help="PSF Gaussian sigma, px (an override: measured per frame by default)"
    )
    p.add_argument("--fit", default="f,k1", help="parameters to fit: any of f,cx,cy,k1,k2,k3,p1,p2")
    p.add_argument("--focal-search", type=float, default=0.05, help="relative focal-length search half-range")
    p.add_argument("-o", "--output", type=output_file, default="camera.json", help="camera model JSON to write")
    p.set_defaults(func=_calibrate)
