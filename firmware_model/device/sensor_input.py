"""What the emulated device sees and solves: frame sources, the frame and parameter slots, and
the GO solver that runs the pipeline.

* Slot 1 holds an uploaded frame (``firmware_model.pipeline.raw_frame.frame_to_bytes`` format); slot 2 holds a
  JSON parameter set (:class:`DeviceParams`); both are validated on COMMIT with reason codes.
* :class:`FileFrames` replays frame files in order (``--frames DIR|GLOB``), optionally looping.
* Further capture sources register under the entry-point group ``st16.frame_sources``
  (``name = "module:factory"``, ``factory(spec: str, camera) -> callable(ctx)``); the project's
  own ``sky`` source renders exposures with the ground sensor simulator from an attitude schedule.
* :class:`PipelineSolver` is the ``Device`` solver: frame + catalog + parameters -> result fields.
"""

from __future__ import annotations

import glob
import importlib
import json
import logging
import math
import multiprocessing
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, replace
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import numpy as np

from firmware_model import user_files
from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.device import index_process
from firmware_model.device.clock import MAX_DRIFT_PPM, MAX_JITTER_US, ROLLOVER_US, ClockModel
from firmware_model.device.device import FrameUnavailable, SlotHandler, SolveContext
from firmware_model.ident.solver import Mode
from firmware_model.pipeline import scale_free
from firmware_model.pipeline.exclusion import ExclusionLimits, LastAttitude
from firmware_model.pipeline.extract import PSF_SIGMA_RANGE_PX
from firmware_model.pipeline.frame_readers import FrameReadError, frame_files, read_frame
from firmware_model.pipeline.raw_frame import Frame, frame_from_bytes
from firmware_model.pipeline.result_fields import result_fields
from firmware_model.pipeline.run import run_pipeline, warm_up
from firmware_model.pipeline.solve_types import PipelineParams, with_psf_sigma
from firmware_model.pipeline.tracking_run import Tracker, frame_time
from protocol.commands import GoBits, SlotRejected
from protocol.result import QuaternionOrder, Status

log = logging.getLogger(__name__)

#: The largest counted search budget a parameter file may set.
MAX_COUNT = 100_000

FRAME_SOURCE_GROUP = "st16.frame_sources"

#: Slot reason codes (ours, docs/ICD.md): catalog images use 0x0201-0x0212
#: (protocol.catalog_image), frames 0x0300-, parameter sets 0x0400-.
REJECT_FRAME_FORMAT = 0x0300
REJECT_FRAME_SIZE = 0x0301
REJECT_PARAMS_JSON = 0x0400
REJECT_PARAMS_KEY = 0x0401
REJECT_PARAMS_VALUE = 0x0402


def load_ephemerides() -> None:
    """Import the ephemerides (``planets``: astropy, slow to import), which a GO on a frame with a
    time needs (planet labels, the bright-body check): at start-up or at the frame's COMMIT, not
    inside the GO."""
    importlib.import_module("firmware_model.pipeline.planets")


def frame_slot_handler(camera: CameraModel) -> SlotHandler:
    """Slot 1: a serialised frame whose size matches the device's camera (one with a time loads
    the ephemerides when it is activated: :func:`load_ephemerides`)."""

    def load(data: bytes) -> Frame:
        try:
            frame = frame_from_bytes(data)
        except (ValueError, KeyError) as exc:
            raise SlotRejected(REJECT_FRAME_FORMAT, f"not a frame image: {exc}") from None
        if (frame.width, frame.height) != (camera.width, camera.height):
            raise SlotRejected(
                REJECT_FRAME_SIZE,
                f"frame is {frame.width} x {frame.height}, the device's camera is {camera.width} x {camera.height}",
            )
        if frame.timestamp:
            load_ephemerides()
        return frame

    def info(data: bytes, frame: Frame) -> bytes:
        return json.dumps(
            {
                "width": frame.width,
                "height": frame.height,
                "pattern": frame.pattern,
                "exposure_s": frame.exposure_s,
                "timestamp": frame.timestamp,
            }
        ).encode()

    def validate(data: bytes) -> None:
        load(data)

    return SlotHandler(validate, load, info)


#: The exclusion parameters (docs/ICD.md section 9): key -> (the ``ExclusionLimits`` field it sets,
#: largest value, unit); the smallest is 0.
EXCLUSION_KEYS = {
    "sun_exclusion_deg": ("sun_deg", 90.0, "deg"),
    "moon_exclusion_deg": ("moon_deg", 90.0, "deg"),
    "earth_exclusion_deg": ("earth_deg", 90.0, "deg"),
    "exclusion_memory_s": ("memory_s", 3600.0, "s"),
}


@dataclass(frozen=True)
class DeviceParams:
    """The slot-2 parameter set (JSON object; every key optional, unknown keys refused):

    ``mode`` "auto" | "colour" | "geometric"; ``sigma_rg``, ``sigma_bg`` colour noise for
    matching; ``centroid_sigma_px`` fixed centroid noise (else from the fit); the counted search
    budgets (docs/identification.md, "The solve plan"; integers, 1 to 100000): ``max_verifications``
    hypotheses verified per solve (``SolveParams.max_verifications``), ``max_seeds`` pattern seeds
    the optics search refines per frame and ``max_frame_verifications`` verifications after which
    a frame starts no further seed (``OpticsSearch``); ``psf_sigma_px`` the optics' PSF sigma, an override of the per-frame
    measurement (detection's hot-pixel tests, the fit's start); ``colour_correction`` eq. 24 as
    ``{"beta": [6 numbers]}``; ``focal_search`` relative half-range of the focal-length search
    for uncalibrated optics (0 to 0.2; 0 takes the camera as calibrated: no search, no optics
    fit); ``max_roll_sigma_deg`` the largest 1-sigma roll (deg, about the boresight) a
    high-confidence answer may have (default ``solver.MAX_ROLL_SIGMA``, 0.1 deg; larger: loosen);
    ``noise_probe_px`` the per-axis centroid noise beyond the announced one that a high-confidence
    answer's stars are looked for with before the frame's own noise is estimated (0 to 20 px,
    default 1; 0: trust the announced noise; ``strategy.adapt_noise``); ``quaternion_order``
    "scalar_first" (default) | "scalar_last": the element order of the standard result
    structure's quaternions (docs/ICD.md section 10.2; the offline paths, which report the
    extension's scalar-first quaternion, accept and ignore it); ``tracking`` true | false (not set:
    the device's default, ``PipelineSolver.tracking``): after a high-confidence fix, track the next frames from the last attitude and rate
    (``pipeline.tracking_run``; a GO without bit 0x01 ON drops the track, docs/ICD.md section 7;
    the offline paths ignore it); ``sun_exclusion_deg``, ``moon_exclusion_deg``,
    ``earth_exclusion_deg`` (deg, 0 to 90; 0 turns that check off; defaults 30, 25, 25:
    ``pipeline.exclusion.ExclusionLimits``, cited there) the bright-body exclusion angles from the
    boresight to the body's disc edge, and ``exclusion_memory_s`` (s, 0 to 3600, default 10; 0:
    none) the age up to which the device's last reported attitude decides for a frame without
    its own (the offline paths have no memory: they accept it and ignore it);
    ``cache_triangle_table`` true | false (default false: the control structure's bit, ICD page
    1-35924): a GO with bits 2 and 5 caches the triangle table, the first such GO slower and later
    ones faster under ``--timing realistic`` (``sequence.Timing``); ``clock_epoch_s`` (s, >= 0),
    ``clock_drift_ppm`` (+-1000) and ``clock_jitter_us`` (0 to 1000): the device clock's model
    (``clock.ClockModel``), read from ``st16-device --params`` at start (the clock is hardware: an
    uploaded set's clock keys are checked and take effect at the next start).
    The same file drives the offline paths (``--params``).
    """

    mode: Mode | None = None
    sigma_rg: float | None = None
    sigma_bg: float | None = None
    centroid_sigma_px: float | None = None
    max_verifications: int | None = None
    max_seeds: int | None = None
    max_frame_verifications: int | None = None
    psf_sigma_px: float | None = None
    colour_beta: tuple | None = None
    focal_search: float | None = None
    max_roll_sigma_deg: float | None = None
    noise_probe_px: float | None = None
    quaternion_order: QuaternionOrder | None = None
    tracking: bool | None = None
    sun_exclusion_deg: float | None = None
    moon_exclusion_deg: float | None = None
    earth_exclusion_deg: float | None = None
    exclusion_memory_s: float | None = None
    cache_triangle_table: bool | None = None
    clock_epoch_s: float | None = None
    clock_drift_ppm: float | None = None
    clock_jitter_us: float | None = None

    KEYS = (
        "mode",
        "sigma_rg",
        "sigma_bg",
        "centroid_sigma_px",
        "max_verifications",
        "max_seeds",
        "max_frame_verifications",
        "psf_sigma_px",
        "colour_correction",
        "focal_search",
        "max_roll_sigma_deg",
        "noise_probe_px",
        "quaternion_order",
        "tracking",
        *EXCLUSION_KEYS,
        "cache_triangle_table",
        "clock_epoch_s",
        "clock_drift_ppm",
        "clock_jitter_us",
    )

    @classmethod
    def load(cls, path) -> DeviceParams:
        """A parameter file (``st16-device --params``, the offline ``--params``); ValueError with a
        one-line reason for an unreadable or invalid one."""
        try:
            return cls.from_json(Path(path).read_bytes())
        except OSError as exc:
            raise ValueError(f"--params {path}: {exc.strerror or exc}") from None
        except SlotRejected as exc:
            raise ValueError(f"--params {path}: {exc.message}") from None

    @classmethod
    def from_json(cls, data: bytes) -> DeviceParams:
        try:
            obj = user_files.loads(data)  # its depth bounded: 100 000 brackets raised RecursionError
        except (UnicodeDecodeError, ValueError) as exc:
            raise SlotRejected(REJECT_PARAMS_JSON, f"parameter set is not UTF-8 JSON: {exc}") from None
        if not isinstance(obj, dict):
            raise SlotRejected(REJECT_PARAMS_JSON, "parameter set must be a JSON object")
        if "time_budget_s" in obj:
            raise SlotRejected(
                REJECT_PARAMS_KEY,
                "time_budget_s is gone: searches are bounded by counted work "
                "(max_verifications, max_seeds, max_frame_verifications), the same answer on any machine",
            )
        unknown = sorted(set(obj) - set(cls.KEYS))
        if unknown:
            raise SlotRejected(REJECT_PARAMS_KEY, f"unknown parameter(s) {unknown}; known: {list(cls.KEYS)}")

        def number(key, lo=0.0, hi=1e3, lo_open=True):
            v = obj.get(key)
            if v is None:
                return None
            if (
                not isinstance(v, (int, float))
                or isinstance(v, bool)
                or not (lo < v if lo_open else lo <= v)
                or not v < hi
            ):
                raise SlotRejected(
                    REJECT_PARAMS_VALUE,
                    f"{key} must be a number in {'(' if lo_open else '['}{lo:g}, {hi:g}), got {v!r}",
                )
            return float(v)

        def positive(key):
            return number(key)

        def closed(key, hi, unit):
            v = obj.get(key)
            if v is None:
                return None
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not 0 <= v <= hi:
                raise SlotRejected(REJECT_PARAMS_VALUE, f"{key} must be a number in [0, {hi:g}] {unit}, got {v!r}")
            return float(v)

        def count(key):
            v = obj.get(key)
            if v is None:
                return None
            if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= MAX_COUNT:
                raise SlotRejected(REJECT_PARAMS_VALUE, f"{key} must be a whole number in [1, {MAX_COUNT}], got {v!r}")
            return v

        mode = None
        if obj.get("mode") is not None:
            try:
                mode = Mode.parse(obj["mode"])
            except ValueError as exc:
                raise SlotRejected(REJECT_PARAMS_VALUE, str(exc)) from None
        beta = None
        if "colour_correction" in obj:
            cc = obj["colour_correction"]
            b = cc.get("beta") if isinstance(cc, dict) else None
            if (
                not isinstance(b, list)
                or len(b) != 6
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and abs(x) < 1e3 for x in b)
            ):
                raise SlotRejected(REJECT_PARAMS_VALUE, 'colour_correction must be {"beta": [6 finite numbers]}')
            beta = tuple(float(x) for x in b)
        for key in ("tracking", "cache_triangle_table"):
            if obj.get(key) is not None and not isinstance(obj[key], bool):
                raise SlotRejected(REJECT_PARAMS_VALUE, f"{key} must be true or false, got {obj[key]!r}")
        return cls(
            mode,
            positive("sigma_rg"),
            positive("sigma_bg"),
            positive("centroid_sigma_px"),
            count("max_verifications"),
            count("max_seeds"),
            count("max_frame_verifications"),
            number("psf_sigma_px", *PSF_SIGMA_RANGE_PX, lo_open=False),
            beta,
            number("focal_search", 0.0, 0.2, lo_open=False),
            number("max_roll_sigma_deg", 0.0, 180.0),
            number("noise_probe_px", 0.0, 20.0, lo_open=False),
            _quaternion_order(obj.get("quaternion_order")),
            obj.get("tracking"),
            cache_triangle_table=obj.get("cache_triangle_table"),
            clock_epoch_s=number("clock_epoch_s", 0.0, ROLLOVER_US / 1e6, lo_open=False),
            clock_drift_ppm=number("clock_drift_ppm", -MAX_DRIFT_PPM, MAX_DRIFT_PPM + 1e-9, lo_open=False),
            clock_jitter_us=number("clock_jitter_us", 0.0, MAX_JITTER_US + 1e-9, lo_open=False),
            **{key: closed(key, hi, unit) for key, (_, hi, unit) in EXCLUSION_KEYS.items()},
        )

    def clock_model(self, base: ClockModel) -> ClockModel:
        """``base`` with this set's clock keys."""
        keys = {"epoch_s": self.clock_epoch_s, "drift_ppm": self.clock_drift_ppm, "jitter_us": self.clock_jitter_us}
        return replace(base, **{k: v for k, v in keys.items() if v is not None})  # type: ignore[arg-type]

    def apply(self, base: PipelineParams) -> PipelineParams:
        solve = base.solve
        for key in ("mode", "sigma_rg", "sigma_bg", "max_verifications"):
            value = getattr(self, key)
            if value is not None:
                solve = replace(solve, **{key: value})
        if self.max_roll_sigma_deg is not None:
            solve = replace(solve, max_roll_sigma=math.radians(self.max_roll_sigma_deg))
        if self.noise_probe_px is not None:
            solve = replace(solve, noise_probe_px=self.noise_probe_px)
        if self.psf_sigma_px is not None:
            base = with_psf_sigma(base, self.psf_sigma_px)
        if self.focal_search == 0.0:
            base = replace(base, optics=None)
        elif base.optics is not None:
            optics: dict[str, Any] = {
                "focal_range": self.focal_search,
                "max_seeds": self.max_seeds,
                "max_verifications": self.max_frame_verifications,
            }
            base = replace(base, optics=replace(base.optics, **{k: v for k, v in optics.items() if v is not None}))
        exclusion = base.exclusion
        if any(getattr(self, key) is not None for key in EXCLUSION_KEYS):
            given = {field: getattr(self, key) for key, (field, _, _) in EXCLUSION_KEYS.items()}
            exclusion = replace(exclusion or ExclusionLimits(), **{f: v for f, v in given.items() if v is not None})
        return replace(
            base,
            solve=solve,
            exclusion=exclusion,
            colour_beta=self.colour_beta if self.colour_beta is not None else base.colour_beta,
            fixed_sigma_px=self.centroid_sigma_px if self.centroid_sigma_px is not None else base.fixed_sigma_px,
        )


def _quaternion_order(value: Any) -> QuaternionOrder | None:
    """The ``quaternion_order`` parameter (None: not set); SlotRejected for an unknown value."""
    if value is None:
        return None
    try:
        return QuaternionOrder(value)
    except ValueError:
        known = " or ".join(repr(o.value) for o in QuaternionOrder)
        raise SlotRejected(REJECT_PARAMS_VALUE, f"quaternion_order must be {known}, got {value!r}") from None


def params_slot_handler() -> SlotHandler:
    def validate(data: bytes) -> None:
        DeviceParams.from_json(data)

    def info(data: bytes, params: DeviceParams) -> bytes:
        return data

    return SlotHandler(validate, DeviceParams.from_json, info)


class FileFrames:
    """Capture source replaying frame files in name order (``DIR``: its files with frame suffixes,
    as ``replay`` lists them; or a glob), optionally looping.

    An unreadable file or one of the wrong size makes that capture fail with a reason (the
    sequence reports BAD_FRAME); the next GO takes the next file.
    """

    def __init__(self, spec: str, camera: CameraModel, loop: bool = False):
        paths = frame_files(spec) if Path(spec).is_dir() else sorted(Path(p) for p in glob.glob(spec))
        if not paths:
            raise ValueError(f"no frame files in {spec!r}")
        self.paths = paths
        self.camera = camera
        self.loop = loop
        self._next = 0
        self._lock = threading.Lock()

    def __call__(self, ctx: SolveContext) -> Frame | None:
        with self._lock:
            if self._next >= len(self.paths):
                if not self.loop:
                    return None
                self._next = 0
            path = self.paths[self._next]
            self._next += 1
        try:
            frame = read_frame(path)
        except (FrameReadError, OSError, ValueError) as exc:
            raise FrameUnavailable(exc.brief if isinstance(exc, FrameReadError) else f"{path.name}: {exc}") from None
        if (frame.width, frame.height) != (self.camera.width, self.camera.height):
            raise FrameUnavailable(
                f"{path.name} is {frame.width} x {frame.height}; the camera is "
                f"{self.camera.width} x {self.camera.height}"
            )
        return frame


def load_frame_source(name: str, spec: str, camera: CameraModel) -> Callable[[SolveContext], Any]:
    """A capture source registered under ``st16.frame_sources`` (e.g. ``sky``)."""
    found = {ep.name: ep for ep in entry_points(group=FRAME_SOURCE_GROUP)}
    if name not in found:
        raise ValueError(f"no frame source {name!r} installed (have: {sorted(found)})")
    return found[name].load()(spec, camera)


class PipelineSolver:
    """GO solver: runs :func:`~firmware_model.pipeline.run.run_pipeline` on the sequence's frame,
    or, with the parameter ``tracking`` (the slot-2 set's, else ``tracking`` here: ``--params``),
    the :class:`~firmware_model.pipeline.tracking_run.Tracker` that persists across sequences (a GO
    without bit 0x01 ON drops its track). It remembers the last attitude it reported (status OK,
    with the tracker's rate when tracked: :attr:`last`), which the bright-body exclusion check
    uses for a frame without an attitude of its own while younger than ``exclusion_memory_s``.

    The catalog's pattern index (``scale_free.catalog_patterns``, seconds once per catalog) is
    built by :meth:`prepare` when a catalog is activated: in this process while the device starts
    (``st16-device`` says ``listening`` after it), in another process once :meth:`serving` is
    called (a catalog COMMIT: a thread here would hold the GIL for much of the build and starve
    the link thread); a GO that comes while it is built waits for it. ``build_index`` builds it
    (``scale_free.pattern_index``'s arguments and answer; picklable: it runs in a spawned process).
    ``ephemerides``: load them now (:func:`load_ephemerides`); False when the capture source's
    frames carry no time (an uploaded frame with one loads them at its COMMIT).
    :meth:`serving` spawns that process, whose imports (``index_process`` and the build's own
    modules, not the rest of the pipeline) then run beside the link's first minutes rather than in
    the start-up or in the first COMMIT's build."""

    def __init__(
        self,
        camera: CameraModel,
        params: PipelineParams = PipelineParams(),
        tracking: bool = False,
        build_index: Callable[..., Any] = scale_free.pattern_index,
        ephemerides: bool = True,
    ):
        self.camera = camera
        self.params = params
        self.tracking = tracking
        self.tracker = Tracker()
        self.last: LastAttitude | None = None  #: the last attitude reported (OK), for the exclusion check
        self.build_index = build_index
        self._pool: ProcessPoolExecutor | None = None  # the index-building process
        self._serving = False
        self._lock = threading.Lock()
        # the pipeline's kernels load (numba, cached on disk; compiled once per install) and, unless
        # no frame is expected to carry a time, the ephemerides: at start-up, not inside the first GO
        if ephemerides:
            load_ephemerides()
        log.info("pipeline kernels ready in %.2f s", warm_up())

    def _builder(self) -> ProcessPoolExecutor:
        """The index-building process (one, kept: it waits for catalogs), spawned if need be."""
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                max_workers=1, mp_context=multiprocessing.get_context("spawn"), initializer=index_process.init
            )
            self._pool.submit(index_process.ready)
        return self._pool

    def serving(self) -> None:
        """From now on (the device serves its link) a catalog's index is built in another process,
        spawned now: it imports what a build runs while the device starts serving."""
        self._serving = True
        self._builder()

    def close(self) -> None:
        """End the index-building process now (a build under way, or its start-up imports, are
        abandoned: ``shutdown`` alone lets a busy worker run to the end of its task)."""
        if self._pool is not None:
            workers = list(getattr(self._pool, "_processes", {}).values())  # ProcessPoolExecutor's own
            self._pool.shutdown(wait=False, cancel_futures=True)
            for worker in workers:
                worker.terminate()
            self._pool = None

    def prepare(self, catalog: OnboardCatalog) -> None:
        """Build ``catalog``'s pattern index for the device's camera: here before :meth:`serving`,
        else in the index-building process (the GO that needs it waits for it: :meth:`index_ready`).
        Mono frames and the optics search both use it, whatever the parameters."""
        mrad = scale_free.pattern_field(self.camera)
        args = (np.ascontiguousarray(catalog.vec), np.ascontiguousarray(catalog.mag), catalog.n_pattern_stars, mrad)
        if not self._serving:
            t0 = time.perf_counter()
            scale_free.set_catalog_patterns(catalog, mrad, self.build_index(*args))
            log.info(
                "catalog pattern index ready in %.2f s (built, or loaded from the cache)", time.perf_counter() - t0
            )
            return
        try:
            future = self._builder().submit(self.build_index, *args)
        except (RuntimeError, OSError):  # the process died (BrokenProcessPool): a new one
            self._pool = None
            try:
                future = self._builder().submit(self.build_index, *args)
            except (RuntimeError, OSError) as exc:
                log.warning("catalog pattern index not built in another process (%s); the next GO builds it", exc)
                return
        with self._lock:
            catalog.__dict__["_pattern_build"] = (mrad, future)

    def index_ready(self, catalog: OnboardCatalog | None, timeout: float | None = None) -> bool:
        """Wait for ``catalog``'s index being built elsewhere (at most ``timeout`` s) and install it;
        True when no build is pending. A build that failed is logged and left to the solve
        (``catalog_patterns`` builds it in this process: the same index)."""
        if not isinstance(catalog, OnboardCatalog):  # none yet (the solve says so)
            return True
        with self._lock:
            pending = catalog.__dict__.get("_pattern_build")
        if pending is None:
            return True
        mrad, future = pending
        try:
            index = future.result(timeout)
        except FutureTimeout:
            return False
        except Exception as exc:  # noqa: BLE001 - a crashed build process: this process builds it
            log.warning("catalog pattern index build failed (%s: %s); building it here", type(exc).__name__, exc)
            index = None
        with self._lock:
            if catalog.__dict__.pop("_pattern_build", None) is not None and index is not None:
                scale_free.set_catalog_patterns(catalog, mrad, index)
        return True

    def __call__(self, ctx: SolveContext) -> dict:
        self.index_ready(ctx.catalog)  # a GO right after a catalog COMMIT waits for its index
        device = ctx.params if isinstance(ctx.params, DeviceParams) else DeviceParams()
        params = device.apply(self.params)
        tracking = self.tracking if device.tracking is None else device.tracking
        if not tracking or not ctx.go_code & GoBits.ON:
            self.tracker.state = None  # tracking off, or the GO asks to drop the track
        t = frame_time(ctx.frame, ctx.started)
        limits = params.exclusion
        recall = self.last.recall(t, limits.memory_s) if self.last is not None and limits is not None else None
        if tracking:
            out = self.tracker.solve(ctx.frame, t, self.camera, ctx.catalog, params, recall)
        else:
            out = run_pipeline(ctx.frame, self.camera, ctx.catalog, params, recall)
        if out.status is Status.OK and out.solution is not None and out.solution.q_icrs_to_sensor is not None:
            self.last = LastAttitude(np.asarray(out.solution.q_icrs_to_sensor, float), t, out.omega)
        fields = result_fields(out)
        fields["ext.reason"] = out.reason
        fields["ext.utc_epoch"] = t  # the exposure's mid-time; the sequence puts it on the device clock
        return fields
