"""The device's detection-to-attitude pipeline on one frame: the declared plan of its solve and
the walk through it.

``run_pipeline(frame, camera, catalog, params) -> PipelineOutput`` chains extraction (detection,
centroid and colour fit, camera model), identification and attitude, then planet labelling and
the bright-body exclusion check. Identification is the stages of :data:`SOLVE_PLAN`, each with its
counted budget and hand-off rule (docs/identification.md, "The solve plan"): the pattern seed and
the optics search (``optics_search``), the matchers (``frame_identification`` over
``firmware_model.ident.strategy``, which decides the methods, fallbacks, confidence and ranking).
The pattern index the frame's patterns are looked up in is an argument of the solve
(``patterns``: off the device, the whole-sky one); without it, the catalog's own for the
camera's field (``scale_free.catalog_patterns``: the device's). It never raises on bad frames:
the output carries a :class:`protocol.result.Status` and a reason. The types are
``solve_types``; ``result_fields`` maps an output onto the result structure.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.ident.attitude import solve_attitude
from firmware_model.ident.budget import Stop
from firmware_model.ident.consensus import NOT_A_STAR_FIELD, Outcome
from firmware_model.ident.solver import SolveResult
from firmware_model.ident.strategy import chance_refusal, ranks_above, routes_geometric
from firmware_model.ident.strategy import warm_up as strategy_warm_up
from firmware_model.ident.verify import warm_up as verify_warm_up
from firmware_model.pipeline import scale_free
from firmware_model.pipeline.camera_fit import StarObservations
from firmware_model.pipeline.exclusion import Recall, check_exclusion
from firmware_model.pipeline.extract import StarList, extract_stars
from firmware_model.pipeline.extract import warm_up as extract_warm_up
from firmware_model.pipeline.frame_fit import fit_frame
from firmware_model.pipeline.frame_identification import has_colour, identify_with_camera, usable_rows
from firmware_model.pipeline.optics_search import (
    FirstSeed,
    first_seed,
    first_tier,
    nominal_off,
    pattern_index,
    refine_optics,
    search_optics,
    verify_seed,
)
from firmware_model.pipeline.pattern_index import PatternIndex
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.solve_types import (
    OpticsSearch,
    PipelineOutput,
    PipelineParams,
    SolveInput,
    StageTimings,
)
from protocol.result import Status


def run_pipeline(
    frame: Frame,
    camera: CameraModel,
    catalog: OnboardCatalog,
    params: PipelineParams = PipelineParams(),
    recall: Recall | None = None,
    patterns: PatternIndex | None = None,
) -> PipelineOutput:
    """Frame -> stars -> identification -> attitude (module docstring), then planet labelling and
    the bright-body exclusion check (``exclusion.check_exclusion``; ``recall``: the device's last
    attitude at this frame's time, for a frame that gives none; ``patterns``: the pattern index,
    None for the catalog's own)."""
    t0 = time.perf_counter()
    stars = frame_stars(frame, camera, params)
    if isinstance(stars, PipelineOutput):
        return stars  # a frame that does not fit the camera: nothing to check
    out = identify_stars(stars, camera, catalog, params, patterns)
    if frame.timestamp and out.solution is not None and out.solution.q_icrs_to_sensor is not None:
        out = label_planets_of(out, frame, catalog, params, patterns)
    out = check_exclusion(out, frame, params.exclusion, recall)
    out.timings.total = time.perf_counter() - t0
    return out


def warm_up() -> float:
    """Compile (or, after the first run of an install, load from numba's disk cache) every kernel a
    solve runs: the extraction's (:func:`extract.warm_up`), the camera's projections, the attitude
    solve, the one-frame optics fit, the verification's, the noise probe's and the pattern stage's,
    so that the first frame's solve (and its optics search's time budget) does not pay for them.
    Returns the seconds it took; meant for start-up."""
    t0 = time.perf_counter()
    extract_warm_up()
    cam = CameraModel(64, 48, 100.0, 31.5, 23.5, k1=0.01)
    x, y = np.array([5.0, 60.0, 10.0, 50.0, 30.0, 20.0]), np.array([4.0, 6.0, 40.0, 44.0, 20.0, 30.0])
    v = cam.pixel_to_vector(x, y)
    cam.vector_to_pixel(v)
    solve_attitude(v, v, 1e-4)
    fit_frame(StarObservations(x + 0.1, y - 0.1, v), cam, k1_min_stars=4)
    verify_warm_up()
    strategy_warm_up()
    scale_free.warm_up()
    return time.perf_counter() - t0


def frame_stars(frame: Frame, camera: CameraModel, params: PipelineParams) -> StarList | PipelineOutput:
    """The stars extracted from ``frame``, or the BAD_FRAME answer for a frame of another size than
    ``camera``'s or one the extraction rejects."""
    if (frame.width, frame.height) != (camera.width, camera.height):
        return PipelineOutput(
            Status.BAD_FRAME,
            f"frame is {frame.width} x {frame.height} but the camera is {camera.width} x {camera.height}",
        )
    try:
        return extract_stars(frame, camera, params.extract)
    except ValueError as exc:
        return PipelineOutput(Status.BAD_FRAME, f"frame rejected: {exc}")


def label_planets_of(
    out: PipelineOutput,
    frame: Frame,
    catalog: OnboardCatalog,
    params: PipelineParams,
    patterns: PatternIndex | None = None,
):
    """Label detections on a predicted planet or the moon at the frame's epoch (``planets``); if
    one of them was matched to a catalog star, identify again without them (with ``patterns``,
    as :func:`identify_stars`)."""
    from firmware_model.pipeline.planets import label_planets

    site = frame.site or {}
    where = (
        (site["lat_deg"], site["lon_deg"], site.get("height_m", 0.0)) if {"lat_deg", "lon_deg"} <= set(site) else None
    )
    stars, sol = out.stars, out.solution
    assert stars is not None and stars.vectors is not None and sol is not None and out.camera is not None
    try:
        labels = label_planets(stars.x, stars.y, sol.q_icrs_to_sensor, out.camera, frame.timestamp, site=where)
    except ValueError as exc:  # an unreadable timestamp: no labels, and say so
        out.reason = f"{out.reason}; planets not predicted: {exc}" if out.reason else f"planets not predicted: {exc}"
        return out
    rows = np.array([lab.index for lab in labels], dtype=np.int64)
    if len(rows) and np.isin(out.used[sol.matched_det], rows).any():
        vectors = stars.vectors.copy()
        hidden = replace(stars, x=stars.x.copy(), y=stars.y.copy(), vectors=vectors)
        hidden.x[rows] = hidden.y[rows] = np.nan
        vectors[rows] = np.nan
        again = identify_stars(hidden, out.camera, catalog, params, patterns)
        again.stars = stars
        if again.optics is None:
            again.optics = out.optics
        out = again
    out.planets = labels
    return out


def identify_stars(
    stars: StarList,
    camera: CameraModel,
    catalog: OnboardCatalog,
    params: PipelineParams = PipelineParams(),
    patterns: PatternIndex | None = None,
) -> PipelineOutput:
    """Identification and attitude from extracted stars (``stars.vectors`` from ``camera``): the
    stages of :data:`SOLVE_PLAN`, in its order, each handing on by its rule. ``patterns``: the
    pattern index the stars' patterns are looked up in (None: the catalog's own for the field)."""
    t0 = time.perf_counter()
    frame = FrameSolve(
        SolveInput(stars, camera, catalog, patterns),
        params,
        StageTimings(
            detect=stars.timings.get("detect_s", 0.0),
            fit=stars.timings.get("fit_s", 0.0),
            vectors=stars.timings.get("vectors_s", 0.0),
        ),
    )
    name = SOLVE_PLAN[0].name
    while name != DONE:
        stage = _PLAN_STAGES[name]
        name = stage.run(frame)
        assert name in stage.hands_to, f"{stage.name} handed to {name}, not in the plan"
    assert frame.out is not None  # every path to DONE leaves an answer
    return _accounted(_chance_checked(frame.out, frame.timings), frame.timings, t0, stars)


def _chance_checked(out: PipelineOutput, timings: StageTimings) -> PipelineOutput:
    """``out``, or NO_MATCH when it is a low-confidence answer that the hypotheses met over the
    whole frame would give by chance (``strategy.chance_refusal``): a frame of hot pixels with no
    star in it. Every solve of the frame (one, and one more per pattern seed the optics search
    refined) is counted as meeting as many hypotheses as the answer's own solve did, or the frame's
    verifications when they are more."""
    sol = out.solution
    if out.status is not Status.LOW_CONFIDENCE or sol is None:
        return out
    met = max(sol.hypotheses * (1 + timings.seeds), timings.verifications)
    refusal = chance_refusal(sol.status, len(sol.matched_det), sol.chance, met)
    if refusal is None:
        return out
    return PipelineOutput(Status.NO_MATCH, refusal, out.stars, out.used, SolveResult(Outcome.NO_MATCH, refusal))


@dataclass
class FrameSolve:
    """What the stages of one frame's solve share: the inputs (``seen``: the stars through the
    nominal camera, the catalog, the pattern index), the frame's ledger (``timings``: seconds and counted work), the
    route, the first tier's pattern matches (``peek``) and their first refined seed, the answer so
    far (``out``) and the optics search's (``found``, once it ran: it runs at most once a frame)."""

    seen: SolveInput
    params: PipelineParams
    timings: StageTimings
    used: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    geometric: bool = False
    peek: scale_free.BrightFirstMatches | None = None
    seed: FirstSeed | None = None
    searched: bool = False
    found: PipelineOutput | None = None
    out: PipelineOutput | None = None


#: The name that ends a solve.
DONE = "done"


@dataclass(frozen=True)
class PlanStage:
    """One row of :data:`SOLVE_PLAN`: the stage's name, what runs, its budget (counted; the
    parameters that set it), the rule that names the next stage, the stages it may hand to, and the
    function that runs it and returns the next stage's name."""

    name: str
    runs: str
    budget: str
    rule: str
    hands_to: tuple[str, ...]
    run: Callable[[FrameSolve], str]


def _prepare(frame: FrameSolve) -> str:
    seen = frame.seen
    frame.used = usable_rows(seen.stars)
    frame.geometric = len(frame.used) >= 4 and routes_geometric(
        frame.params.solve.mode, seen.catalog, has_colour(seen.stars, frame.used)
    )
    if _first_tier_search(frame) is not None:
        t1 = time.perf_counter()
        pattern_index(seen)  # the catalog's own is built once per catalog and field: a set-up stage
        frame.timings.index = time.perf_counter() - t1
    if frame.params.flight_deadline_s is not None:  # from the frame's extraction, set-up stages excluded
        deadline = time.perf_counter() - seen.stars.timings.get("total_s", 0.0) + frame.params.flight_deadline_s
        frame.params = replace(frame.params, solve=replace(frame.params.solve, deadline=deadline))
    return "pattern seed" if len(frame.used) >= 4 else "matchers"


def _first_tier_search(frame: FrameSolve) -> OpticsSearch | None:
    """The first tier's settings: the optics search's, or on the geometric route a calibrated
    camera's (no search) default ones."""
    return frame.params.optics or (OpticsSearch() if frame.geometric else None)


def _pattern_seed(frame: FrameSolve) -> str:
    tier = _first_tier_search(frame)
    frame.peek = first_tier(frame.seen, tier, frame.timings)
    frame.seed = first_seed(frame.seen, tier, frame.timings, frame.peek)
    search = frame.params.optics
    if search is not None and nominal_off(frame.peek, frame.seed, frame.seen, search):
        return "optics search"
    if frame.seed is not None and frame.seed.refined is not None and frame.geometric:
        return "nominal verify"
    return "matchers"


def _nominal_verify(frame: FrameSolve) -> str:
    assert frame.seed is not None and frame.seed.refined is not None  # the rule that leads here
    out = verify_seed(frame.seed.refined, frame.seen, frame.params, frame.timings)
    if out is None or out.status is not Status.OK:
        return "matchers"
    frame.out = out
    return "refine optics" if frame.params.optics is not None else DONE


def _matchers(frame: FrameSolve) -> str:
    with_search = frame.params.optics is not None
    out = identify_with_camera(frame.seen, frame.params, frame.timings, defer_fallback=with_search)
    frame.out = out
    if not with_search or out.status is Status.TOO_FEW_STARS:
        return DONE
    return "refine optics" if out.status is Status.OK else "optics search"


def _optics_search(frame: FrameSolve) -> str:
    if not frame.searched:  # once a frame: a later visit reads its answer
        frame.searched = True
        frame.found = search_optics(frame.seen, frame.params, frame.timings, frame.peek, frame.seed)
    found, out = frame.found, frame.out
    if out is None:  # it went first
        if found is not None and found.status is Status.OK:
            frame.out = found
            return DONE
        return "matchers"
    if out.status is not Status.OK:
        return "fallback" if out.fallback_due and (found is None or found.status is not Status.OK) else "choose"
    if found is not None and found.status is Status.OK and ranks_above(found.solution, out.solution):
        frame.out = found  # a high-confidence answer only: the search may return a low one
    return DONE


def _fallback(frame: FrameSolve) -> str:
    assert frame.out is not None
    again = identify_with_camera(frame.seen, frame.params, frame.timings, fallback_only=True)
    if again.status is Status.NO_MATCH and NOT_A_STAR_FIELD in again.reason:  # said first
        why = again.reason[again.reason.index(NOT_A_STAR_FIELD) :]
        frame.out.reason = f"{why}; {frame.out.reason}" if frame.out.reason else why
    elif again.status is not Status.NO_MATCH:
        frame.out = again
        if again.status is Status.OK:
            frame.found = None  # the nominal camera's consensus answer: its optics are checked next
    return "choose"


def _choose(frame: FrameSolve) -> str:
    found, out = frame.found, frame.out
    assert out is not None
    if found is not None and (found.status is Status.OK or ranks_above(found.solution, out.solution)):
        frame.out = found
        return DONE
    return "refine optics" if out.status is Status.OK else DONE


def _refine(frame: FrameSolve) -> str:
    out = frame.out
    assert out is not None
    refined = refine_optics(out, frame.seen, frame.params, frame.timings)
    if refined is not None:
        frame.out = refined
        return DONE
    # too few stars matched to check the optics: a search may match more
    return "optics search" if out.optics is None and not frame.searched else DONE


#: The solve plan of one frame: the stages in the order the first runs, each one's counted budget,
#: and the rule that hands on to the next (docs/identification.md, "The solve plan", is this
#: table). Every search inside is bounded by counts; only flight timing adds a clock.
SOLVE_PLAN: tuple[PlanStage, ...] = (
    PlanStage(
        "prepare",
        "usable detections, the route (colour or geometric), the catalog's pattern index for the field "
        "(off the device, the whole-sky database's: no per-field index)",
        "one pass; the index once per catalog and field (a set-up stage, `index` in timings_s)",
        "at least 4 usable detections: pattern seed; else matchers",
        ("pattern seed", "matchers"),
        _prepare,
    ),
    PlanStage(
        "pattern seed",
        "the first tier's scale-free 4-star matches, rank by rank; the first one refined",
        "`first_tier` brightest detections, `first_tier_hypotheses` matches, 1 seed refined",
        "its refined optics would refit the nominal camera: optics search; on the geometric route: "
        "nominal verify; else matchers",
        ("optics search", "nominal verify", "matchers"),
        _pattern_seed,
    ),
    PlanStage(
        "nominal verify",
        "the refined seed's stars verified over the frame with the nominal camera",
        "1 verification (2 when the deep one is not high-confidence)",
        "high confidence: refine optics (done without the optics search); else matchers",
        ("refine optics", "matchers", DONE),
        _nominal_verify,
    ),
    PlanStage(
        "matchers",
        "strategy.identify with the nominal camera: colour consensus or 4-star voting then triangles, "
        "the photometric re-solve, deep verification (match_deep, adapt_noise); the mono fallback deferred",
        "`max_verifications` per solve",
        "high confidence: refine optics; else optics search; without the optics search or with too few stars: done",
        ("refine optics", "optics search", DONE),
        _matchers,
    ),
    PlanStage(
        "optics search",
        "pattern seeds best first, each refined (focal length, k1), verified, else identified with the "
        "fitted camera (runs once a frame)",
        "`max_seeds` seeds refined; no seed started past `max_frame_verifications` verifications",
        "run first: high confidence done, else matchers; after a failed answer: fallback when it is due "
        "and the search found none, else choose; after a high-confidence answer without optics: its "
        "answer taken when high-confidence with more stars, done",
        ("matchers", "fallback", "choose", DONE),
        _optics_search,
    ),
    PlanStage(
        "fallback",
        "the mono consensus on every detection's geometry with the nominal camera",
        "`max_verifications`",
        "choose",
        ("choose",),
        _fallback,
    ),
    PlanStage(
        "choose",
        "the search's answer against the nominal camera's",
        "none",
        "the search's when high-confidence or ranked higher: done; else refine optics when high "
        "confidence, done otherwise",
        ("refine optics", DONE),
        _choose,
    ),
    PlanStage(
        "refine optics",
        "focal length and k1 fitted to the answer's stars; the frame identified again with them when "
        "they replace the camera",
        "one fit; at most one re-identification (`max_verifications` per solve)",
        "refitted: done; no optics fit and the search not yet run: optics search; else done",
        ("optics search", DONE),
        _refine,
    ),
)


_PLAN_STAGES = {stage.name: stage for stage in SOLVE_PLAN}


def plan_table() -> str:
    """:data:`SOLVE_PLAN` as a Markdown table (docs/identification.md quotes it)."""
    rows = ["| stage | runs | budget (counted) | hands on |", "|---|---|---|---|"]
    rows += [f"| {s.name} | {s.runs} | {s.budget} | {s.rule} |" for s in SOLVE_PLAN]
    return "\n".join(rows)


def _accounted(out: PipelineOutput, timings: StageTimings, t0: float, stars: StarList) -> PipelineOutput:
    """``out`` with the frame's timings and counted work. An answer short of high confidence whose
    search a budget cut short says so first in its reason, as does any answer the flight-timing
    deadline cut short: a missed deadline is never hidden."""
    out.timings = timings
    told = timings.stopped is Stop.DEADLINE or out.status in (Status.NO_MATCH, Status.LOW_CONFIDENCE)
    if told and timings.stop_reason and not out.reason.startswith(timings.stop_reason):
        out.reason = f"{timings.stop_reason}; {out.reason}" if out.reason else timings.stop_reason
    timings.total = time.perf_counter() - t0 + stars.timings.get("total_s", 0.0)
    return out
