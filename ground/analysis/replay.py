"""Field-test replay: solve every frame of a directory over the link or in-process, score
against truth, log every result as it comes, and summarise.

* Frames are the files of a directory that the frame readers accept, in name order; truth is
  ``NAME.truth.json`` beside a frame (the renderer's format: ``attitude_quaternion``
  scalar-first ICRS->sensor, and ``stars`` with ``id``, ``x``, ``y``).
* The solver is any ``ground.solver.Solver``: ``ground.link_solver.LinkSolver`` on a device
  (a result is logged only once it is complete, so nothing logged is lost and nothing is logged
  twice), or ``ground.solver.in_process_solver``'s, the same pipeline in-process.
* Scoring: ``correct`` when the attitude error is at most :data:`CORRECT_DEG` and no matched
  star carries a wrong id (an id is wrong when truth stars lie within :data:`MATCH_RADIUS_PX`
  of the detection and none of them has it: a blend may be matched to either component); ``wrong`` for any other returned attitude; ``no_match`` when no
  attitude came back; ``unscored`` without truth; ``unreadable`` when the file could not be
  read (the run goes on).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from firmware_model.camera import CameraModel
from firmware_model.pipeline.frame_readers import frame_files, read_frame
from firmware_model.pipeline.raw_frame import Frame
from ground.analysis.results_log import ResultsLog, plot_summary, summarize
from ground.atomic_write import write_text
from ground.link.solve_report import matched_stars
from ground.optional import MissingExtra
from ground.sim.truth import CORRECT_DEG, MATCH_RADIUS_PX, Truth, score  # noqa: F401 (replay's own names)

if TYPE_CHECKING:
    from ground.solver import Solver

_log = logging.getLogger(__name__)  # (``log`` is the exchange log and the results log here)


def replay(
    directory,
    solver: Solver,
    out_dir,
    progress: bool = True,
    make_plots: bool = True,
    resume: bool = False,
    wcs_camera=None,
) -> dict:
    """Solve every frame of ``directory`` with ``solver`` (``ground.solver.Solver``: in-process or
    ``ground.link_solver.LinkSolver``); log and summarise.
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
            record = solver.solve(frame, say).record
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
