"""A frame solved with its field of view searched (``sky_search``), then identified as a frame of
known field: the whole pipeline, off the device (``solve-file``, ``solve_image``, ``replay
--offline``, the whole-sky simulation; docs/identification.md, "Blind and wide").

1. The frame's stars are extracted once (their positions do not depend on the camera).
2. The sky search (counted: ``sky_search.FIRST_CHECKS`` hypotheses, then on to ``MAX_CHECKS``
   while no answer is high-confidence) finds the focal length and attitude; a hypothesis under
   ``sky_search.FALSE_ALARM`` over the search is taken, else its best candidates of distinct
   focal lengths are handed on (``sky_search.CANDIDATES``, each focal length once).
3. Each candidate's pinhole camera identifies the frame (``run.identify_stars``: the field's
   catalog matched against the whole-sky patterns the caller passes, the optics search and fit
   within its focal range, the deep verification and its confidence), until one is
   high-confidence. With a taken hypothesis an ``auto``-mode frame is
   identified on geometry first (the search found its stars), by colour only if that fails.
4. The answer must agree with the hypothesis it came from (boresight within
   :data:`AGREE_PX` pixels); the record's ``sky`` block gives the search's field of view, checks
   and false-alarm probability.

Units: px, radians; fields of view in deg (horizontal).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.ident.attitude import quat_matrix
from firmware_model.ident.solver import Mode
from firmware_model.pipeline.exclusion import check_exclusion
from firmware_model.pipeline.optics_search import pattern_rows
from firmware_model.pipeline.pattern_index import PatternIndex
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.run import frame_stars, identify_stars, label_planets_of
from firmware_model.pipeline.sky_search import (
    DISTINCT_F,
    FIRST_CHECKS,
    MAX_CHECKS,
    FieldRange,
    SkyFit,
    SkyResult,
    SkySearch,
)
from firmware_model.pipeline.solve_types import PipelineOutput, PipelineParams
from protocol.result import Status

#: An answer and the hypothesis it came from agree when their boresights are this close (px).
AGREE_PX = 20.0


@dataclass(frozen=True)
class SkyReport:
    """The sky search behind an answer: the range searched (deg), the field of view of the
    hypothesis the answer came from (deg; NaN: none), hypotheses checked, its false-alarm
    probability over the search (1: none), whether it was taken outright and whether the count
    stopped the search."""

    fov_range_deg: tuple[float, float]
    fov_deg: float
    checks: int
    false_alarm: float
    taken: bool
    stopped: bool

    def to_dict(self) -> dict:
        return {
            "fov_range_deg": list(self.fov_range_deg),
            "fov_deg": None if math.isnan(self.fov_deg) else self.fov_deg,
            "checks": self.checks,
            "false_alarm": self.false_alarm,
            "taken": self.taken,
            "budget_reached": self.stopped,
        }


def run_pipeline_sky(
    frame: Frame,
    fov: FieldRange,
    sky: SkySearch,
    catalog_for: Callable[[CameraModel], OnboardCatalog],
    params: PipelineParams = PipelineParams(),
    checks: tuple[int, ...] = (FIRST_CHECKS, MAX_CHECKS),
    patterns: PatternIndex | None = None,
) -> tuple[PipelineOutput, SkyReport]:
    """Frame -> stars -> sky search -> identification with the found camera (module docstring).
    ``catalog_for(camera)``: the field's catalog; ``checks``: the counts of hypotheses checked (in
    all) after which the candidates found so far are identified, the search going on to the next
    while none is high-confidence; ``patterns``: the pattern index each identification looks its
    patterns up in (the whole-sky one; None: each catalog's own for its field)."""
    t0 = time.perf_counter()
    catalog_s = 0.0

    def catalog(camera: CameraModel) -> OnboardCatalog:  # timed: a set-up stage, not the frame's
        nonlocal catalog_s
        t1 = time.perf_counter()
        cat = catalog_for(camera)
        catalog_s += time.perf_counter() - t1
        return cat

    w, h = frame.width, frame.height
    brackets = fov.focal_brackets(w)
    mid = CameraModel.pinhole(w, h, math.sqrt(brackets[0][0] * brackets[-1][0]))
    stars = frame_stars(frame, mid, params)
    nothing = SkyReport((fov.lo_deg, fov.hi_deg), math.nan, 0, 1.0, False, False)
    if isinstance(stars, PipelineOutput):
        return stars, nothing
    if len(stars.x) < 4:  # the pipeline's own TOO_FEW_STARS answer
        seen = replace(stars, vectors=mid.pixel_to_vector(stars.x, stars.y))
        return identify_stars(seen, mid, catalog(mid), params, patterns), nothing
    clean = pattern_rows(stars)
    run = sky.start(stars.x[clean], stars.y[clean], w, h, fov)
    out: PipelineOutput | None = None
    used: SkyFit | None = None
    search_s, tried_f = 0.0, list[float]()
    for budget in checks:
        t1 = time.perf_counter()
        found = run.advance(budget)
        search_s += time.perf_counter() - t1
        # a decisive hypothesis' stars are verified first on either route (``auto`` mode: geometry,
        # then colour only if that fails): the sky search has done the colour matcher's work
        solve_params = params
        if found.taken is not None and params.solve.mode == Mode.AUTO:
            solve_params = replace(params, solve=replace(params.solve, mode=Mode.GEOMETRIC))
        for fit in found.candidates:
            if any(abs(fit.f / f - 1.0) <= DISTINCT_F for f in tried_f):
                continue  # identified with this focal length already
            tried_f.append(fit.f)
            camera = CameraModel.pinhole(w, h, fit.f)
            seen, field = replace(stars, vectors=camera.pixel_to_vector(stars.x, stars.y)), catalog(camera)
            tried = identify_stars(seen, camera, field, solve_params, patterns)
            if tried.status is not Status.OK and solve_params is not params:  # the colour route after all
                again = identify_stars(seen, camera, field, params, patterns)
                again.timings.identify += tried.timings.identify + tried.timings.attitude
                tried = again if _higher_tier(again, tried) else tried
            if out is None or _higher_tier(tried, out):
                loser, out, used = out, tried, fit
            else:
                loser = tried
            if loser is not None:  # the other try's work counts as the answer's identification
                search_s += loser.timings.identify + loser.timings.attitude
            if tried.status is Status.OK:
                break
        if (out is not None and out.status is Status.OK) or found.taken is not None or run.exhausted:
            break
    if out is None:
        out = _no_match(stars, found)
    else:
        assert used is not None
        _held_to_hypothesis(out, used)
        if frame.timestamp and out.solution is not None and out.solution.q_icrs_to_sensor is not None:
            assert out.camera is not None
            out = label_planets_of(out, frame, catalog(out.camera), params, patterns)
    out = check_exclusion(out, frame, params.exclusion)  # as run_pipeline's answers (docs/ICD.md section 7)
    out.timings.identify += search_s  # the sky search (and any earlier candidate) is identification
    out.timings.catalog = catalog_s
    out.timings.total = time.perf_counter() - t0  # the whole call, the catalogs' set-up included
    report = SkyReport(
        (fov.lo_deg, fov.hi_deg),
        used.fov_deg(w) if used is not None else math.nan,
        found.checks,
        # its chance of coincidence counted over every hypothesis the search checked, not only
        # those before it (a candidate handed on after the search went further)
        min(1.0, used.false_alarm * found.checks / used.checks) if used is not None else 1.0,
        found.taken is not None,
        found.stopped,
    )
    return out, report


def _higher_tier(a: PipelineOutput, b: PipelineOutput) -> bool:
    """Whether candidate camera ``a``'s answer is in a higher tier than ``b``'s: high confidence,
    then any attitude, then none. Within a tier the earlier candidate stays (the sky search ranked
    its hypotheses already), unlike ``strategy.ranks_above``, which prefers more matched stars
    among one camera's answers."""
    return _tier(a) > _tier(b)


def _tier(out: PipelineOutput) -> int:
    if out.status is Status.OK:
        return 2
    return 1 if out.solution is not None and out.solution.q_icrs_to_sensor is not None else 0


def _held_to_hypothesis(out: PipelineOutput, fit: SkyFit) -> None:
    """Demote a high-confidence answer whose boresight is more than :data:`AGREE_PX` from the sky
    search hypothesis it came from (in place): identification judged the field's catalog alone,
    this judges the answer against the search that chose the camera."""
    sol = out.solution
    if out.status is not Status.OK or sol is None or sol.q_icrs_to_sensor is None:
        return
    cos = float(np.clip(quat_matrix(sol.q_icrs_to_sensor)[2] @ fit.a[2], -1.0, 1.0))
    if math.acos(cos) * fit.f > AGREE_PX:
        out.status = Status.LOW_CONFIDENCE
        note = "the field's identification disagrees with the sky search's hypothesis"
        out.reason = f"{note}; {out.reason}" if out.reason else note


def _no_match(stars, found: SkyResult) -> PipelineOutput:
    """The NO_MATCH answer of a search with no candidate."""
    lo, hi = found.fov.lo_deg, found.fov.hi_deg
    if found.checks == 0:
        reason = f"no pattern of the brightest detections matched the sky for fields of view {lo:.3g}-{hi:.3g} deg"
    else:
        reason = (
            f"none of {found.checks} hypotheses from the brightest detections' patterns matched five stars"
            f" (fields of view {lo:.3g}-{hi:.3g} deg)"
        )
    if found.stopped:
        reason = f"sky search budget of {found.checks} hypotheses reached; {reason}"
    return PipelineOutput(Status.NO_MATCH, reason, stars=stars)
