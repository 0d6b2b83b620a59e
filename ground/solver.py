"""One in-process solve of a frame: the options turned into a route once, one answer back.

:func:`in_process_solver` is the one place that reads the options (a camera, a field of view or
range, a catalog, a sky database, the parameters, a site) and :func:`choose_route` the one place
that picks a :class:`Route` from them:

* ``TWIN``: a camera and a catalog, the device's own solve (that catalog's own pattern index);
* ``FIELD_CATALOG``: a camera alone, its field's catalog (``ground.catalog.field_catalogs``)
  matched against the whole-sky database's patterns;
* ``SKY_SEARCH``: no camera, the field of view searched (a hint, a range, or blind) against the
  whole-sky database, with the given catalog for every frame or each field found's own.

The pattern index a solve matches against is the solver's :attr:`InProcessSolver.patterns` (None:
the catalog's own), handed to the pipeline as an argument (``patterns=``); the catalog object a
solve is given is never written to.

Every solver, this module's and ``ground.link_solver.LinkSolver``, answers
``solve(frame, say=None)`` with one :class:`Solve`: the pipeline's output, the record, the field
of view search's report and the set-up seconds charged to it.
"""

from __future__ import annotations

import enum
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from ground.arg_types import InputError
from ground.kernels import warm_up_kernels

if TYPE_CHECKING:  # the pipeline imports scipy: only when a solve runs
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.onboard import OnboardCatalog
    from firmware_model.pipeline.raw_frame import Frame
    from firmware_model.pipeline.sky_run import SkyReport
    from firmware_model.pipeline.sky_search import FieldRange
    from firmware_model.pipeline.solve_types import PipelineOutput, PipelineParams

#: Centroid noise assumed for the approximate attitude before the refraction correction, px.
LOOSE_SIGMA_PX = 3.0


class Route(enum.Enum):
    """How a frame is solved in-process (module docstring)."""

    TWIN = "twin"
    FIELD_CATALOG = "field catalog"
    SKY_SEARCH = "sky search"


class OptionsError(InputError, ValueError):
    """Solve options that contradict each other or cannot be used, said in one line (``st16-ground``
    prints it and exits 2; from Python it is a ValueError)."""


def choose_route(camera: bool, catalog: bool, field_of_view: bool, site: bool) -> Route:
    """The route for the options given (each flag: that option was given); contradictions raise
    :class:`OptionsError`."""
    if camera and field_of_view:
        raise OptionsError(
            "give a calibrated camera or a field of view (a hint or a range), not both: the field of view is searched"
        )
    if site and not camera:
        raise OptionsError(
            "the refraction correction at a site needs a calibrated camera (a camera model, --camera FILE), "
            "not a field-of-view search"
        )
    if camera:
        return Route.TWIN if catalog else Route.FIELD_CATALOG
    return Route.SKY_SEARCH


@dataclass
class Solve:
    """One frame's answer. ``record``: the result record (``st16-ground solve --json``'s fields);
    ``output``: the pipeline's output it was made from (None from a device); ``report``: the field
    of view search's (``SKY_SEARCH`` only, also the record's ``sky`` block); ``setup_s``: set-up
    seconds this solve paid before its frame, s (in the record's ``timings_s``); ``camera``: the
    camera the answer was found with, before the optics fit (None: the device's, or none found)."""

    record: dict[str, Any]
    output: PipelineOutput | None = None
    report: SkyReport | None = None
    setup_s: dict[str, float] = field(default_factory=dict)
    camera: CameraModel | None = None


class Solver(Protocol):
    """What ``replay`` and the commands solve with: in-process or on a device."""

    def solve(self, frame: Frame | None, say: Callable[[str], object] | None = None) -> Solve: ...

    def close(self) -> None: ...


class InProcessSolver:
    """The device pipeline in-process on the route :func:`in_process_solver` chose.

    ``camera``: one model, or a function of the frame (a pinhole camera per frame size); ``catalog``:
    one catalog (None: each camera's field catalog); ``database``: the loaded
    ``ground.catalog.sky_database.SkyDatabase`` (``FIELD_CATALOG`` and ``SKY_SEARCH``); ``fov``: the
    ``sky_search.FieldRange`` searched (``SKY_SEARCH``).

    With a ``site`` (``ground.calibration.corrections.Site``) and a frame timestamp, star vectors are
    corrected for atmospheric refraction before the final match (Enright & McVittie section 5.3.2): a
    first solve (with a loose :data:`LOOSE_SIGMA_PX` noise model if the rigorous one fails) gives the
    approximate attitude, the vectors are corrected (``correct_refraction``) and the stars identified
    again at full rigour; the record then says ``"refraction": "corrected"``. With a site the camera
    is taken as calibrated (no optics search): on one low field, refraction and a focal-length error
    are nearly degenerate.

    The first solve reports the set-up seconds charged before it (:meth:`charge_setup`:
    :func:`in_process_solver` charges the catalog, the database and, for the process's first
    solver, the pipeline's modules and kernels as ``compile``) in its ``timings_s`` and their total.
    """

    #: list every detection in a record's ``stars``, not only the result record's brightest
    #: (``solve-file`` and ``solve_image``, whose record is not a device's)
    every_star: bool = False

    def __init__(
        self,
        route: Route,
        params: PipelineParams,
        camera: CameraModel | Callable[[Frame], CameraModel] | None = None,
        catalog: OnboardCatalog | None = None,
        database=None,
        fov: FieldRange | None = None,
        site=None,
    ):
        self.route, self.params, self.camera, self.catalog = route, params, camera, catalog
        self.database, self.fov, self.site = database, fov, site
        self._setup: dict[str, float] = {}

    @property
    def patterns(self):
        """The pattern index frames are matched against: the database's, or None (the catalog's own)."""
        return None if self.route is Route.TWIN else self.database.index

    def charge_setup(self, **seconds: float) -> None:
        """Add set-up seconds (``compile``, ``database``, ``catalog``) to the next solve's record."""
        for name, value in seconds.items():
            self._setup[name] = self._setup.get(name, 0.0) + value

    @property
    def setup_s(self) -> dict[str, float]:
        """The seconds charged and not yet reported."""
        return dict(self._setup)

    def camera_for(self, frame: Frame) -> CameraModel | None:
        """The camera the options give for ``frame`` (None on ``SKY_SEARCH``: the search finds it)."""
        from firmware_model.camera import CameraModel

        if self.camera is None or isinstance(self.camera, CameraModel):
            return self.camera
        return self.camera(frame)

    def close(self) -> None:
        """Nothing to release (the link solver's counterpart)."""

    def solve(self, frame: Frame | None, say: Callable[[str], object] | None = None) -> Solve:
        """Solve ``frame`` on this solver's route (``say`` is the link solver's; unused here)."""
        if frame is None:
            raise ValueError("an in-process solve needs a frame (a device can capture one)")
        from ground.link.solve_report import add_setup_stages, record_from_output

        setup, self._setup = self._setup, {}
        report, note = None, None
        if self.route is Route.SKY_SEARCH:
            from firmware_model.pipeline.sky_run import run_pipeline_sky

            assert self.fov is not None
            out, report = run_pipeline_sky(
                frame, self.fov, self.database.search, self._catalog_for, self.params, patterns=self.patterns
            )
            camera = out.camera
        else:
            camera = self.camera_for(frame)
            assert camera is not None
            out, note = self._run(frame, camera, self._catalog_for(camera))
        rec = add_setup_stages(record_from_output(out, every_star=self.every_star), **setup)
        if note is not None:
            rec["refraction"] = note
        if report is not None:
            rec["sky"] = report.to_dict()
        return Solve(rec, out, report, setup, camera)

    def _catalog_for(self, camera: CameraModel) -> OnboardCatalog:
        """The catalog a camera's frames are solved with (matched against :attr:`patterns`): the
        given one, else the camera's field catalog."""
        if self.catalog is not None:
            return self.catalog
        from ground.catalog.design import DesignError
        from ground.catalog.field_catalogs import catalog_for_camera

        try:
            return catalog_for_camera(camera)
        except DesignError as exc:
            raise OptionsError(
                f"the camera's field of view is too wide for a field catalog ({camera.width} x {camera.height} px: {exc})"
            ) from None

    def _run(self, frame: Frame, camera: CameraModel, catalog: OnboardCatalog) -> tuple[PipelineOutput, str | None]:
        """The pipeline on a known camera; with a site, refraction corrected (class docstring):
        the output and the record's ``refraction`` note (None without a site)."""
        from firmware_model.pipeline.run import identify_stars, run_pipeline

        if self.site is None:
            return run_pipeline(frame, camera, catalog, self.params, patterns=self.patterns), None
        # refraction squeezes a low field like a focal-length error: with a site, the camera is
        # taken as calibrated (no optics search), so the two are not confused
        params = replace(self.params, optics=None)
        out = run_pipeline(frame, camera, catalog, params, patterns=self.patterns)
        if out.stars is None or len(out.stars) < 2:
            return out, None
        if not frame.timestamp:
            raise ValueError("refraction correction needs the frame's timestamp")
        from astropy.time import Time

        from firmware_model.reference_frames import quat_to_matrix
        from ground.calibration.corrections import correct_refraction
        from protocol.result import Status

        approx = out
        if out.status is not Status.OK:
            # differential refraction can exceed the centroid noise: look for the approximate
            # attitude with a loose noise model (the final match below is made at full rigour); a
            # low-confidence first answer (e.g. a two-star last resort) is no approximation to trust
            approx = identify_stars(
                out.stars, camera, catalog, replace(params, fixed_sigma_px=LOOSE_SIGMA_PX), self.patterns
            )
        q_approx = approx.solution.q_icrs_to_sensor if approx.solution is not None else None
        if q_approx is None:  # (an OK answer always has its attitude)
            return out, "not corrected: no approximate attitude"
        vec = correct_refraction(
            out.stars.vectors, quat_to_matrix(q_approx), self.site, Time(frame.timestamp, scale="utc")
        )
        return identify_stars(replace(out.stars, vectors=vec), camera, catalog, params, self.patterns), "corrected"


def in_process_solver(
    *,
    camera: CameraModel | Callable[[Frame], CameraModel] | None = None,
    catalog: OnboardCatalog | str | Path | None = None,
    fov_deg: float | None = None,
    fov_range: tuple[float, float] | None = None,
    database: str | Path | None = None,
    params: PipelineParams | None = None,
    site=None,
    progress: bool = False,
) -> InProcessSolver:
    """The solver the options describe (module docstring), checked before any work (bad options
    raise :class:`OptionsError` in one line), with the catalog and the database it needs loaded
    and the pipeline's kernels (:func:`~ground.kernels.warm_up_kernels`, once per process: a line
    on stderr, and a bar with ``progress``, when they compile), their seconds charged to its first
    solve (``catalog``, ``database``, ``compile``: the modules and kernels loaded by this call). ``fov_deg`` is a hint (the field within
    ``fov_deg / 1.4`` to ``1.4 fov_deg``, horizontal, deg), ``fov_range`` bounds the search,
    neither with no camera solves blind; ``catalog`` an object or a catalog image path;
    ``database`` a file (None: the user cache's, built once, with a bar when ``progress``)."""
    start = time.perf_counter()
    from firmware_model.pipeline.sky_search import FieldRange
    from firmware_model.pipeline.solve_types import PipelineParams

    route = choose_route(
        camera is not None, catalog is not None, fov_deg is not None or fov_range is not None, site is not None
    )
    fov = None
    if route is Route.SKY_SEARCH:
        try:
            fov = FieldRange.of(fov_deg, fov_range)
        except ValueError as exc:
            raise OptionsError(str(exc)) from None
    setup: dict[str, float] = {}
    t0 = time.perf_counter()
    loaded = _catalog(catalog)
    if isinstance(catalog, (str, Path)):
        setup["catalog"] = time.perf_counter() - t0
    db = None
    if route is not Route.TWIN:
        from ground.catalog.sky_database import DatabaseError, sky_database

        try:
            db = sky_database(database, progress=progress)
        except DatabaseError as exc:
            raise OptionsError(str(exc)) from None
        setup["database"] = db.load_s
    solver = InProcessSolver(route, params or PipelineParams(), camera, loaded, db, fov, site)
    solver.charge_setup(**setup)
    if warm_up_kernels(progress=progress) > 0:  # the process's first solver: its modules and kernels
        solver.charge_setup(compile=time.perf_counter() - start - sum(setup.values()))
    return solver


def _catalog(catalog) -> OnboardCatalog | None:
    """The given catalog (an object, or a catalog image path read now); None when none was given."""
    if isinstance(catalog, (str, Path)):
        from firmware_model import user_files
        from firmware_model.catalog.image_io import catalog_from_image

        try:
            return catalog_from_image(user_files.check_file(catalog).read_bytes())
        except user_files.UserFileError as exc:  # missing, a directory, a FIFO (which would block the read)
            raise OptionsError(f"catalog {exc}") from None
        except (OSError, ValueError) as exc:
            raise OptionsError(f"catalog {catalog}: {exc}") from None
    return catalog
