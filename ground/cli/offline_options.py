"""Options shared by the offline paths (``replay --offline``, ``solve --offline``, ``frame inspect``,
``camera calibrate``): the camera model, the parameter set, the catalog and the in-process solver.

* Camera: ``--camera FILE`` (``CameraModel`` JSON), or ``--fov-deg F``, a pinhole camera built per
  frame from its size and horizontal field of view (the pipeline's focal-length search and
  optics fit absorb a few per cent of error and the lens distortion); default the reference design.
* ``--params FILE``: the device's slot-2 parameter set (``firmware_model.device.sensor_input.DeviceParams``,
  the file ``params upload`` sends), so an offline run and the device solve with the same settings.

Bad values fail before any work with an :class:`~ground.arg_types.InputError` (one line, exit 2).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from ground.arg_types import InputError

if TYPE_CHECKING:  # the pipeline imports scipy: only when a command runs
    from firmware_model.camera import CameraModel
    from firmware_model.pipeline.raw_frame import Frame
    from firmware_model.pipeline.run import PipelineParams


def add_camera_options(parser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--camera", help="camera model JSON (default: the reference design)")
    group.add_argument(
        "--fov-deg",
        type=float,
        help="horizontal field of view across the frame width, deg: a distortion-free pinhole camera per frame",
    )


def add_params_option(parser) -> None:
    parser.add_argument("--params", help="parameter set JSON, the schema of the device's slot 2 (params upload)")


def load_params(path: str | None) -> PipelineParams:
    """Pipeline parameters from a slot-2 parameter file (defaults without one)."""
    from firmware_model.device.sensor_input import DeviceParams
    from firmware_model.pipeline.run import PipelineParams

    if path is None:
        return PipelineParams()
    try:
        return DeviceParams.load(path).apply(PipelineParams())
    except ValueError as exc:
        raise InputError(str(exc)) from None


def camera_for_frames(args) -> Callable[[Frame], CameraModel]:
    """Frame -> camera model from ``--camera`` / ``--fov-deg`` (checked here, before any work)."""
    from firmware_model.camera import CameraModel
    from firmware_model.device.cli import load_camera

    fov = getattr(args, "fov_deg", None)
    if fov is not None:
        if not 0.0 < fov < 180.0:
            raise InputError(f"--fov-deg must be in (0, 180) deg, got {fov}")
        return lambda frame: CameraModel.from_horizontal_fov(frame.width, frame.height, fov)
    try:
        camera = load_camera(args.camera)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    return lambda frame: camera


def load_catalog(path):
    """The on-board catalog from a catalog image file."""
    from firmware_model.catalog.image_io import catalog_from_image

    return catalog_from_image(Path(path).read_bytes())


def offline_solver(args):
    """The in-process solver the offline options describe (camera, catalog, parameters, site)."""
    from ground.analysis.replay import OfflineSolver

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
        catalog = load_catalog(args.catalog)
    except (OSError, ValueError) as exc:
        raise InputError(f"--catalog {args.catalog}: {exc}") from None
    return OfflineSolver(camera, catalog, params, site)
