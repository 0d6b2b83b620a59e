"""The device's detection-to-attitude pipeline on one frame, and its result-structure fields.

``run_pipeline(frame, camera, catalog, params) -> PipelineOutput`` chains extraction
(detection, centroid and colour fit, camera model), the optional eq. 24 colour correction,
identification and attitude: the stages of :data:`SOLVE_PLAN`, each with its counted budget and
hand-off rule (``firmware_model.ident.strategy.identify`` decides the order of the matching methods
and the confidence; the optics search calls it again with a fitted camera). It never raises on
bad frames: the output carries a :class:`protocol.result.Status` and a reason.
``firmware_model.pipeline.result_fields`` maps an output onto the result structure.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.ident.attitude import solve_attitude
from firmware_model.ident.budget import Stop, stop_reason
from firmware_model.ident.consensus import NOT_A_STAR_FIELD, Outcome
from firmware_model.ident.solver import Method, Mode, SolveParams, SolveResult
from firmware_model.ident.strategy import (
    Detections,
    Identification,
    IdentifyTimings,
    StrategyParams,
    agrees,
    bound_roll,
    chance_refusal,
    estimated_noise_factor,
    geometric_detection_cap,
    hold_searched,
    identify,
    routes_geometric,
    solve_rows,
    verify_pattern,
)
from firmware_model.ident.strategy import warm_up as strategy_warm_up
from firmware_model.ident.verify import FieldOfView
from firmware_model.ident.verify import warm_up as verify_warm_up
from firmware_model.pipeline import scale_free
from firmware_model.pipeline.camera_fit import StarObservations
from firmware_model.pipeline.exclusion import ExclusionLimits, Recall, check_exclusion
from firmware_model.pipeline.extract import ExtractParams, StarList, extract_stars
from firmware_model.pipeline.extract import warm_up as extract_warm_up
from firmware_model.pipeline.frame_fit import fit_frame
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.reference_frames import rotation_angle
from protocol.result import Status
from protocol.star_flags import UNTRUSTED, StarFlag

#: Floor on the per-axis centroid noise fed to the solver (px): covers camera-model and
#: optical residuals that the photon-noise covariance of the fit does not know about.
CENTROID_SIGMA_FLOOR_PX = 0.1

#: Centroid noise assumed when the fit gave no covariance (centre-of-gravity fallback), px.
UNKNOWN_CENTROID_SIGMA_PX = 1.0
#: Floor for stars whose fit is flagged untrusted (saturated, blended, poor fit, edge), px. Such
#: stars keep their place in the geometry with this weight; saturated or blended stars lose
#: their colour (the identification then uses their geometry alone).
UNTRUSTED_CENTROID_FLOOR_PX = 0.5

#: Detections whose fitted centroid is less certain than this (px, 1-sigma) are not used.
MAX_CENTROID_SIGMA_PX = 3.0

#: Stage names reported in the result extension, in order (fields of :class:`StageTimings`).
STAGES = ("detect", "fit", "vectors", "identify", "attitude", "total")
#: Set-up stages a solve may pay for before its frame's own work, reported beside :data:`STAGES`
#: off the device (``timings_s``): ``index`` the catalog's pattern index for the field, ``catalog``
#: building or loading the catalog, ``compile`` loading or compiling the kernels. The device does
#: all three before it says ``listening`` or at a catalog COMMIT, so a GO reports none of them.
SETUP_STAGES = ("index", "catalog", "compile")


@dataclass
class StageTimings(IdentifyTimings):
    """Seconds per pipeline stage (:data:`STAGES`): detection, centroid fit, camera vectors (from
    the extraction), identification and attitude (every solve of the frame, the optics search's
    included), and the whole frame; then the set-up stages (:data:`SETUP_STAGES`), which ``total``
    includes: the whole time the caller waited."""

    detect: float = 0.0
    fit: float = 0.0
    vectors: float = 0.0
    total: float = 0.0
    index: float = 0.0
    catalog: float = 0.0
    compile: float = 0.0

    def to_dict(self) -> dict[str, float]:
        """``{stage: seconds}``: :data:`STAGES`, then the set-up stages that took any time."""
        out = {name: getattr(self, name) for name in STAGES}
        out.update({name: getattr(self, name) for name in SETUP_STAGES if getattr(self, name) > 0})
        return out


#: Pattern seeds one frame's optics search may refine (``OpticsSearch.max_seeds``).
MAX_SEEDS = 48
#: Verifications after which a frame starts no further seed (``OpticsSearch.max_verifications``).
MAX_FRAME_VERIFICATIONS = 2000


@dataclass(frozen=True)
class OpticsSearch:
    """Lost in space with a datasheet camera (focal length off by a few per cent, radial
    distortion and principal-point offset not modelled), as plate solvers do it.

    The brightest ``n_bright`` detections are matched as scale-free 4-star patterns: first the
    ``first_tier_hypotheses`` first pattern matches among the brightest ``first_tier`` detections,
    rank by rank (``scale_free.BrightFirstMatches``: the 4 brightest, then the patterns adding the
    5th, ... up to 70 patterns: a frame's brightest stars are its catalog's brightest, and on the
    tetra3 frames the first one is the answer), then the best among all ``n_bright`` (4845
    patterns; clutter such as a foreground tree can hold the brightest detections)
    (``firmware_model.pipeline.scale_free``: edge ratios within ``pattern_tolerance``, focal length
    within ``focal_range`` of the nominal; blended, failed-fit and edge detections are left out).
    The first tier's first match is refined (:func:`_first_seed`), and the search goes first when
    that refinement would refit the nominal camera (:func:`_nominal_off`: a nominal camera that
    cannot match would spend its matchers' whole search failing); else, on the geometric route,
    the refined match is verified with the nominal camera first (:func:`_verify_seed`), and the
    search runs after the nominal camera gives no high-confidence answer. Each pattern match,
    best first, seeds a predict-match-fit of the focal length (and k1 when at least
    ``k1_min_stars`` stars match) with the attitude; the refined match is verified over every detection and taken when it is high-confidence as a
    search-chosen match (``strategy.searched_confident``: the chance of a coincidence counted over
    the search's attempts), else the frame is identified from scratch with the fitted camera and
    the normal tight noise model (held to the same rule). Every solve reports the fitted optics
    and their 1-sigma (``PipelineOutput.optics``, from at least ``min_stars`` matched stars); when
    the fit moves a corner by more than ``refit_px`` (and 3 sigma of the fit) or fits the stars
    :data:`REFIT_RMS_RATIO` times better, the frame is identified again with it so stars the first
    camera missed are matched. The search is bounded by counted work, never by the clock: at most
    ``max_seeds`` pattern seeds refined, and no seed started once the frame has made
    ``max_verifications`` verifications (every solve's and pattern check's, ``IdentifyTimings``);
    docs/identification.md ("The solve plan") gives the worst case on this machine class, which
    keeps GO to result within the device's 2 s. ``focal_search 0`` on the device (``optics=None`` here) takes the camera as calibrated:
    no search and no refit; on the geometric route its first pattern match (``OpticsSearch()``'s
    first tier, refined to find its stars) is still verified with it before the matchers run."""

    focal_range: float = 0.05
    n_bright: int = 20
    pattern_tolerance: float = 0.01
    k1_min_stars: int = 6
    min_stars: int = 4
    refit_px: float = 1.0
    max_seeds: int = MAX_SEEDS
    max_verifications: int = MAX_FRAME_VERIFICATIONS
    first_tier: int = 8
    first_tier_hypotheses: int = 4


@dataclass
class OpticsFit:
    """Optics fitted to the matched stars of one solve: the camera (principal point held at the
    nominal one: on a narrow field it is degenerate with the attitude), 1-sigma of each fitted
    parameter (``f`` px, ``k1``), RMS residual (px), stars used, and ``focal_scale`` the focal
    length of the pattern match that found the answer over the nominal one (NaN: no search)."""

    camera: CameraModel
    sigmas: dict
    residual_rms_px: float
    n_stars: int
    focal_scale: float = float("nan")
    #: the attitude covariance (rad^2, sensor axes) the fitted parameters' uncertainty adds
    #: (``CalibrationResult.camera_attitude_covariance``)
    attitude_covariance: np.ndarray | None = None
    #: the fitted stars: detection rows (of the answer's star list) and catalog indices
    rows: np.ndarray | None = None
    cat: np.ndarray | None = None


@dataclass(frozen=True)
class PipelineParams:
    """Pipeline configuration. ``colour_beta`` is the eq. 24 correction (6 numbers) or None;
    ``solve`` is the solver configuration (its colour sigmas are raised to the catalog's design
    values, its field of view defaults to the camera's); the per-detection direction noise is derived from
    the fit covariance (with the floor ``centroid_floor_px``) unless ``fixed_sigma_px`` is set.

    ``photometric_gate`` (mag, or None to disable): a low-confidence consensus may be caused by
    detections fainter than the catalog holds, which the eta test of Enright & McVittie counts against the
    match. The pipeline then estimates every detection's magnitude from the zero point of the
    matched stars, drops those fainter than the catalog limit plus this margin, and solves
    again; the second answer is taken only if it is high-confidence and agrees with the first.

    ``geometric_density_factor``: the geometric (4-star) method sees only the brightest
    detections, this factor times the catalog stars expected in the field
    (``strategy.geometric_detection_cap``), in one solve (no 4/6/8 ladder). ``geometric_fallback``: when that 4-star match finds
    nothing, the consensus matcher of Enright & McVittie runs on geometry alone (colours unknown), which
    tolerates missing and extra stars far better; its answers are labelled
    ``geometric-consensus``. ``colour_fallback``: in ``auto`` mode a colour frame that the colour
    matcher cannot solve with high confidence (colours biased beyond the catalog's noise model,
    e.g. through the atmosphere before calibration, or gamma-encoded sRGB images) is solved on
    geometry alone, as a mono frame would be; that answer is taken when the colour matcher found
    none or when it is high-confidence.

    ``optics``: the uncalibrated-optics search and the per-solve focal-length/distortion fit
    (:class:`OpticsSearch`; None takes the camera as calibrated: neither runs).

    ``flight_deadline_s``: flight timing only (``st16-device --timing realistic``): seconds after
    the frame's extraction began past which every search stops (``budget.SearchBudget``) and the
    answer says the deadline was missed; None, the default: counted budgets alone, the same
    answer on any machine.

    ``exclusion``: the bright-body exclusion angles (``exclusion.ExclusionLimits``; None: no
    check, no BLINDED status)."""

    extract: ExtractParams = ExtractParams()
    solve: SolveParams = SolveParams()
    colour_beta: tuple | None = None
    fixed_sigma_px: float | None = None
    photometric_gate: float | None = 0.1
    geometric_density_factor: float = 1.5
    geometric_fallback: bool = True
    colour_fallback: bool = True
    optics: OpticsSearch | None = OpticsSearch()
    centroid_floor_px: float = CENTROID_SIGMA_FLOOR_PX
    flight_deadline_s: float | None = None
    exclusion: ExclusionLimits | None = ExclusionLimits()


@dataclass
class PipelineOutput:
    status: Status
    reason: str = ""
    stars: StarList | None = None
    used: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))  #: star rows given to the solver
    solution: SolveResult | None = None
    timings: StageTimings = field(default_factory=StageTimings)  #: seconds per stage (STAGES)
    colour_beta: tuple | None = None  #: the eq. 24 correction the matcher's colours went through
    camera: CameraModel | None = None  #: the camera model the answer was identified with
    optics: OpticsFit | None = None  #: focal length and distortion fitted to the matched stars
    planets: list = field(default_factory=list)  #: ``planets.PlanetLabel`` of detections on a planet / the moon
    fallback_due: bool = False  #: the mono consensus fallback was deferred (``_identify``'s ``defer_fallback``)
    omega: np.ndarray | None = None  #: body rate (rad/s, sensor axes) of a tracked answer (``tracking_run``)
    omega_covariance: np.ndarray | None = None  #: its 3x3 covariance ((rad/s)^2)
    in_fov: tuple = ()  #: bodies inside their exclusion angles (``exclusion.check_exclusion``)

    @property
    def ok(self) -> bool:
        return self.status is Status.OK

    @property
    def stopped(self) -> Stop:
        """What stopped a search of this frame early (``budget.Stop``), if anything."""
        return self.timings.stopped


def with_psf_sigma(params: PipelineParams, sigma_px: float | None) -> PipelineParams:
    """``params`` with the PSF Gaussian sigma fixed to ``sigma_px`` (an override of the per-frame
    measurement; None measures again)."""
    return replace(params, extract=replace(params.extract, psf_sigma_px=sigma_px))


def apply_colour_correction(rg, bg, beta):
    """Eq. 24 with ``beta = [b1..b6]``: ``rg' = b1 rg + b2 bg + b5``, ``bg' = b3 rg + b4 bg + b6``."""
    b = np.asarray(beta, dtype=float)
    return b[0] * rg + b[1] * bg + b[4], b[2] * rg + b[3] * bg + b[5]


def run_pipeline(
    frame: Frame,
    camera: CameraModel,
    catalog: OnboardCatalog,
    params: PipelineParams = PipelineParams(),
    recall: Recall | None = None,
) -> PipelineOutput:
    """Frame -> stars -> identification -> attitude (module docstring), then planet labelling and
    the bright-body exclusion check (``exclusion.check_exclusion``; ``recall``: the device's last
    attitude at this frame's time, for a frame that gives none)."""
    t0 = time.perf_counter()
    stars = frame_stars(frame, camera, params)
    if isinstance(stars, PipelineOutput):
        return stars  # a frame that does not fit the camera: nothing to check
    out = identify_stars(stars, camera, catalog, params)
    if frame.timestamp and out.solution is not None and out.solution.q_icrs_to_sensor is not None:
        out = label_planets_of(out, frame, catalog, params)
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


def label_planets_of(out: PipelineOutput, frame: Frame, catalog: OnboardCatalog, params: PipelineParams):
    """Label detections on a predicted planet or the moon at the frame's epoch (``planets``); if
    one of them was matched to a catalog star, identify again without them."""
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
        again = identify_stars(hidden, out.camera, catalog, params)
        again.stars = stars
        if again.optics is None:
            again.optics = out.optics
        out = again
    out.planets = labels
    return out


def identify_stars(
    stars: StarList, camera: CameraModel, catalog: OnboardCatalog, params: PipelineParams = PipelineParams()
) -> PipelineOutput:
    """Identification and attitude from extracted stars (``stars.vectors`` from ``camera``): the
    stages of :data:`SOLVE_PLAN`, in its order, each handing on by its rule."""
    t0 = time.perf_counter()
    frame = FrameSolve(
        stars,
        camera,
        catalog,
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
    """What the stages of one frame's solve share: the inputs, the frame's ledger (``timings``:
    seconds and counted work), the route, the first tier's pattern matches (``peek``) and their
    first refined seed, the answer so far (``out``) and the optics search's (``found``, once it
    ran: it runs at most once a frame)."""

    stars: StarList
    camera: CameraModel
    catalog: OnboardCatalog
    params: PipelineParams
    timings: StageTimings
    used: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    geometric: bool = False
    peek: scale_free.BrightFirstMatches | None = None
    seed: tuple[scale_free.Hypothesis, tuple | None] | None = None
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
    frame.used = _usable(frame.stars)
    frame.geometric = len(frame.used) >= 4 and routes_geometric(
        frame.params.solve.mode, frame.catalog, _has_colour(frame.stars, frame.used)
    )
    if _first_tier_search(frame) is not None:
        t1 = time.perf_counter()
        scale_free.catalog_patterns(frame.catalog, frame.camera)  # once per catalog and field: a set-up stage
        frame.timings.index = time.perf_counter() - t1
    if frame.params.flight_deadline_s is not None:  # from the frame's extraction, set-up stages excluded
        deadline = time.perf_counter() - frame.stars.timings.get("total_s", 0.0) + frame.params.flight_deadline_s
        frame.params = replace(frame.params, solve=replace(frame.params.solve, deadline=deadline))
    return "pattern seed" if len(frame.used) >= 4 else "matchers"


def _first_tier_search(frame: FrameSolve) -> OpticsSearch | None:
    """The first tier's settings: the optics search's, or on the geometric route a calibrated
    camera's (no search) default ones."""
    return frame.params.optics or (OpticsSearch() if frame.geometric else None)


def _pattern_seed(frame: FrameSolve) -> str:
    tier = _first_tier_search(frame)
    frame.peek = _first_tier(frame.stars, frame.camera, frame.catalog, tier, frame.timings)
    frame.seed = _first_seed(frame.stars, frame.camera, frame.catalog, tier, frame.timings, frame.peek)
    search = frame.params.optics
    if search is not None and _nominal_off(frame.peek, frame.seed, frame.stars, frame.camera, frame.catalog, search):
        return "optics search"
    if frame.seed is not None and frame.seed[1] is not None and frame.geometric:
        return "nominal verify"
    return "matchers"


def _nominal_verify(frame: FrameSolve) -> str:
    assert frame.seed is not None and frame.seed[1] is not None  # the rule that leads here
    out = _verify_seed(frame.seed[1], frame.stars, frame.camera, frame.catalog, frame.params, frame.timings)
    if out is None or out.status is not Status.OK:
        return "matchers"
    frame.out = out
    return "refine optics" if frame.params.optics is not None else DONE


def _matchers(frame: FrameSolve) -> str:
    with_search = frame.params.optics is not None
    out = _identify(frame.stars, frame.camera, frame.catalog, frame.params, frame.timings, defer_fallback=with_search)
    frame.out = out
    if not with_search or out.status is Status.TOO_FEW_STARS:
        return DONE
    return "refine optics" if out.status is Status.OK else "optics search"


def _optics_search(frame: FrameSolve) -> str:
    if not frame.searched:  # once a frame: a later visit reads its answer
        frame.searched = True
        frame.found = _search_optics(
            frame.stars, frame.camera, frame.catalog, frame.params, frame.timings, frame.peek, frame.seed
        )
    found, out = frame.found, frame.out
    if out is None:  # it went first
        if found is not None and found.status is Status.OK:
            frame.out = found
            return DONE
        return "matchers"
    if out.status is not Status.OK:
        return "fallback" if out.fallback_due and (found is None or found.status is not Status.OK) else "choose"
    if found is not None and found.status is Status.OK and _rank(found) > _rank(out):
        frame.out = found  # a high-confidence answer only: the search may return a low one
    return DONE


def _fallback(frame: FrameSolve) -> str:
    assert frame.out is not None
    again = _identify(frame.stars, frame.camera, frame.catalog, frame.params, frame.timings, fallback_only=True)
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
    if found is not None and (found.status is Status.OK or _rank(found) > _rank(out)):
        frame.out = found
        return DONE
    return "refine optics" if out.status is Status.OK else DONE


def _refine(frame: FrameSolve) -> str:
    out = frame.out
    assert out is not None
    refined = _refine_optics(out, frame.stars, frame.camera, frame.catalog, frame.params, frame.timings)
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


def _first_tier(
    stars: StarList, camera: CameraModel, catalog: OnboardCatalog, search: OpticsSearch | None, timings: StageTimings
) -> scale_free.BrightFirstMatches | None:
    """The first pattern matches of ``search`` (the ``first_tier`` brightest clean detections,
    rank by rank; None without one); the caller builds the catalog's patterns for the field and
    has at least four usable detections."""
    if search is None or search.first_tier <= 0 or search.first_tier_hypotheses <= 0:
        return None
    t1 = time.perf_counter()
    clean = pattern_rows(stars)
    peek = scale_free.BrightFirstMatches(
        stars.x[clean], stars.y[clean], camera, catalog, search.first_tier, search.pattern_tolerance, search.focal_range
    )
    timings.identify += time.perf_counter() - t1
    return peek


def _first_seed(
    stars: StarList,
    camera: CameraModel,
    catalog: OnboardCatalog,
    search: OpticsSearch | None,
    timings: StageTimings,
    peek: scale_free.BrightFirstMatches | None,
) -> tuple[scale_free.Hypothesis, tuple | None] | None:
    """The first tier's first hypothesis and its refinement (``scale_free.refine``: focal length
    and k1 fitted to every star it predicts; None when it finds too few stars, so that the search
    does not refine it again), or None (no search, no match)."""
    if search is None or peek is None:
        return None
    t1 = time.perf_counter()
    hyp = next(peek.hypotheses(1), None)
    timings.identify += time.perf_counter() - t1
    if hyp is None:
        return None
    t1 = time.perf_counter()
    refined = scale_free.refine(stars.x, stars.y, camera, hyp, catalog, k1_min_stars=search.k1_min_stars)
    timings.attitude += time.perf_counter() - t1
    timings.seeds += 1
    return hyp, refined


def _nominal_off(
    peek: scale_free.BrightFirstMatches | None,
    seed: tuple[scale_free.Hypothesis, tuple | None] | None,
    stars: StarList,
    camera: CameraModel,
    catalog: OnboardCatalog,
    search: OpticsSearch,
) -> bool:
    """Whether the nominal camera would be refitted (:func:`_refit_due`, :func:`_refine_optics`'s
    rule) on the first pattern match's refined stars (:func:`_first_seed`). A nominal camera that cannot
    match would spend its matchers' whole search failing (10-50 ms per tetra3 frame, measured), and
    one whose answer is refitted identifies the frame twice, so the search goes first. The refined
    camera, not the pattern's own scale: one pattern's scale is known to ~0.1 %. Without a
    refinement, the first tier's best key's focal length decides."""
    if seed is None or seed[1] is None:
        if peek is None or not np.isfinite(peek.best_f):
            return False
        return _corner_shift_px(camera, replace(camera, f=peek.best_f)) > search.refit_px
    fitted, rows, cat, fit = seed[1]
    refined = OpticsFit(fitted, fit.sigmas, fit.residual_rms_px, fit.n_observations, rows=rows, cat=cat)
    return _refit_due(camera, refined, stars, catalog, search)


def _refined_noise(params: PipelineParams, fit) -> PipelineParams:
    """``params`` without the search, the floor of the centroid noise raised to the per-axis RMS of
    a refinement's stars (``fit``, with the fitted unknowns' degrees of freedom): the refined
    optics leave residuals no centroid covariance knows about (coma, an unmodelled distortion,
    centroids noisier than announced), and the identification's gates and covariance must know."""
    dof = 2 * fit.n_observations - len(fit.sigmas) - 3
    rms_px = fit.residual_rms_px * np.sqrt(2 * fit.n_observations / max(dof, 1))
    return replace(params, optics=None, centroid_floor_px=max(params.centroid_floor_px, rms_px / np.sqrt(2.0)))


def _verify_seed(
    refined: tuple,
    stars: StarList,
    camera: CameraModel,
    catalog: OnboardCatalog,
    params: PipelineParams,
    timings: StageTimings,
) -> PipelineOutput | None:
    """The first pattern match's refinement (:func:`_first_seed`): its stars verified over the frame with
    the nominal ``camera`` and the refinement's noise floor (:func:`_verify_pattern`, the search's
    first attempt)."""
    _, rows, cat, fit = refined
    noise = _refined_noise(params, fit)
    out = _verify_pattern(stars, camera, rows, cat, catalog, noise, timings, 1)
    return None if out is None else _with_estimated_floor(out, noise, params)


def _identify(
    stars: StarList,
    camera: CameraModel,
    catalog: OnboardCatalog,
    params: PipelineParams,
    timings: StageTimings,
    defer_fallback: bool = False,
    fallback_only: bool = False,
) -> PipelineOutput:
    """One identification with one camera model (``strategy.identify``: the order of methods and
    fallbacks). ``defer_fallback``: leave the mono consensus fallback out (``fallback_due`` on the
    answer says it would have run); ``fallback_only``: run that fallback alone."""
    used = _usable(stars)
    if len(used) < 2:
        why = stars.reason or f"{len(stars)} detection(s)"
        return PipelineOutput(Status.TOO_FEW_STARS, f"too few stars: {why}", stars, used, camera=camera)
    strategy = StrategyParams(
        solve=_solve_params(stars, camera, catalog, params),
        photometric_gate=params.photometric_gate,
        geometric_cap=geometric_detection_cap(camera, catalog, params.geometric_density_factor),
        geometric_fallback=params.geometric_fallback,
        colour_fallback=params.colour_fallback,
        defer_fallback=defer_fallback,
    )
    det = _detections(used, stars, camera, params)
    if fallback_only:
        found = geometric_fallback(det, catalog, strategy, timings)
    else:
        found = identify(det, catalog, strategy, timings)
    sol, rows = found.solution, used[found.rows]
    if sol.status is Outcome.NO_MATCH:
        return PipelineOutput(
            Status.NO_MATCH,
            sol.reason,
            stars,
            rows,
            sol,
            colour_beta=params.colour_beta,
            camera=camera,
            fallback_due=found.fallback_due,
        )
    status = Status.OK if sol.status is Outcome.HIGH_CONFIDENCE else Status.LOW_CONFIDENCE
    return PipelineOutput(status, sol.reason, stars, rows, sol, colour_beta=params.colour_beta, camera=camera)


def geometric_fallback(
    det: Detections, catalog: OnboardCatalog, strategy: StrategyParams, timings: StageTimings
) -> Identification:
    """``strategy.geometric_fallback`` (the mono consensus on every detection's geometry), its
    NO_MATCH answer kept with the reason (a "not a star field" refusal is told)."""
    found = solve_rows(det, np.arange(len(det)), catalog, strategy, Mode.COLOUR, False, timings)
    if found.solution.status is Outcome.NO_MATCH:
        return Identification(SolveResult(Outcome.NO_MATCH, f"mono consensus fallback: {found.solution.reason}"))
    found.solution.method = Method.GEOMETRIC_CONSENSUS
    return found


def _usable(stars: StarList) -> np.ndarray:
    """Rows with a direction and a centroid known to better than :data:`MAX_CENTROID_SIGMA_PX` (a
    degenerate fit can report a finite centre with a covariance of tens of px^2, or a negative
    variance: on a steep stray-light gradient, -8e17 px^2 with no flag)."""
    if not len(stars):
        return np.empty(0, np.int64)
    diag = stars.cov_xy[:, [0, 1], [0, 1]]
    var = 0.5 * diag.sum(axis=1)
    known = ~(var > MAX_CENTROID_SIGMA_PX**2) & ~(diag < 0).any(axis=1)  # NaN (no covariance) stays: 1 px
    assert stars.vectors is not None  # extracted with a camera
    return np.flatnonzero(np.isfinite(stars.vectors).all(axis=1) & known)


def _with_camera(stars: StarList, camera: CameraModel) -> StarList:
    return replace(stars, vectors=camera.pixel_to_vector(stars.x, stars.y))


def _fit_optics(out: PipelineOutput, catalog: OnboardCatalog, search: OpticsSearch, known=None) -> OpticsFit | None:
    """Focal length (and k1 with enough stars) fitted with the attitude to the matched stars; stars
    off by more than :data:`OPTICS_OUTLIER_PX` (or 5 x the median) after a first fit (a blend, a
    saturated or badly fitted star the answer keeps with a wide noise floor) are left out of a second.
    ``known`` (detection rows, catalog indices, fit): a fit already made (the search's
    refinement), used for the first fit when it is of the same stars."""
    sol, stars, camera = out.solution, out.stars, out.camera
    if sol is None or len(sol.matched_det) < search.min_stars:
        return None
    assert stars is not None and camera is not None  # a solution comes with both
    rows, cat = out.used[sol.matched_det], sol.matched_cat
    res = None
    for _ in range(2):
        if known is not None and _same_stars(known[0], known[1], rows, cat):
            res, known = known[2], None
        else:
            obs = StarObservations(stars.x[rows], stars.y[rows], catalog.vec[cat])
            res = fit_frame(obs, camera, search.k1_min_stars)
        if res is None or not res.success or not np.isfinite(res.residual_rms_px):
            return None
        err = np.hypot(*res.residuals[0].T)
        keep = err <= max(OPTICS_OUTLIER_PX, 5.0 * statistics.median(err.tolist()))
        if keep.all() or keep.sum() < search.min_stars:
            break
        rows, cat = rows[keep], cat[keep]
    assert res is not None
    added = res.camera_attitude_covariance[0] if res.camera_attitude_covariance else None
    return OpticsFit(
        res.camera, res.sigmas, res.residual_rms_px, len(rows), attitude_covariance=added, rows=rows, cat=cat
    )


def _with_fitted_camera_uncertainty(
    out: PipelineOutput, catalog: OnboardCatalog, params: PipelineParams
) -> PipelineOutput:
    """``out``, an answer found with a camera fitted to this frame's stars, with its attitude solved
    again (same stars, same weights) through the camera of its optics fit (fitted to every matched
    star), that camera as the answer's, and the covariance the fitted parameters' uncertainty adds
    (``OpticsFit.attitude_covariance``), held to the roll bound again. The answer was identified
    with the camera the search fitted to a few stars; a focal length off by a few pixels tilts the
    attitude of an off-centre star field, and the solution's covariance treats its camera as exact
    (measured: 1 px noise, 21 stars, a focal length 9 px off, 4.1 sigma off)."""
    sol, fit, stars = out.solution, out.optics, out.stars
    if sol is None or sol.covariance is None or fit is None or fit.attitude_covariance is None or stars is None:
        return out
    added = np.asarray(fit.attitude_covariance)
    if not np.all(np.isfinite(added)):
        return out
    seen = _with_camera(stars, fit.camera)
    rows = out.used[sol.matched_det]
    sigma = np.hypot(_centroid_sigma_px(rows, stars, params), sol.noise_extra * fit.camera.f) / fit.camera.f
    assert seen.vectors is not None  # _with_camera sets them
    att = solve_attitude(seen.vectors[rows], catalog.vec[sol.matched_cat], sigma)
    sol.q_icrs_to_sensor, sol.residuals = att.q, att.residuals
    sol.covariance = np.asarray(sol.covariance) + added
    out.stars, out.camera = seen, fit.camera
    bound_roll(sol, params.solve.max_roll_sigma)
    return _held_low(out)


def _held_low(out: PipelineOutput) -> PipelineOutput:
    """``out`` low confidence, with its solution's reason, when it was OK but a later rule (the
    roll bound, the searched-confidence rule) held its solution below high confidence."""
    sol = out.solution
    if out.status is Status.OK and sol is not None and sol.status is not Outcome.HIGH_CONFIDENCE:
        out.status, out.reason = Status.LOW_CONFIDENCE, sol.reason
    return out


def _same_stars(rows_a, cat_a, rows_b, cat_b) -> bool:
    """Whether two matched sets pair the same detections with the same catalog stars."""
    a = sorted(zip(np.asarray(rows_a).tolist(), np.asarray(cat_a).tolist()))
    return a == sorted(zip(np.asarray(rows_b).tolist(), np.asarray(cat_b).tolist()))


#: Star residual (px) beyond which a star is left out of the optics fit (with 5 x the median).
OPTICS_OUTLIER_PX = 1.0


def _corner_shift_px(a: CameraModel, b: CameraModel) -> float:
    """Largest pixel displacement between two camera models over the array corners."""
    xs = np.array([0.0, a.width - 1.0, 0.0, a.width - 1.0])
    ys = np.array([0.0, 0.0, a.height - 1.0, a.height - 1.0])
    x2, y2 = b.vector_to_pixel(a.pixel_to_vector(xs, ys))
    return float(np.nanmax(np.hypot(x2 - xs, y2 - ys)))


def _corner_shift_sigma_px(fit: OpticsFit) -> float:
    """1-sigma displacement (px) of the farthest array corner from the fitted focal length's and
    k1's uncertainties (``r sigma_f / f`` and ``r (r / f)^2 sigma_k1`` at the corner radius ``r``)."""
    cam = fit.camera
    r = float(np.hypot(max(cam.cx + 0.5, cam.width - 0.5 - cam.cx), max(cam.cy + 0.5, cam.height - 0.5 - cam.cy)))
    sf, sk = fit.sigmas.get("f", 0.0), fit.sigmas.get("k1", 0.0)
    return float(np.hypot(r * sf / cam.f, r * (r / cam.f) ** 2 * sk))


def _moves_corners(camera: CameraModel, fit: OpticsFit, search: OpticsSearch) -> bool:
    """Whether fitted optics move the array's farthest corner from where ``camera`` puts it by more
    than ``refit_px`` and by more than 3 sigma of the fit (a focal length and k1 fitted to a few
    noisy stars move the corners by chance)."""
    shift = _corner_shift_px(camera, fit.camera)
    return shift > search.refit_px and shift > 3.0 * _corner_shift_sigma_px(fit)


#: The frame is identified again with the fitted optics when they fit this much better (RMS ratio).
REFIT_RMS_RATIO = 1.5


def _refit_due(
    camera: CameraModel, fit: OpticsFit, stars: StarList, catalog: OnboardCatalog, search: OpticsSearch
) -> bool:
    """Whether fitted optics replace ``camera``: they move the array's corners (:func:`_moves_corners`)
    or fit their stars (``fit.rows`` of ``stars`` on ``fit.cat``) :data:`REFIT_RMS_RATIO` times
    better than ``camera`` with its best attitude does: the same stars both ways (measured: an
    answer's own RMS counts the stars the optics fit leaves out, and flagged a camera the fit did
    not move on 2 of 8 tetra3 frames, each then identified again from scratch)."""
    if _moves_corners(camera, fit, search):
        return True
    assert fit.rows is not None and fit.cat is not None  # every OpticsFit of a solve names its stars
    x, y = stars.x[fit.rows], stars.y[fit.rows]
    nominal = solve_attitude(camera.pixel_to_vector(x, y), catalog.vec[fit.cat], 1.0)
    return nominal.rms * camera.f > REFIT_RMS_RATIO * fit.residual_rms_px


def _refine_optics(
    out: PipelineOutput,
    stars: StarList,
    camera: CameraModel,
    catalog: OnboardCatalog,
    params: PipelineParams,
    timings: StageTimings,
) -> PipelineOutput | None:
    """Attach the optics fit to a high-confidence ``out``; identify again with the fitted camera when
    it replaces ``camera`` (:func:`_refit_due`: a focal length and k1 fitted to a few noisy stars
    move the corners by chance, and a camera fitted to the noise would hide it from the
    identification's noise check); keep that answer if it is high-confidence and agrees
    (``strategy.agrees``): its camera fits the stars better by construction."""
    search, sol = params.optics, out.solution
    assert search is not None and sol is not None  # called with the optics fit on, for an answer
    fit = _fit_optics(out, catalog, search)
    out.optics = fit
    if fit is None or not _refit_due(camera, fit, stars, catalog, search):
        return None
    again = _identify(_with_camera(stars, fit.camera), fit.camera, catalog, params, timings)
    if again.status is Status.OK and again.solution is not None and agrees(again.solution, sol):
        again.optics = _fit_optics(again, catalog, search) or fit
        return _with_fitted_camera_uncertainty(again, catalog, params)
    return None


def _search_optics(
    stars: StarList,
    camera: CameraModel,
    catalog: OnboardCatalog,
    params: PipelineParams,
    timings: StageTimings,
    peek: scale_free.BrightFirstMatches | None = None,
    seed: tuple[scale_free.Hypothesis, tuple | None] | None = None,
) -> PipelineOutput | None:
    """The scale-free search of :class:`OpticsSearch`: the first pattern match that leads to a
    high-confidence answer with the fitted camera, else the low-confidence answer of a pattern
    match that explains the most stars (None when no pattern match verifies). ``peek``: the
    first tier's pattern matches when the caller has them (:func:`_first_tier`); ``seed``: its
    first hypothesis and its refinement, already made (:func:`_first_seed`)."""
    search = params.optics
    assert search is not None  # called with the optics search on (the caller built its patterns)
    tried: list[np.ndarray] = []
    best: tuple[PipelineOutput, float, PipelineParams] | None = None  # (answer, its pattern's focal scale, noise)
    for hyp in _pattern_seeds(stars, camera, catalog, search, timings, peek):
        if _search_spent(search, params.solve.deadline, timings):
            break
        if any(rotation_angle(hyp.a, a) < _SAME_SEED_RAD for a in tried):
            continue
        if seed is not None and hyp is seed[0]:  # the first tier keeps its hypotheses: the same object
            refined = seed[1]
        else:
            t1 = time.perf_counter()
            refined = scale_free.refine(stars.x, stars.y, camera, hyp, catalog, k1_min_stars=search.k1_min_stars)
            timings.attitude += time.perf_counter() - t1
            timings.seeds += 1
        if refined is None:
            continue
        tried.append(hyp.a)  # a seed near one that refined to a failed identification leads there too
        fitted, rows, cat, fit = refined
        seen = _with_camera(stars, fitted)
        tight = _refined_noise(params, fit)
        # the refined pattern match verified over the frame first (one verification); the frame
        # identified from scratch with the fitted camera only when that is not high-confidence
        pattern = _verify_pattern(seen, fitted, rows, cat, catalog, tight, timings, len(tried))
        if pattern is not None and pattern.status is Status.OK:
            out = pattern
        else:
            out = _identify(seen, fitted, catalog, tight, timings)
            if out.solution is not None and out.status is Status.OK:
                out.solution = hold_searched(out.solution, params.solve.consensus, len(tried))
                out = _held_low(out)
            if pattern is not None and _rank(pattern) > _rank(out):
                out = pattern
        if out.status is Status.OK:
            return _with_optics(out, hyp.f / camera.f, catalog, params, tight, (rows, cat, fit))
        if out.solution is not None and _rank(out) > _rank(best[0] if best else None):
            best = (out, hyp.f / camera.f, tight)
    if best is None:
        return None
    answer, scale, noise = best
    return _with_optics(answer, scale, catalog, params, noise)  # the optics of the answer only


def _search_spent(search: OpticsSearch, deadline: float | None, timings: StageTimings) -> bool:
    """Whether the optics search may start no further seed: its seeds or the frame's verifications
    counted up to their budgets, or (flight timing) the deadline passed; the stop is recorded."""
    if timings.seeds >= search.max_seeds:
        timings.stop(Stop.COUNT, stop_reason(Stop.COUNT, search.max_seeds, "pattern seed"), frame=True)
    elif timings.verifications >= search.max_verifications:
        reason = stop_reason(Stop.COUNT, search.max_verifications, "verification", " per frame")
        timings.stop(Stop.COUNT, reason, frame=True)
    elif deadline is not None and time.perf_counter() > deadline:
        timings.stop(Stop.DEADLINE, stop_reason(Stop.DEADLINE, 0, ""), frame=True)
    else:
        return False
    return True


def _with_optics(
    out: PipelineOutput,
    focal_scale: float,
    catalog: OnboardCatalog,
    params: PipelineParams,
    noise: PipelineParams,
    known=None,
) -> PipelineOutput:
    """``out`` with the optics fitted to its matched stars and the search's focal scale, its
    covariance widened by their uncertainty (:func:`_with_fitted_camera_uncertainty`, with
    ``noise``, the parameters it was identified with) and for its estimated noise floor
    (:func:`_with_estimated_floor`); ``known`` (detection rows, catalog indices, fit): a fit of some
    stars already made (the refinement's)."""
    assert params.optics is not None  # the search's answers
    out.optics = _fit_optics(out, catalog, params.optics, known)
    if out.optics is not None:
        out.optics.focal_scale = focal_scale
    return _with_estimated_floor(_with_fitted_camera_uncertainty(out, catalog, noise), noise, params)


def _with_estimated_floor(out: PipelineOutput, noise: PipelineParams, params: PipelineParams) -> PipelineOutput:
    """``out`` with its covariance widened for a centroid-noise floor estimated from a refinement's
    stars (``noise``'s floor above ``params``', :func:`_refined_noise`): the Student t factor of a
    noise estimated with ``2n - 3`` degrees of freedom over its ``n`` stars
    (``strategy.estimated_noise_factor``), unless ``adapt_noise`` estimated the noise itself."""
    sol = out.solution
    if sol is None or sol.covariance is None or sol.noise_extra > 0:
        return out
    if noise.centroid_floor_px <= params.centroid_floor_px:
        return out
    sol.covariance = np.asarray(sol.covariance) * estimated_noise_factor(2 * len(sol.matched_det) - 3)
    bound_roll(sol, params.solve.max_roll_sigma)
    return _held_low(out)


def _rank(out: PipelineOutput | None) -> tuple[int, float]:
    """Preference between low-confidence answers: stars matched, then the solution's confidence
    (coverage of the predicted stars times the share of detections explained); (0, 0) for none."""
    return (0, 0.0) if out is None or out.solution is None else (len(out.solution.matched_det), out.solution.confidence)


def _pattern_seeds(
    stars: StarList,
    camera: CameraModel,
    catalog: OnboardCatalog,
    search: OpticsSearch,
    timings: StageTimings,
    peek: scale_free.BrightFirstMatches | None = None,
):
    """Pattern hypotheses (``scale_free.pattern_matches``) from the brightest clean detections, then, when
    poor fits were among them (hot-pixel clusters and other unblurred clutter can outshine the
    stars), from the brightest detections that also fit the PSF well. ``peek``: the first tier's
    pattern matches of the first pass, already computed."""
    clean = pattern_rows(stars)  # clutter is blended or badly fitted
    well = clean[(stars.flags[clean] & int(StarFlag.POOR_FIT)) == 0]
    for rows in (clean, well):
        if rows is well and np.array_equal(well[: search.n_bright], clean[: search.n_bright]):
            return
        for n, most in ((search.first_tier, search.first_tier_hypotheses), (search.n_bright, 64)):
            if n <= 0 or most <= 0:
                continue
            found: scale_free.PatternMatches | scale_free.BrightFirstMatches
            if peek is not None and rows is clean and n == search.first_tier:
                found = peek
            elif n == search.first_tier:  # rank by rank, as the hypotheses are asked for (timed there)
                found = scale_free.BrightFirstMatches(
                    stars.x[rows], stars.y[rows], camera, catalog, n, search.pattern_tolerance, search.focal_range
                )
            else:
                t1 = time.perf_counter()
                found = scale_free.pattern_matches(
                    stars.x[rows], stars.y[rows], camera, catalog, n, search.pattern_tolerance, search.focal_range
                )
                timings.identify += time.perf_counter() - t1
            # one at a time (the first is usually it); the second pass repeats the first's best:
            # the caller skips seeds it tried
            yield from _timed(found.hypotheses(most), timings)


def _timed(hypotheses, timings: StageTimings):
    """The hypotheses of a generator, the time to work each out added to ``timings.identify``."""
    while True:
        t1 = time.perf_counter()
        hyp = next(hypotheses, None)
        timings.identify += time.perf_counter() - t1
        if hyp is None:
            return
        yield hyp


def _verify_pattern(
    stars: StarList,
    camera: CameraModel,
    rows,
    cat,
    catalog: OnboardCatalog,
    params: PipelineParams,
    timings: StageTimings,
    attempts: int,
) -> PipelineOutput | None:
    """The refined pattern match itself (detection ``rows`` on catalog stars ``cat``, the search's
    attempt ``attempts``), verified over every usable detection with the fitted camera and the
    tight noise model and judged by ``strategy.verify_pattern`` (method "pattern"), or None when
    verification refuses it."""
    used = _usable(stars)
    rows, cat = np.asarray(rows), np.asarray(cat)
    usable = np.zeros(len(stars), bool)
    usable[used] = True
    inside = usable[rows]
    sol = verify_pattern(
        _detections(used, stars, camera, params),
        np.searchsorted(used, rows[inside]),
        cat[inside],
        catalog,
        _solve_params(stars, camera, catalog, params),
        timings,
        attempts,
    )
    if sol is None:
        return None
    status = Status.OK if sol.status is Outcome.HIGH_CONFIDENCE else Status.LOW_CONFIDENCE
    return PipelineOutput(status, sol.reason, stars, used, sol, colour_beta=params.colour_beta, camera=camera)


#: Detections left out of the pattern search's brightest stars (saturated stars stay: they are real).
_PATTERN_EXCLUDE = int(StarFlag.BLEND | StarFlag.FIT_FAILED | StarFlag.EDGE)


def pattern_rows(stars: StarList) -> np.ndarray:
    """Rows of the detections fit to make patterns of (blended, failed-fit and edge ones left out)."""
    return np.flatnonzero((stars.flags & _PATTERN_EXCLUDE) == 0)


#: Pattern seeds whose attitudes differ by less than this (rad) lead to the same refined answer.
_SAME_SEED_RAD = np.radians(0.2)


def _solve_params(stars: StarList, camera: CameraModel, catalog: OnboardCatalog, params: PipelineParams):
    """The solver configuration for ``stars``: the field of view defaults to the camera's, the
    colour noise is at least the catalog's design value (``strategy.identify`` raises it further to
    the median colour sigma the fit measured), verification knows the frame's detection count
    (the solver may see only the brightest)."""
    return replace(
        params.solve,
        fov=params.solve.fov or FieldOfView.from_camera(camera),
        sigma_rg=_larger(params.solve.sigma_rg, catalog.meta.get("sigma_rg")),
        sigma_bg=_larger(params.solve.sigma_bg, catalog.meta.get("sigma_bg")),
        verify=replace(params.solve.verify, frame_detections=len(stars)),
    )


def _larger(value: float, design: float | None) -> float:
    """The larger of a configured noise and a catalog's design value (None or NaN: not set)."""
    known = [float(v) for v in (value, design) if v is not None and not math.isnan(v)]
    return max(known) if known else float("nan")


def _detections(used: np.ndarray, stars: StarList, camera: CameraModel, params: PipelineParams) -> Detections:
    """What identification sees of the ``used`` rows of ``stars``.

    Saturated or blended stars keep their geometry but lose their colour; colours go through the
    eq. 24 correction; the per-star centroid noise comes from the fit covariance with a floor,
    larger for untrusted fits (or is ``fixed_sigma_px``); the measured colour sigmas let the
    matcher widen its colour noise (a small aperture leaves 4th-magnitude stars with ~0.1 colour
    noise; matching them at 0.05 rejects true matches)."""
    flags = stars.flags[used]
    colour_ok = (flags & int(StarFlag.SATURATED | StarFlag.BLEND)) == 0
    rg = np.where(colour_ok, stars.rg[used], np.nan)
    bg = np.where(colour_ok, stars.bg[used], np.nan)
    if params.colour_beta is not None:
        rg, bg = apply_colour_correction(rg, bg, params.colour_beta)
    colour_sigma = np.sqrt(np.where(colour_ok[:, None], stars.cov_colour[used][:, [0, 1], [0, 1]], np.nan))
    assert stars.vectors is not None  # extracted with a camera
    return Detections(
        vectors=stars.vectors[used],
        rg=rg,
        bg=bg,
        sigma_px=_centroid_sigma_px(used, stars, params),
        focal_px=camera.f,
        flux=stars.flux[used],
        colour_sigma=colour_sigma,
        measured_colour=_has_colour(stars, used),
    )


def _centroid_sigma_px(rows: np.ndarray, stars: StarList, params: PipelineParams) -> np.ndarray:
    """Per-axis centroid noise (px) of ``rows`` of ``stars``: from the fit covariance with a floor,
    larger for untrusted fits (or ``fixed_sigma_px``)."""
    if params.fixed_sigma_px is not None:
        return np.full(len(rows), float(params.fixed_sigma_px))
    var = 0.5 * (stars.cov_xy[rows, 0, 0] + stars.cov_xy[rows, 1, 1])
    var = np.where(np.isfinite(var), var, UNKNOWN_CENTROID_SIGMA_PX**2)
    floor = np.where(
        (stars.flags[rows] & int(UNTRUSTED)) != 0,
        max(UNTRUSTED_CENTROID_FLOOR_PX, params.centroid_floor_px),
        params.centroid_floor_px,
    )
    return np.sqrt(var + floor**2)


def _has_colour(stars: StarList, used: np.ndarray | None = None) -> bool:
    """Whether the frame measured colour on its ``used`` rows (default: the usable ones)."""
    return bool(np.isfinite(stars.rg[_usable(stars) if used is None else used]).any())
