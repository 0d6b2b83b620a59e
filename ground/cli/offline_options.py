"""Options shared by the offline paths (``replay --offline``, ``solve --offline``, ``frame inspect``,
``camera calibrate``): the camera model, the parameter set, the catalog and the in-process solver.

* Camera: ``--camera FILE`` (``CameraModel`` JSON), or ``--fov-deg F``, a pinhole camera built per
  frame from its size and horizontal field of view (the pipeline's focal-length search and
  optics fit absorb a few per cent of error and the lens distortion); default the reference design.
  Where the field of view is searched (``solve-file``, ``replay --offline``: ``add_camera_options(sky=True)``),
  ``--fov-deg F`` is a hint (the field within F / 1.4 to 1.4 F), ``--fov-range LO HI`` bounds the
  search, and neither solves blind over 5-60 deg, all against the whole-sky pattern database
  (``--database FILE``, default the user cache's; ``ground.catalog.sky_database``).
* ``--params FILE``: the device's slot-2 parameter set (``firmware_model.device.sensor_input.DeviceParams``,
  the file ``params upload`` sends), so an offline run and the device solve with the same settings.

Bad values fail before any work with an :class:`~ground.arg_types.InputError` (one line, exit 2).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_model.pipeline.field_of_view_limits import FOV_LIMITS_DEG
from ground.arg_types import InputError, progress_on

if TYPE_CHECKING:  # the pipeline imports scipy: only when a command runs
    from firmware_model.camera import CameraModel
    from firmware_model.pipeline.raw_frame import Frame
    from firmware_model.pipeline.solve_types import PipelineParams


_FOV_TEXT = "{:g}-{:g}".format(*FOV_LIMITS_DEG)


def add_camera_options(parser, sky: bool = False) -> None:
    """``--camera`` / ``--fov-deg``; with ``sky``, the field-of-view search's options too
    (``--fov-deg`` a hint, ``--fov-range``, ``--database``)."""
    group = parser.add_mutually_exclusive_group()
    if not sky:
        group.add_argument("--camera", help="camera model JSON (default: the reference design)")
        group.add_argument(
            "--fov-deg",
            type=float,
            help=f"horizontal field of view across the frame width, deg ({_FOV_TEXT}): a distortion-free pinhole "
            "camera per frame",
        )
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


def sky_field(args):
    """The ``sky_search.FieldRange`` of ``--fov-deg`` / ``--fov-range`` (blind without either),
    checked before any work (:class:`InputError`, exit 2)."""
    from firmware_model.pipeline.sky_search import FieldRange

    rng = getattr(args, "fov_range", None)
    try:
        return FieldRange.of(getattr(args, "fov_deg", None), tuple(rng) if rng else None)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def load_database(args):
    """The sky database ``--database`` names (or the user cache's, built once when missing)."""
    from ground.catalog.sky_database import DatabaseError, sky_database

    try:
        return sky_database(getattr(args, "database", None), progress=progress_on(args))
    except DatabaseError as exc:
        raise InputError(str(exc)) from None


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
    """Frame -> camera model from ``--camera`` / ``--fov-deg`` (checked here, before any work)."""
    from firmware_model.camera import CameraModel
    from firmware_model.device.cli import load_camera

    fov = getattr(args, "fov_deg", None)
    if fov is not None:
        lo, hi = FOV_LIMITS_DEG  # the range the option's help states (the sky search's: sky_field)
        if not lo <= fov <= hi:
            raise InputError(f"--fov-deg {fov:g} deg is outside {_FOV_TEXT} deg")
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
    """The in-process solver the offline options describe, its set-up seconds charged to its first
    record (``database``, ``catalog``; ``charge_setup``):

    * no ``--camera`` (nor ``--site``): the field of view searched (``SkySolver``) against the sky
      database, with ``--catalog`` for every frame or each found field's catalog;
    * ``--camera`` (or ``--site``) and ``--catalog``: the device's twin (``OfflineSolver``): that
      catalog and its own pattern index, as the device solves with them;
    * ``--camera`` alone: the camera's field catalog, matched against the sky database."""
    from ground.analysis.replay import OfflineSolver, SkySolver

    site = _site(args)
    sky = hasattr(args, "fov_range")
    fov = sky_field(args) if sky and not (args.camera or site) else None  # checked before any work
    if not sky and not args.catalog:
        raise InputError("the offline solver needs --catalog IMAGE")
    if fov is None and sky and site is not None and not (args.camera or args.fov_deg):
        raise InputError("--site needs a calibrated camera: --camera FILE (or an exact --fov-deg)")
    camera_of = camera_for_frames(args) if fov is None else None
    params = load_params(args.params)
    catalog, setup = None, {}
    if args.catalog:
        t0 = time.perf_counter()
        try:
            catalog = load_catalog(args.catalog)
        except (OSError, ValueError) as exc:
            raise InputError(f"--catalog {args.catalog}: {exc}") from None
        setup["catalog"] = time.perf_counter() - t0
    if not sky or (fov is None and catalog is not None):
        assert catalog is not None and camera_of is not None  # --catalog is required above
        solver: OfflineSolver | SkySolver = OfflineSolver(camera_of, catalog, params, site)
    else:
        db = load_database(args)
        setup["database"] = db.load_s
        if fov is not None:
            solver = SkySolver(fov, db, params, catalog=catalog)
        else:
            assert camera_of is not None
            solver = OfflineSolver(camera_of, lambda camera: _field_catalog(camera, db), params, site)
    solver.charge_setup(**setup)
    return solver


def _field_catalog(camera, db):
    """The field catalog of ``camera`` (``sky_catalog``); a camera too wide for one is bad input
    (one line, exit 2), not a traceback."""
    from ground.catalog.design import DesignError
    from ground.catalog.field_catalogs import sky_catalog

    try:
        return sky_catalog(camera, db)
    except DesignError as exc:
        raise InputError(
            f"the camera's field of view is too wide for a field catalog ({camera.width} x {camera.height} px: {exc})"
        ) from None


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
