"""Options shared by the offline paths (``replay --offline``, ``solve --offline``, ``solve-file``):
the camera model, the parameter set and the catalog, handed to ``ground.solver.in_process_solver``,
which chooses the route.

* ``--fov-deg F`` is a hint in every command that has it (the field within F / 1.4 to 1.4 F,
  searched: ``solve-file`` and ``replay``, ``add_camera_options(search=True)``), with
  ``--fov-range LO HI`` to bound the search and neither to solve blind over 5-60 deg, all against
  the whole-sky pattern database (``--database FILE``, default the user cache's;
  ``ground.catalog.sky_database``). ``--camera FILE`` (``CameraModel`` JSON) is a calibrated
  camera instead: no search.
* ``solve``, which never searches, takes ``--camera FILE`` or ``--pinhole-fov-deg F`` (a
  distortion-free pinhole camera per frame from its size and horizontal field of view; the
  pipeline's focal-length search and optics fit absorb a few per cent of error and the lens
  distortion); default the reference design. Its ``--fov-deg`` is refused in one line that names
  ``--pinhole-fov-deg``.
* ``--params FILE``: the device's slot-2 parameter set (``firmware_model.device.sensor_input.DeviceParams``,
  the file ``params upload`` sends), so an offline run and the device solve with the same settings.

Bad values fail before any work with an :class:`~ground.arg_types.InputError` (one line, exit 2).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_model.pipeline.field_of_view_limits import FOV_LIMITS_DEG
from ground.arg_types import InputError, progress_on

if TYPE_CHECKING:  # the pipeline imports scipy: only when a command runs
    from firmware_model.camera import CameraModel
    from firmware_model.pipeline.raw_frame import Frame
    from firmware_model.pipeline.solve_types import PipelineParams
    from ground.solver import InProcessSolver


_FOV_TEXT = "{:g}-{:g}".format(*FOV_LIMITS_DEG)


def add_camera_options(parser, search: bool = False) -> None:
    """``--camera`` / ``--pinhole-fov-deg``; with ``search``, ``--camera`` / ``--fov-deg`` (a hint) /
    ``--fov-range`` and ``--database`` instead (module docstring)."""
    group = parser.add_mutually_exclusive_group()
    if not search:
        group.add_argument("--camera", help="camera model JSON (default: the reference design)")
        group.add_argument(
            "--pinhole-fov-deg",
            type=float,
            metavar="F",
            help=f"horizontal field of view across the frame width, deg ({_FOV_TEXT}): a distortion-free pinhole "
            "camera per frame",
        )
        parser.add_argument("--fov-deg", type=_refused_fov_deg, help=argparse.SUPPRESS)
        return
    group.add_argument("--camera", help="calibrated camera model JSON: no field-of-view search")
    group.add_argument(
        "--fov-deg",
        type=float,
        help=f"horizontal field of view hint across the frame width, deg ({_FOV_TEXT}): the field is searched "
        "from F/1.4 to 1.4 F; without a hint or range the search is blind over 5-60 deg",
    )
    group.add_argument(
        "--fov-range",
        type=float,
        nargs=2,
        metavar=("LO", "HI"),
        help=f"horizontal fields of view to search, deg ({_FOV_TEXT})",
    )
    parser.add_argument(
        "--database", help="whole-sky pattern database file (default: the user cache's, built once if missing)"
    )


def _refused_fov_deg(value: str) -> float:
    """``--fov-deg`` where no field of view is searched: it means a hint everywhere else."""
    raise argparse.ArgumentTypeError(
        "--fov-deg is a field-of-view hint (solve-file, replay), and this command searches no field of view: "
        f"for an exact pinhole camera give --pinhole-fov-deg {value}"
    )


def add_params_option(parser) -> None:
    parser.add_argument("--params", help="parameter set JSON, the schema of the device's slot 2 (params upload)")


def load_params(path: str | None) -> PipelineParams:
    """Pipeline parameters from a slot-2 parameter file (defaults without one)."""
    from firmware_model.device.cli import load_params as load_device_params
    from firmware_model.pipeline.solve_types import PipelineParams

    if path is None:
        return PipelineParams()
    try:  # the device's own reading of --params: a FIFO refused, the size and the JSON depth bounded
        return load_device_params(path).apply(PipelineParams())
    except ValueError as exc:
        raise InputError(str(exc)) from None


def camera_for_frames(args) -> Callable[[Frame], CameraModel]:
    """Frame -> camera model from ``--camera`` / ``--pinhole-fov-deg`` (checked here, before any work)."""
    from firmware_model.camera import CameraModel
    from firmware_model.device.cli import load_camera

    fov = getattr(args, "pinhole_fov_deg", None)  # solve's option alone
    if fov is not None:
        lo, hi = FOV_LIMITS_DEG  # the range the option's help states
        if not lo <= fov <= hi:
            raise InputError(f"--pinhole-fov-deg {fov:g} deg is outside {_FOV_TEXT} deg")
        return lambda frame: CameraModel.from_horizontal_fov(frame.width, frame.height, fov)
    try:
        camera = load_camera(args.camera)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    return lambda frame: camera


def load_catalog(path):
    """The on-board catalog from a catalog image file (``--catalog``)."""
    from firmware_model.catalog.image_io import catalog_from_image

    try:
        return catalog_from_image(_catalog_path(path).read_bytes())
    except (OSError, ValueError) as exc:
        raise InputError(f"--catalog {path}: {exc}") from None


def _catalog_path(path) -> Path:
    """``--catalog``'s path, refused in one line naming the option when it is not a file."""
    from firmware_model import user_files

    why = user_files.problem(path)
    if why is not None:
        raise InputError(f"--catalog {path}: {why}")
    return Path(path)


def offline_solver(args, search: bool) -> InProcessSolver:
    """The in-process solver the offline options describe (``ground.solver.in_process_solver``
    chooses its route), options checked before any work. ``search``: the command searches the
    field of view (``add_camera_options(search=True)``): without ``--camera`` the field is searched;
    without it (``solve``) the camera is ``--camera``, ``--pinhole-fov-deg`` or the reference
    design, and ``--catalog`` is required (the device's twin)."""
    from ground.solver import in_process_solver

    if not search and not args.catalog:
        raise InputError("the offline solver needs --catalog IMAGE")
    site = _site(args)
    camera = camera_for_frames(args) if args.camera or not search else None
    params = load_params(args.params)
    return in_process_solver(
        camera=camera,
        catalog=_catalog_path(args.catalog) if args.catalog else None,
        fov_deg=args.fov_deg if search else None,
        fov_range=tuple(args.fov_range) if search and args.fov_range else None,
        database=args.database if search else None,
        params=params,
        site=site,
        progress=progress_on(args),
    )


def _site(args):
    """The ``--site`` of the offline refraction correction, or None."""
    if not getattr(args, "site", None):
        return None
    from ground.calibration.corrections import Site

    try:
        parts = [float(v) for v in args.site.split(",")]
        given = dict(zip(("lat_deg", "lon_deg", "height_m"), parts))  # a fourth value is ignored
        return Site(**given, pressure_hpa=args.pressure, temperature_c=args.temperature)
    except (ValueError, TypeError):
        raise InputError(f"--site wants LAT,LON[,HEIGHT_M] in degrees/metres, got {args.site!r}") from None
