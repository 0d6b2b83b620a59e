"""Field-test replay: solve every frame of a directory over the link or in-process, score
against truth, log every result as it comes, and summarise.

* Frames are the files of a directory that the frame readers accept, in name order; truth is
  ``NAME.truth.json`` beside a frame (the renderer's format: ``attitude_quaternion``
  scalar-first ICRS->sensor, and ``stars`` with ``id``, ``x``, ``y``).
* :class:`LinkSolver` uploads each frame to slot 1 and commands GO over the serial link. A
  device that stops answering is reported, waited for (PING every half second) and the frame
  is solved again once it is back; a result is logged only once it is complete, so nothing
  logged is lost and nothing is logged twice.
* :class:`OfflineSolver` runs the same pipeline in-process.
* Scoring: ``correct`` when the attitude error is at most :data:`CORRECT_DEG` and no matched
  star carries a wrong id (an id is wrong when truth stars lie within :data:`MATCH_RADIUS_PX`
  of the detection and none of them has it: a blend may be matched to either component); ``wrong`` for any other returned attitude; ``no_match`` when no
  attitude came back; ``unscored`` without truth; ``unreadable`` when the file could not be
  read (the run goes on).
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.pipeline.extract import StarList, extract_stars
from firmware_model.pipeline.frame_readers import frame_files, read_frame
from firmware_model.pipeline.raw_frame import Frame, frame_to_bytes
from firmware_model.pipeline.run import identify_stars, run_pipeline, warm_up
from firmware_model.pipeline.solve_types import PipelineParams
from firmware_model.reference_frames import quat_to_matrix
from ground.analysis.results_log import ResultsLog, plot_summary, summarize
from ground.arg_types import InputError
from ground.atomic_write import write_text
from ground.link.solve_report import add_setup_stages, matched_stars, record_from_output, solve_record

if TYPE_CHECKING:
    from ground.link.client import Client
from ground.optional import MissingExtra
from ground.sim.truth import CORRECT_DEG, MATCH_RADIUS_PX, Truth, score  # noqa: F401 (replay's own names)
from protocol.commands import Slot
from protocol.result import Status

_log = logging.getLogger(__name__)  # (``log`` is the exchange log and the results log here)

LOOSE_SIGMA_PX = 3.0  #: centroid noise assumed for the approximate attitude before refraction correction


_kernels_lock = threading.Lock()
_kernels_loaded = False


def warm_up_kernels(progress: bool = False) -> float:
    """Load the pipeline's compiled kernels once per process, as the device does before it says
    ``listening`` (``run.warm_up``: ~0.4 s from numba's disk cache; the first run after install
    compiles them, about a minute on 2 cores). Returns the seconds this call spent (0 once they
    are loaded: a solve reports them as its ``compile`` stage). When something compiles, one line
    says so on stderr, and with ``progress`` a bar counts the kernels compiled."""
    global _kernels_loaded
    with _kernels_lock:
        if _kernels_loaded:
            return 0.0
        t0 = time.perf_counter()
        with _compile_progress(progress):
            warm_up()
        _kernels_loaded = True
        return time.perf_counter() - t0


@contextlib.contextmanager
def _compile_progress(progress: bool):
    """Say when numba compiles (its ``numba:compile`` events): a loaded cache says nothing."""
    from numba.core import event

    bar: list = []

    class Listener(event.Listener):
        def on_start(self, ev) -> None:
            if not bar:
                tqdm.write(
                    "compiling the pipeline's kernels: the first run after install (about a minute on 2 "
                    "cores; kept in numba's cache for every later run)",
                    file=sys.stderr,
                )
                bar.append(tqdm(desc="kernels compiled", unit=" kernel", disable=not progress, file=sys.stderr))

        def on_end(self, ev) -> None:
            if bar:
                bar[0].update(1)

    with event.install_listener("numba:compile", Listener()):
        try:
            yield
        finally:
            if bar:
                bar[0].close()


class SetupCharges:
    """Set-up seconds (``compile``, ``database``, ``catalog``) an in-process solver paid before
    its first frame, reported by its next record (``add_setup_stages``)."""

    _setup: dict[str, float]
    #: list every detection in a record's ``stars``, not only the result record's brightest
    #: (``record_from_output(every_star=True)``: ``solve-file``, whose record is not a device's)
    every_star: bool = False

    def _record(self, out) -> dict:
        return record_from_output(out, every_star=self.every_star)

    def charge_setup(self, **seconds: float) -> None:
        for name, value in seconds.items():
            self._setup[name] = self._setup.get(name, 0.0) + value

    @property
    def setup_s(self) -> dict[str, float]:
        """The seconds charged and not yet reported."""
        return dict(self._setup)

    def _take_setup(self) -> dict[str, float]:
        """The seconds charged so far, the kernels loaded now (``compile``) among them, for the
        record about to be made; none left for the next."""
        setup, self._setup = self._setup, {}
        setup["compile"] = setup.get("compile", 0.0) + warm_up_kernels()
        return setup


class OfflineSolver(SetupCharges):
    """The device pipeline in-process (``replay --offline``).

    With a ``site`` (``ground.calibration.corrections.Site``) and a frame timestamp, star vectors are
    corrected for atmospheric refraction before the final match (Enright & McVittie section 5.3.2): a
    first solve (with a loose :data:`LOOSE_SIGMA_PX` noise model if the rigorous one fails: the
    paper used a manual match) gives the approximate attitude that places each star in the
    sky, the vectors are corrected (``correct_refraction``) and the stars identified again at
    full rigour; the record then says ``"refraction": "corrected"``. With a site the camera is
    taken as calibrated (no optics search): on one low field, refraction and a focal-length error
    are nearly degenerate.

    ``camera`` is one model for every frame, or a function of the frame (``--fov-deg``: a pinhole
    camera per frame size); ``catalog`` one catalog, or a function of the camera (each camera's
    field catalog, ``ground.catalog.field_catalogs.sky_catalog``).

    The first solve loads the kernels (:func:`warm_up_kernels`, as the device does before it
    serves) and reports those seconds as its ``compile`` stage, with the set-up stages the caller
    charged to this solver (:meth:`charge_setup`, e.g. ``catalog=s``) in its ``timings_s`` and
    their ``total``.
    """

    def __init__(
        self,
        camera: CameraModel | Callable[[Frame], CameraModel],
        catalog: OnboardCatalog | Callable[[CameraModel], OnboardCatalog],
        params: PipelineParams = PipelineParams(),
        site=None,
    ):
        self.camera, self.catalog, self.params, self.site = camera, catalog, params, site
        self._setup: dict[str, float] = {}  # charged to the first solve

    def camera_for(self, frame: Frame) -> CameraModel:
        return self.camera if isinstance(self.camera, CameraModel) else self.camera(frame)

    def solve(self, frame: Frame) -> dict:
        setup = self._take_setup()
        return add_setup_stages(self._solve(frame), **setup)

    def _solve(self, frame: Frame) -> dict:
        camera = self.camera_for(frame)
        catalog = self.catalog(camera) if callable(self.catalog) else self.catalog
        if self.site is None:
            return self._record(run_pipeline(frame, camera, catalog, self.params))
        # refraction squeezes a low field like a focal-length error: with a site, the camera is
        # taken as calibrated (no optics search), so the two are not confused
        params = replace(self.params, optics=None)
        out = run_pipeline(frame, camera, catalog, params)
        if out.stars is None or len(out.stars) < 2:
            return self._record(out)
        if not frame.timestamp:
            raise ValueError("refraction correction needs the frame's timestamp")
        from astropy.time import Time

        from ground.calibration.corrections import correct_refraction

        stars = out.stars
        approx = out
        if out.status is not Status.OK:
            # differential refraction can exceed the centroid noise: look for the approximate
            # attitude with a loose noise model (the final match below is made at full rigour); a
            # low-confidence first answer (e.g. a two-star last resort) is no approximation to trust
            approx = identify_stars(stars, camera, catalog, replace(params, fixed_sigma_px=LOOSE_SIGMA_PX))
        q_approx = approx.solution.q_icrs_to_sensor if approx.solution is not None else None
        if q_approx is None:  # (an OK answer always has its attitude)
            rec = self._record(out)
            rec["refraction"] = "not corrected: no approximate attitude"
            return rec
        vec = correct_refraction(
            stars.vectors,
            quat_to_matrix(q_approx),
            self.site,
            Time(frame.timestamp, scale="utc"),
        )
        corrected = identify_stars(replace(stars, vectors=vec), camera, catalog, params)
        rec = self._record(corrected)
        rec["refraction"] = "corrected"
        return rec


def solve_sky(frame: Frame, fov, db, params: PipelineParams, catalog: OnboardCatalog | None = None):
    """``sky_run.run_pipeline_sky`` with the database's search and each found camera's field
    catalog (``catalog``, when given, for every camera, matched against the database's patterns):
    (PipelineOutput, SkyReport)."""
    from firmware_model.pipeline.scale_free import set_sky_patterns
    from firmware_model.pipeline.sky_run import run_pipeline_sky
    from ground.catalog.field_catalogs import sky_catalog

    if catalog is not None:
        set_sky_patterns(catalog, db.index)

    def catalog_for(camera: CameraModel) -> OnboardCatalog:
        return catalog if catalog is not None else sky_catalog(camera, db)

    return run_pipeline_sky(frame, fov, db.search, catalog_for, params)


class SkySolver(SetupCharges):
    """The pipeline in-process with the field of view searched (``replay --offline`` and
    ``solve-file`` without ``--camera``): ``fov`` a ``sky_search.FieldRange`` (a hint's, a
    range or blind), ``database`` the loaded ``ground.catalog.sky_database.SkyDatabase``, ``catalog``
    one catalog for every frame (None: each found camera's field catalog, ``solve_sky``).
    Each record carries the search's ``sky`` block; the first one the set-up seconds, as
    :class:`OfflineSolver`'s."""

    def __init__(self, fov, database, params: PipelineParams = PipelineParams(), catalog=None):
        self.fov, self.database, self.params, self.catalog = fov, database, params, catalog
        self._setup: dict[str, float] = {}

    def solve(self, frame: Frame) -> dict:
        setup = self._take_setup()
        out, report = solve_sky(frame, self.fov, self.database, self.params, self.catalog)
        rec = add_setup_stages(self._record(out), **setup)
        rec["sky"] = report.to_dict()
        return rec


class LinkSolver:
    """Solves on a device over the serial link (``replay`` / ``solve``), surviving link loss."""

    def __init__(
        self,
        url: str,
        reconnect_timeout: float = 120.0,
        go_timeout: float = 60.0,
        log=None,
        upload_progress: bool = False,
        **client_kw,
    ):
        self.url = url
        self.upload_progress = upload_progress  #: a progress bar while the frame uploads (minutes at 115 200 baud)
        self.reconnect_timeout = reconnect_timeout
        self.go_timeout = go_timeout
        self.log = log
        self.client_kw = client_kw
        self.client: Client | None = None
        self.reconnects = 0

    def _connect(self) -> Client:
        from ground.link.client import Client

        client = Client(self.url, log=self.log, **self.client_kw)
        try:
            if "BOOTLOADER" in client.ping():
                client.init()
        except Exception:
            client.close()
            raise
        self.client = client
        _log.debug("connected to the device at %s", self.url)
        return client

    def close(self):
        if self.client is not None:
            self.client.close()
            self.client = None

    def _wait_for_device(self, why: Exception, say, deadline: float) -> None:
        left = max(deadline - time.monotonic(), 0.0)
        say(f"device not answering ({type(why).__name__}: {why}); waiting up to {left:.0f} s")
        self.close()
        while time.monotonic() < deadline:
            try:
                self._connect()
                self.reconnects += 1
                say("device is back; solving the frame again")
                return
            except Exception:
                time.sleep(0.5)
        raise TimeoutError(f"device at {self.url} did not come back within {self.reconnect_timeout:.0f} s")

    def solve(self, frame: Frame | None, say: Callable[[str], object] | None = None) -> dict:
        """Upload ``frame`` (or capture, when None), GO, and return the decoded result. A silent or
        lost device is waited for, at most ``reconnect_timeout`` seconds in all for this frame (said
        through ``say``, by default a warning of this module's logger); a NACK is the device's
        answer and is raised (``ground.link.client.Nack``), never retried."""
        from ground.link.client import LinkError, Nack

        say = say or _log.warning

        data = frame_to_bytes(frame) if frame is not None else None
        deadline = None
        while True:
            try:
                client = self.client if self.client is not None else self._connect()
                if data is not None:
                    client.upload(Slot.FRAME, data, progress=self.upload_progress)
                return solve_record(client.go_and_wait(timeout=self.go_timeout))
            except Nack:
                raise
            except (LinkError, OSError) as exc:
                if deadline is None:
                    deadline = time.monotonic() + self.reconnect_timeout
                self._wait_for_device(exc, say, deadline)


def replay(
    directory, solver, out_dir, progress: bool = True, make_plots: bool = True, resume: bool = False, wcs_camera=None
) -> dict:
    """Solve every frame of ``directory`` with ``solver`` (Link/OfflineSolver); log and summarise.
    Each record is on disk before the next frame starts, so an interrupted run keeps what it
    solved; ``resume`` continues it (frames already logged in ``out_dir`` are skipped). Without
    ``resume`` an ``out_dir`` that already holds results is refused (InputError, exit 2): runs never mix.
    With ``wcs_camera`` (frame -> CameraModel) every solved frame's WCS goes to
    ``out_dir/wcs/NAME.wcs`` (``record["wcs"]`` names it)."""
    from ground.arg_types import InputError
    from ground.link.client import Nack

    if not Path(directory).is_dir():  # a missing input: exit 2, as every other
        raise InputError(f"{directory}: {'not a directory' if Path(directory).exists() else 'no such directory'}")
    paths = frame_files(directory)
    if not paths:  # nothing to replay is an input error (exit 2), not an empty success
        raise InputError(f"{directory}: no frame files (DNG/raw, FITS, TIFF, PNG, JPEG, .npy) in the directory")
    log = ResultsLog(out_dir)
    done = {r.get("frame") for r in log.records()}
    if done and not resume:
        raise InputError(
            f"{out_dir} already holds {len(done)} frame result(s): --resume continues that run, or choose another -o/--output"
        )
    say = _log.warning  # above the progress bar: st16-ground's log handler writes through tqdm
    todo = [p for p in paths if p.name not in done]
    _log.debug(
        "replay %s: %d frame(s), %d already logged in %s", directory, len(paths), len(paths) - len(todo), out_dir
    )
    bar = tqdm(
        todo, desc="replay", unit="frame", disable=not progress, initial=len(paths) - len(todo), total=len(paths)
    )
    for path in bar:
        base = {"time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "frame": path.name}
        try:
            frame = read_frame(path)
        except Exception as exc:  # unreadable frames are logged and skipped; the run goes on
            log.append({**base, "outcome": "unreadable", "reason": f"{type(exc).__name__}: {exc}"})
            continue
        t0 = time.perf_counter()
        try:
            record = solver.solve(frame, say) if isinstance(solver, LinkSolver) else solver.solve(frame)
            record["exchange_s"] = time.perf_counter() - t0
            record["solve_s"] = record["timings_s"].get("total")
            truth = Truth.for_frame(path, frame, say)
            record.update(base)
            record.update(score(record, truth))
            record["residuals_arcsec"] = [
                s["residual_arcsec"] for s in matched_stars(record) if s["residual_arcsec"] is not None
            ]
            if wcs_camera is not None and record["q_icrs_to_sensor"] is not None:
                wcs_stem = Path(out_dir) / "wcs" / path.stem
                record["wcs"] = str(_write_frame_wcs(record, frame, wcs_camera(frame), wcs_stem))
        except Nack as exc:  # the device refused this frame (its size, say): logged, and the run goes on
            log.append({**base, "outcome": "refused", "reason": str(exc)})
            continue
        except TimeoutError:  # the device did not come back: the run ends (exit 4), its records kept
            raise
        except Exception as exc:  # one frame that fails is a counted row, never the end of the run
            _log.debug("%s: failed", path.name, exc_info=True)
            log.append({**base, "outcome": "failed", "reason": _failure(exc)})
            continue
        log.append(record)
        bar.set_postfix_str(record["outcome"])
        _log.debug("%s: %s", path.name, record["outcome"])
    records = log.records()
    summary = summarize(records)
    summary["plots"] = []
    if make_plots:
        try:
            summary["plots"] = [str(p) for p in plot_summary(records, out_dir)]
        except MissingExtra as exc:  # the results are kept; only the pictures are missing
            say(f"plots skipped: {exc}")
    write_text(Path(out_dir) / "summary.json", json.dumps(summary, indent=2))
    return summary


def _failure(exc: BaseException) -> str:
    """One line, at most 300 characters, saying why a frame failed (``--debug``/``--log-level
    debug`` gives its traceback)."""
    text = " ".join(f"{type(exc).__name__}: {exc}".split())
    return text if len(text) <= 300 else text[:297] + "..."


def _write_frame_wcs(record: dict, frame: Frame, camera: CameraModel, stem: Path) -> Path:
    from ground.analysis.wcs import record_wcs, write_wcs

    stem.parent.mkdir(parents=True, exist_ok=True)
    return write_wcs(stem.with_suffix(".wcs"), record_wcs(record, frame.width, frame.height, camera)[0])


# --------------------------------------------------------------------------- table 5 (Enright & McVittie)

TABLE5_MODES = ("basic", "ideal colour", "chromatic correction", "ideal colour + chromatic")


def _associate(stars: StarList, truth: Truth):
    """(detection row, truth row) pairs within MATCH_RADIUS_PX."""
    pairs = []
    for i in range(len(stars)):
        d = np.hypot(truth.x - stars.x[i], truth.y - stars.y[i])
        if len(d) and d.min() <= MATCH_RADIUS_PX:
            pairs.append((i, int(np.argmin(d))))
    return pairs


class NothingToScore(InputError):
    """``table5`` was given no frame it can score (none has a truth file): ``st16-ground`` says why in
    one line and exits 2, as for any input it cannot use."""


def _mean_colour_error(errors: list) -> np.ndarray | None:
    """Mean (rg, bg) error of one star over the frames where its colour was measured; None when it
    never was (a mono frame measures no colour: its rg, bg are NaN)."""
    e = np.array(errors, dtype=float)
    e = e[np.isfinite(e).all(axis=1)]
    return e.mean(axis=0) if len(e) else None


def table5(
    paths,
    camera: CameraModel,
    catalog: OnboardCatalog,
    params: PipelineParams = PipelineParams(),
    progress: bool = True,
) -> dict:
    """Enright & McVittie table 5 on frames with truth: correct/incorrect matches for the basic pipeline,
    with idealised colour (each star's mean colour error over the run removed), with
    idealised geometry (each star's mean centroid error removed: the paper's chromatic
    correction) and with both. Frames without a truth file are left out; none with one raises
    :class:`NothingToScore`."""
    ids = {int(s): k for k, s in enumerate(catalog.star_id)}
    paths = [Path(p) for p in paths]
    runs = []
    for path in tqdm(paths, desc="extract", unit="frame", disable=not progress):
        truth = Truth.for_frame(path)
        if truth is None:
            continue
        stars = extract_stars(read_frame(path), camera, params.extract)
        runs.append((stars, truth, _associate(stars, truth)))
    if not runs:
        where = f" in {paths[0].parent}" if len({p.parent for p in paths}) == 1 else ""
        missing = f"none of the {len(paths)} frames{where} has truth" if paths else "no frame to score"
        raise NothingToScore(
            f"table5: {missing}: table5 scores frames against truth files <stem>.truth.json beside them "
            "(frame render and the demo write them)"
        )
    colour_err: dict[int, list] = {}
    pos_err: dict[int, list] = {}
    for stars, truth, pairs in runs:
        for i, t in pairs:
            sid = int(truth.star_id[t])
            pos_err.setdefault(sid, []).append((stars.x[i] - truth.x[t], stars.y[i] - truth.y[t]))
            if sid in ids:
                c = ids[sid]
                colour_err.setdefault(sid, []).append((stars.rg[i] - catalog.rg[c], stars.bg[i] - catalog.bg[c]))
    mean_colour = {s: m for s, v in colour_err.items() if (m := _mean_colour_error(v)) is not None}
    mean_pos = {s: np.mean(np.array(v), axis=0) for s, v in pos_err.items()}
    table = {}
    for mode in TABLE5_MODES:
        counts = {"correct": 0, "incorrect": 0, "no_match": 0}
        for stars, truth, pairs in runs:
            s2 = replace(stars, x=stars.x.copy(), y=stars.y.copy(), rg=stars.rg.copy(), bg=stars.bg.copy())
            for i, t in pairs:
                sid = int(truth.star_id[t])
                if "colour" in mode and sid in mean_colour:
                    s2.rg[i] -= mean_colour[sid][0]
                    s2.bg[i] -= mean_colour[sid][1]
                if "chromatic" in mode:
                    s2.x[i] -= mean_pos[sid][0]
                    s2.y[i] -= mean_pos[sid][1]
            s2 = replace(s2, vectors=camera.pixel_to_vector(s2.x, s2.y))
            sc = score(record_from_output(identify_stars(s2, camera, catalog, params)), truth)
            key = {"correct": "correct", "wrong": "incorrect"}.get(sc["outcome"], "no_match")
            counts[key] += 1
        table[mode] = counts
    return {"frames": len(runs), "table": table}
