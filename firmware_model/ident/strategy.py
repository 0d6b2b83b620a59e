"""Where a solve is decided: the order of the matching methods, their fallbacks and the
confidence of the answer, for one set of star vectors (:func:`solve`) and for one frame's
detections (:func:`identify`). The matchers themselves live in their modules (``consensus``,
``four_star``, ``triangle``, ``verify``, ``attitude``); each stage here is a small function with
typed inputs and outputs, composed top-down:

``identify(IdentificationInput, catalog, StrategyParams) -> Identification`` (the device
pipeline, the whole-sky simulation), steps 1-5:

1. route: geometric when the mode says so, or in ``auto`` mode when the catalog or the frame has no
   colour; else colour (:func:`colour_route`).
2. colour route: :func:`solve_rows` on every detection (the solver decides colour consensus),
   with the photometric gate; in ``auto`` mode, an answer that is not high confidence is tried
   against the geometric route on the same detections (``colour_fallback``): that answer is taken
   when colour found none or geometry is high-confidence.
3. geometric route (:func:`geometric_route`): one :func:`solve_rows` on the brightest detections up
   to the density cap (no ladder: the matchers rank their hypotheses brightest first and stop at
   the first decisive verified set; :func:`brightest_eta` keeps the brightness preference in the
   confidence); the answer is verified again over every detection (:func:`match_all`).
4. mono fallback: a geometric route that found nothing runs the consensus matcher on geometry
   alone (``geometric_fallback``; method ``geometric-consensus``). With ``defer_fallback`` the
   answer instead comes back with ``fallback_due`` set and the caller runs the fallback itself
   (:func:`geometric_fallback`, which answers NO_MATCH with its own reason when it finds nothing)
   when its cheaper methods fail: the pipeline's optics search tries its pattern hypotheses first
   when the nominal camera fails.
5. every star in view and the frame's own noise (:func:`finish`): a high-confidence answer is
   verified again against every catalog star, the verification-only stars fainter than the
   pattern stars included (:func:`match_deep`); one whose stars, looked for with wider gates,
   reject the announced centroid noise is verified again with the noise they show
   (:func:`adapt_noise`, ``SolveParams.noise_probe_px``).

Every answer is held to the roll bound (:func:`bound_roll`, ``SolveParams.max_roll_sigma``): high
confidence needs the attitude's own roll sigma within it.

``solve_rows`` is one :func:`solve` on a subset plus the photometric gate: a low-confidence answer
is solved again without detections fainter than the catalog holds (zero point from the matched
stars) and that answer is taken if it is high-confidence and agrees.

``solve(vectors, rg, bg, catalog, SolveParams) -> SolveResult``: clean the input
(``solver.clean``), choose the method (:func:`choose_method`), then colour consensus
(``consensus.match_scene``, whose high / low confidence is decided as it searches: it stops at
the first confident set) or geometric matching (:func:`match_geometric`: 4-star voting, then the
triangle fallback when that is not conclusive), and the geometric confidence
(:func:`decide_geometric`). It never raises on bad input: it answers NO_MATCH with a reason.

The pipeline's optics search (``firmware_model.pipeline.optics_search``) judges its refined
pattern matches with :func:`verify_pattern` and answers found with a camera fitted to one with
:func:`hold_searched` (both by :func:`searched_confident`), calling :func:`identify` with the
fitted camera when the pattern alone is not high-confidence; an answer identified with a noise
floor estimated from its own stars has its covariance widened (:func:`widen_for_estimated_noise`),
and the search and the solve plan prefer one answer short of high confidence to another by
:func:`ranks_above`.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit
from scipy.special import ndtr, stdtrit

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog, angle_between
from firmware_model.ident.attitude import covariance_kernel, quat_matrix, solve_attitude
from firmware_model.ident.budget import SearchBudget, Stop, stop_reason
from firmware_model.ident.consensus import (
    CHANCE_ANSWERS,
    NOT_A_STAR_FIELD,
    ConsensusParams,
    Outcome,
    chance_answers,
    confident,
    match_scene,
)
from firmware_model.ident.four_star import match_four_star
from firmware_model.ident.pair_match import PairNoise
from firmware_model.ident.solver import (
    Method,
    Mode,
    SolveParams,
    SolveResult,
    SolveTimings,
    clean,
    solution_from_match,
)
from firmware_model.ident.triangle import match_triangles
from firmware_model.ident.verify import FieldOfView, VerifiedMatch, miss_tail, verify
from firmware_model.reference_frames import rotation_angle

#: Fewest detections given to the geometric matcher by :func:`geometric_detection_cap`.
MIN_GEOMETRIC_DETECTIONS = 8

#: A hypothesis check: detection indices and catalog indices -> (verified match or None, reason).
Check = Callable[[np.ndarray, np.ndarray], tuple[VerifiedMatch | None, str]]


# ------------------------------------------------------------------ inputs and outputs
@dataclass(frozen=True)
class IdentificationInput:
    """One frame's detections as identification sees them, brightest first.

    vectors (N, 3) sensor-frame directions; rg, bg (N,) colour ratios (NaN: no usable colour);
    sigma_px (N,) per-axis centroid noise (px) with ``focal_px`` the focal length they scale by
    (None: the solver parameters' ``sigma_vec`` as given); flux (N,) for the photometric gate
    (None: no gate); colour_sigma (N, 2) measured 1-sigma of rg, bg (NaN where unknown; their
    median raises the colour noise the matcher assumes; None: the parameters' as given);
    measured_colour: whether the frame measured colour, which routes ``auto`` mode (None: any
    finite ``rg``)."""

    vectors: np.ndarray
    rg: np.ndarray
    bg: np.ndarray
    sigma_px: np.ndarray | None = None
    focal_px: float = 1.0
    flux: np.ndarray | None = None
    colour_sigma: np.ndarray | None = None
    measured_colour: bool | None = None

    def __len__(self) -> int:
        return len(self.vectors)

    @property
    def has_colour(self) -> bool:
        if self.measured_colour is not None:
            return self.measured_colour
        return bool(np.isfinite(self.rg).any())


@dataclass(frozen=True)
class StrategyParams:
    """How :func:`identify` orders the methods.

    solve: the solver configuration (``mode`` picks the route); photometric_gate: margin (mag)
    beyond the catalog limit for the gate, None to disable; geometric_cap: the brightest detections
    the geometric route gives its matchers (None: every detection); geometric_fallback: consensus
    on geometry alone when the geometric route finds nothing; colour_fallback: in ``auto`` mode,
    the geometric route when colour is not high-confidence; defer_fallback: leave that consensus
    to the caller (``Identification.fallback_due``)."""

    solve: SolveParams = SolveParams()
    photometric_gate: float | None = None
    geometric_cap: int | None = None
    geometric_fallback: bool = True
    colour_fallback: bool = True
    defer_fallback: bool = False


@dataclass
class IdentifyTimings:
    """What identifying one frame cost, summed over every solve: seconds (``identify`` matching and
    input cleaning, ``attitude`` verification and attitude; measured, never enforced) and the
    counted work that bounds it (the frame's ledger): ``verifications`` made, pattern ``seeds``
    refined, and the first thing that stopped a search early (``budget.Stop``)."""

    identify: float = 0.0
    attitude: float = 0.0
    verifications: int = 0
    seeds: int = 0
    stopped: Stop = Stop.NONE
    stop_reason: str = ""

    def add_solve(self, sol: SolveResult) -> None:
        self.identify = self.identify + sol.timings.match + sol.timings.validate
        self.attitude += sol.timings.verify
        self.verifications += sol.verifications
        if sol.stopped is not Stop.NONE:
            self.stop(sol.stopped, stop_reason(sol.stopped, sol.verifications, "verification"))

    def stop(self, why: Stop, reason: str, frame: bool = False) -> None:
        """Record what stopped a search and why: the first solve's stop, unless a ``frame`` budget
        (one that ends the frame's whole search) stopped it, which the answer names instead."""
        if self.stopped is Stop.NONE or frame:
            self.stopped, self.stop_reason = why, reason


@dataclass
class Identification:
    """The answer of :func:`identify`: the solution (status NO_MATCH when none) and the detections
    (indices into :class:`IdentificationInput`) its ``matched_det`` refers to. ``fallback_due``: the mono
    fallback would have run but was deferred (``StrategyParams.defer_fallback``)."""

    solution: SolveResult
    rows: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    fallback_due: bool = False

    @property
    def status(self) -> Outcome:
        return self.solution.status


# ------------------------------------------------------------------ one frame
def routes_geometric(mode: str, catalog: OnboardCatalog, measured_colour: bool) -> bool:
    """Whether a frame takes the geometric route: the mode asks for it, or in ``auto`` mode the
    catalog or the frame (``measured_colour``) has no colour."""
    return mode == Mode.GEOMETRIC or (mode == Mode.AUTO and (not catalog.has_colour or not measured_colour))


def identify(
    det: IdentificationInput, catalog: OnboardCatalog, params: StrategyParams, timings: IdentifyTimings | None = None
) -> Identification:
    """The order of methods and fallbacks for one frame (module docstring, steps 1-5)."""
    timings = timings if timings is not None else IdentifyTimings()
    mode = params.solve.mode
    geometric = routes_geometric(mode, catalog, det.has_colour)
    if geometric:
        found = geometric_route(det, catalog, params, timings)
    else:
        found = colour_route(det, catalog, params, timings)
        if found.status is not Outcome.HIGH_CONFIDENCE and params.colour_fallback and mode == Mode.AUTO:
            # colours biased beyond the catalog's noise model (the atmosphere, an sRGB image): geometry alone
            geo = geometric_route(
                det, catalog, replace(params, solve=replace(params.solve, mode=Mode.GEOMETRIC)), timings
            )
            if found.status is Outcome.NO_MATCH or geo.status is Outcome.HIGH_CONFIDENCE:
                geometric, found = True, geo
    if geometric and found.status is Outcome.NO_MATCH and params.geometric_fallback and catalog.has_colour:
        if params.defer_fallback:
            found.fallback_due = True
        else:
            fallback = geometric_fallback(det, catalog, params, timings)
            if fallback.status is not Outcome.NO_MATCH:
                found = fallback
    return finish(found, det, catalog, params.solve, timings)


def geometric_fallback(
    det: IdentificationInput, catalog: OnboardCatalog, params: StrategyParams, timings: IdentifyTimings
) -> Identification:
    """Step 4, the mono fallback: the consensus matcher on every detection's geometry alone
    (method ``geometric-consensus``). When it finds nothing, a NO_MATCH answer on no detection
    whose reason is the fallback's (a "not a star field" refusal is told)."""
    again = solve_rows(det, np.arange(len(det)), catalog, params, Mode.COLOUR, False, timings)
    if again.status is Outcome.NO_MATCH:
        return Identification(SolveResult(Outcome.NO_MATCH, f"mono consensus fallback: {again.solution.reason}"))
    again.solution.method = Method.GEOMETRIC_CONSENSUS
    return again


def colour_route(det: IdentificationInput, catalog: OnboardCatalog, params: StrategyParams, timings: IdentifyTimings):
    """Every detection with its colour, in the configured mode (the solver picks the method)."""
    return solve_rows(det, np.arange(len(det)), catalog, params, params.solve.mode, True, timings)


def geometric_route(
    det: IdentificationInput, catalog: OnboardCatalog, params: StrategyParams, timings: IdentifyTimings
) -> Identification:
    """Geometric matching on the brightest detections up to the density cap, in one solve: the
    matchers rank their hypotheses themselves (4-star groups, then triads brightest first, each
    verified over every detection given, the search ending at the first decisive set), so a
    hypothesis from the brightest stars is tried first without a ladder of smaller solves. An
    answer is then matched over every detection (:func:`match_all`)."""
    n = len(det) if params.geometric_cap is None else min(params.geometric_cap, len(det))
    found = solve_rows(det, np.arange(n), catalog, params, params.solve.mode, False, timings)
    return found if found.status is Outcome.NO_MATCH else match_all(found, det, catalog, params.solve, timings)


def solve_rows(
    det: IdentificationInput,
    rows: np.ndarray,
    catalog: OnboardCatalog,
    params: StrategyParams,
    mode: Mode | str,
    use_colour: bool,
    timings: IdentifyTimings,
) -> Identification:
    """One :func:`solve` on detections ``rows`` (their colours only when ``use_colour``), and the
    photometric gate: a low-confidence answer is solved again on the detections bright enough to
    be catalog stars, and that answer taken if it is high-confidence and agrees."""
    rg, bg, sp = _rows_inputs(det, rows, params.solve, mode, use_colour)

    def run(sub: np.ndarray) -> SolveResult:
        sigma = sp.sigma_vec if np.ndim(sp.sigma_vec) == 0 else np.asarray(sp.sigma_vec)[sub]
        out = solve(det.vectors[rows[sub]], rg[sub], bg[sub], catalog, replace(sp, sigma_vec=sigma))
        timings.add_solve(out)
        return out

    sol = run(np.arange(len(rows)))
    if sol.status is Outcome.LOW_CONFIDENCE and params.photometric_gate is not None and det.flux is not None:
        gated = photometric_gate(det.flux[rows], sol, catalog, params.photometric_gate)
        if gated is not None and 2 <= len(gated) < len(rows):
            sol2 = run(gated)
            if sol2.status is Outcome.HIGH_CONFIDENCE and same_attitude(sol, sol2, _tolerance(det, rows, sp)):
                return Identification(sol2, rows[gated])
    return Identification(sol, rows)


def _rows_inputs(det: IdentificationInput, rows: np.ndarray, base: SolveParams, mode: Mode | str, use_colour: bool):
    """Colours and solver parameters for ``rows``: the per-detection direction noise, and the
    colour noise raised to the median colour sigma measured on these detections (faint stars
    through a small aperture are noisier in colour than the catalog's design value, and matching
    them at that value rejects true matches; docs/identification.md)."""
    n = len(rows)
    rg = det.rg[rows] if use_colour else np.full(n, np.nan)
    bg = det.bg[rows] if use_colour else np.full(n, np.nan)
    sp = replace(base, mode=mode)
    if det.sigma_px is not None:
        sp = replace(sp, sigma_vec=det.sigma_px[rows] / det.focal_px)
    if det.colour_sigma is not None:
        measured = det.colour_sigma[rows] if use_colour else np.full((n, 2), np.nan)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN: no colour measured
            frame_rg, frame_bg = np.nanmedian(measured, axis=0)
        sp = replace(
            sp,
            sigma_rg=float(np.nanmax([base.sigma_rg, frame_rg])),
            sigma_bg=float(np.nanmax([base.sigma_bg, frame_bg])),
        )
    return rg, bg, sp


def _tolerance(det: IdentificationInput, rows: np.ndarray, sp: SolveParams) -> float:
    """Attitude agreement between two answers on the same stars: 5 x the largest centroid noise."""
    if det.sigma_px is not None:
        return 5 * float(np.max(det.sigma_px[rows])) / det.focal_px
    return 5 * float(np.max(sp.sigma_vec))


def match_all(
    found: Identification,
    det: IdentificationInput,
    catalog: OnboardCatalog,
    base: SolveParams,
    timings: IdentifyTimings,
) -> Identification:
    """An answer found on the brightest detections verified again over every detection, so every
    star in view is matched and the final attitude uses them all; the answer stands if that
    verification fails, finds fewer stars or moves the attitude. An answer held below high
    confidence by the roll bound alone is judged again on the wider set (:func:`bound_roll`)."""
    sol, rows = found.solution, found.rows
    if len(rows) >= len(det):
        return found
    everything = np.arange(len(det))
    match = verify_over(det, rows[sol.matched_det], sol.matched_cat, catalog, base, timings)
    if (
        match is None
        or match.n < len(sol.matched_det)
        or rotation_angle(match.attitude.a, quat_matrix(sol.q_icrs_to_sensor)) > _tolerance(det, everything, base)
    ):
        return found
    status, reason = (Outcome.HIGH_CONFIDENCE, "") if sol.roll_limited else (sol.status, sol.reason)
    full = solution_from_match(match, status, reason, everything, catalog, sol.method, len(det))
    full.attempts, full.timings, full.notes = sol.attempts, sol.timings, sol.notes
    return Identification(bound_roll(full, base.max_roll_sigma), everything)


def finish(
    found: Identification,
    det: IdentificationInput,
    catalog: OnboardCatalog,
    base: SolveParams,
    timings: IdentifyTimings,
) -> Identification:
    """A decided answer matched against every catalog star (:func:`match_deep`), then held to
    the noise its stars show (:func:`adapt_noise`), both verifications over every catalog star."""
    deep = _deep(base, catalog)
    return adapt_noise(match_deep(found, det, catalog, deep, timings), det, catalog, deep, timings)


def _deep(base: SolveParams, catalog: OnboardCatalog) -> SolveParams:
    """``base`` verifying against every catalog star when the catalog has verification-only stars."""
    return replace(base, verify=replace(base.verify, deep=True)) if catalog.has_deep_stars else base


def match_deep(
    found: Identification,
    det: IdentificationInput,
    catalog: OnboardCatalog,
    base: SolveParams,
    timings: IdentifyTimings,
) -> Identification:
    """A decided answer (high confidence, or held low by the roll bound alone) verified again over
    every detection against every catalog star, the verification-only stars below the pattern
    stars included, so the attitude uses every star in view. The decision is the pattern stars':
    confidence and chance stay as decided, coverage counts pattern stars as before. The answer
    stands when the catalog has no verification-only stars, that verification fails or finds no
    more stars, or it does not keep every star of the answer (:func:`keeps_stars`)."""
    sol = found.solution
    high = sol.status is Outcome.HIGH_CONFIDENCE or sol.roll_limited
    if not (catalog.has_deep_stars and high and base.verify.deep):
        return found
    match = verify_over(det, found.rows[sol.matched_det], sol.matched_cat, catalog, base, timings)
    if (
        match is None
        or match.n <= len(sol.matched_det)
        or not keeps_stars(match, found.rows[sol.matched_det], sol.matched_cat)
    ):
        return found
    everything = np.arange(len(det))
    status, reason = (Outcome.HIGH_CONFIDENCE, "") if sol.roll_limited else (sol.status, sol.reason)
    out = solution_from_match(match, status, reason, everything, catalog, sol.method, len(det))
    out.chance, out.attempts, out.timings, out.notes = sol.chance, sol.attempts, sol.timings, sol.notes
    return Identification(bound_roll(out, base.max_roll_sigma), everything, found.fallback_due)


#: The announced centroid noise is rejected when the chance of so many stars beyond its
#: :data:`NOISE_TAIL` quantile is below this.
NOISE_TEST_ALPHA = 0.01
#: Tail probability of a star's chi^2 (2 degrees of freedom) the noise test counts stars beyond.
NOISE_TAIL = 0.1
#: chi^2 (2 degrees of freedom) beyond which a star lies in that tail: ``-2 ln NOISE_TAIL``.
_TAIL_CHI2 = float(-2.0 * np.log(NOISE_TAIL))


def adapt_noise(
    found: Identification,
    det: IdentificationInput,
    catalog: OnboardCatalog,
    base: SolveParams,
    timings: IdentifyTimings,
) -> Identification:
    """An answer held to the noise its own stars show, when that is more than announced (a
    defocused or smeared frame, centroids from another extractor, a wrong noise model): the
    announced noise sets every gate, so a frame noisier than announced loses its stars to them
    and keeps the few that happen to fit, with a roll too loose for the covariance it reports.

    1. Probe: verify the answer again over every detection with ``noise_probe_px`` (per axis)
       added in quadrature to every detection's noise, so the stars of a noisier frame are found.
    2. Test (:func:`noise_rejected`): how many probed stars lie beyond the :data:`NOISE_TAIL`
       quantile of their announced noise; a binomial tail below :data:`NOISE_TEST_ALPHA` rejects the
       announced noise. A count, so a false star inside the wide probe gates weighs one star.
    3. Estimate (:func:`extra_noise`): the extra per-axis noise ``e`` that brings the median of
       the stars' chi^2 to its expected value (the median: robust to a false star and to the
       probe's gates, which cut the tail, not the middle), and verify again with ``e`` added:
       tight gates in units of the noise the frame has, and an attitude and covariance weighted by it,
       the covariance widened for a noise estimated from the answer's own stars
       (:func:`estimated_noise_factor` with the median's degrees of freedom, :data:`MEDIAN_DOF`).

    Only high-confidence answers (or those held low by the roll bound alone) are checked: a
    low-confidence answer may be a wrong match, whose residuals would read as noise and whose
    wider gates would gather more wrong stars. The answer stays high-confidence, held again to the
    roll bound with the new covariance; it stands unchanged when the test passes or the estimate
    exceeds twice the probe (residuals the probe did not look for: a wrong match's). When the
    verification with the estimated noise fails or does not keep all the answer's stars
    (:func:`keeps_stars`), the answer keeps its stars, re-solved and its covariance widened with the
    estimated noise: the rejected one would leave it too tight (docs/identification.md)."""
    sol = found.solution
    probe = base.noise_probe_px
    high = sol.status is Outcome.HIGH_CONFIDENCE or sol.roll_limited
    if not high or det.sigma_px is None or probe <= 0 or len(sol.matched_det) < 3:
        return found
    if _probe_cannot_reject(found, det, catalog, base):
        return found
    sigma = np.asarray(det.sigma_px, float)  # px
    everything = np.arange(len(det))
    seen = verify_over(
        replace(det, sigma_px=np.hypot(sigma, probe)),
        found.rows[sol.matched_det],
        sol.matched_cat,
        catalog,
        base,
        timings,
    )
    if seen is None or not noise_rejected(seen.attitude.residuals * det.focal_px, sigma[seen.det]):
        return found
    extra = extra_noise(seen.attitude.residuals * det.focal_px, sigma[seen.det])
    if extra > 2.0 * probe:  # beyond what the probe looked for: residuals of a wrong match, not noise
        return found
    tuned_px = np.hypot(sigma, extra)
    tuned = replace(det, sigma_px=tuned_px)
    factor = estimated_noise_factor(MEDIAN_DOF * (2 * seen.n - 3))  # the median of the probed stars' chi^2
    note = f"residuals reject the announced centroid noise: {extra:.2g} px per axis added"
    match = verify_over(tuned, seen.det, seen.cat, catalog, base, timings)
    if match is None or not keeps_stars(match, found.rows[sol.matched_det], sol.matched_cat):
        # the answer's own stars, weighted and judged by the noise they showed (the announced one
        # was rejected: its covariance would be too tight)
        rows = found.rows[sol.matched_det]
        att = solve_attitude(det.vectors[rows], catalog.vec[sol.matched_cat], tuned_px[rows] / det.focal_px)
        kept = replace(sol, q_icrs_to_sensor=att.q, residuals=att.residuals, covariance=att.covariance * factor)
        kept.noise_extra, kept.notes = extra / det.focal_px, [*sol.notes, f"{note}; its stars kept"]
        return Identification(bound_roll(kept, base.max_roll_sigma), found.rows, found.fallback_due)
    out = solution_from_match(match, Outcome.HIGH_CONFIDENCE, "", everything, catalog, sol.method, len(det))
    out.covariance = np.asarray(out.covariance) * factor
    out.attempts, out.timings = sol.attempts, sol.timings
    out.noise_extra = extra / det.focal_px
    out.notes = [*sol.notes, note]
    return Identification(bound_roll(out, base.max_roll_sigma), everything, found.fallback_due)


def _probe_cannot_reject(
    found: Identification, det: IdentificationInput, catalog: OnboardCatalog, base: SolveParams
) -> bool:
    """Whether the probe's verification (:func:`adapt_noise` step 1) could not reject the announced
    noise, read from the answer without running it (docs/identification.md gives what the probe
    costs): the answer's stars beyond 80 % of the tail quantile, plus every free detection the probe's
    wider gate could take in (110 % of it, about the answer's attitude, with the covariance of the
    answer's stars at the probe's noise), all counted beyond, over the answer's stars alone, still
    give a binomial tail of at least :data:`NOISE_TEST_ALPHA`. The probe's own count has at least
    as many stars and at most as many beyond, and the tail only grows with more stars and fewer
    beyond, so it could not reject either."""
    sol = found.solution
    rows = found.rows[sol.matched_det]
    sigma = np.asarray(det.sigma_px, float)
    wide = np.hypot(sigma, base.noise_probe_px) / det.focal_px  # rad
    chi2 = (np.asarray(sol.residuals) * det.focal_px / sigma[rows]) ** 2
    beyond = int(np.count_nonzero(chi2 > 0.8 * _TAIL_CHI2))
    if len(rows) < len(det):
        a = quat_matrix(sol.q_icrs_to_sensor)
        near = catalog.stars_within(a[2], _fov(base, det.vectors).radius, deep=base.verify.deep)
        if len(near):
            vectors = np.ascontiguousarray(det.vectors, float)
            beyond += _free_in_gate(vectors, rows, catalog.vec[near], a, wide, 1.1 * base.verify.refine_sigmas)
    return miss_tail(len(rows), beyond, NOISE_TAIL) >= NOISE_TEST_ALPHA


def warm_up() -> None:
    """Compile (or load from numba's disk cache) the noise probe's kernel."""
    v = np.array([[0.0, 0.0, 1.0], [0.01, 0.0, 1.0], [0.0, 0.02, 1.0], [0.03, 0.01, 1.0]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    _free_in_gate(v, np.arange(3), v, np.eye(3), np.full(4, 1e-3), 4.0)


@njit(cache=True, nogil=True)
def _free_in_gate(vectors, rows, near_vec, a, sigma, sigmas):  # pragma: no cover - compiled
    """Detections not in ``rows`` whose nearest catalog star of ``near_vec`` (through attitude ``a``)
    lies within ``sigmas`` of ``sqrt(sigma^2 + tr P)`` (``sigma`` per detection, rad; ``P`` the
    covariance of the attitude from the ``rows`` stars at their ``sigma``)."""
    trace = np.trace(covariance_kernel(vectors[rows], sigma[rows]))
    taken = np.zeros(len(vectors), np.bool_)
    taken[rows] = True
    pred = near_vec @ a.T
    count = 0
    for i in range(len(vectors)):
        if taken[i]:
            continue
        cos = -np.inf
        for k in range(len(pred)):
            cos = max(cos, vectors[i, 0] * pred[k, 0] + vectors[i, 1] * pred[k, 1] + vectors[i, 2] * pred[k, 2])
        count += np.arccos(min(max(cos, -1.0), 1.0)) < sigmas * np.sqrt(sigma[i] ** 2 + trace)
    return count


def keeps_stars(match: VerifiedMatch, rows: np.ndarray, cat: np.ndarray) -> bool:
    """Whether ``match`` holds every detection ``rows[k]`` with its catalog star ``cat[k]``: the
    same identification, more stars on it (an attitude test would judge the first answer by the
    covariance of a noise it did not have, and by stars chosen for fitting tight gates)."""
    pairs = set(zip(np.asarray(match.det).tolist(), np.asarray(match.cat).tolist()))
    return pairs.issuperset(zip(np.asarray(rows).tolist(), np.asarray(cat).tolist()))


#: Sigmas (per sensor axis, of the two answers' covariances together) within which an answer
#: verified again must stay of the one it started from.
SAME_ANSWER_SIGMAS = 5.0


def within_covariance(a: np.ndarray, cov: np.ndarray, sol: SolveResult) -> bool:
    """Whether attitude ``a`` (covariance ``cov``, rad^2) lies within :data:`SAME_ANSWER_SIGMAS` of
    ``sol``'s attitude on every sensor axis, the two covariances added."""
    m = a @ quat_matrix(sol.q_icrs_to_sensor).T  # small rotation, sensor frame
    delta = 0.5 * np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    var = np.diag(cov) + (np.diag(sol.covariance) if sol.covariance is not None else 0.0)
    return bool(np.all(np.abs(delta) <= SAME_ANSWER_SIGMAS * np.sqrt(var)))


def estimated_noise_factor(dof: float) -> float:
    """Covariance factor for an attitude whose noise was estimated with ``dof`` degrees of freedom
    (``2n - 3`` for a sum of squares over ``n`` stars; less for the median, :data:`MEDIAN_DOF`):
    the attitude error over a sigma from a variance estimate follows a Student t, so the factor
    ``(t_q / 3)^2`` (``q`` the Gaussian's 3-sigma quantile, 0.99865; scipy's inverse t) keeps
    "beyond 3 sigma" as rare as for a known noise (9 degrees of freedom: 1.88; 17: 1.39; 37:
    1.16)."""
    return float((stdtrit(max(float(dof), 1.0), _THREE_SIGMA) / 3.0) ** 2)


#: The Gaussian's 3-sigma quantile.
_THREE_SIGMA = float(ndtr(3.0))

#: Degrees of freedom of a noise scale read from the median of ``n`` chi^2(2) values, per ``2n - 3``:
#: ``ln(2)^2`` (the median's relative variance ``1 / (n ln^2 2)`` against ``2 / nu`` for a sum of
#: squares with ``nu`` degrees of freedom; the median of chi^2(2) at ``2 ln 2``, its density there 1/4).
MEDIAN_DOF = float(np.log(2.0) ** 2)


def noise_rejected(residuals: np.ndarray, sigma: np.ndarray) -> bool:
    """Whether residual angles reject the announced per-axis noise ``sigma`` (same units): the
    chance that at least as many stars as observed lie beyond the :data:`NOISE_TAIL` quantile of
    their chi^2 (2 degrees of freedom: ``(r / sigma)^2 > -2 ln NOISE_TAIL``), each with
    probability ``NOISE_TAIL``, is below :data:`NOISE_TEST_ALPHA`."""
    n = len(residuals)
    beyond = int(np.count_nonzero((np.asarray(residuals) / sigma) ** 2 > _TAIL_CHI2))
    return n >= 3 and miss_tail(n, beyond, NOISE_TAIL) < NOISE_TEST_ALPHA


def extra_noise(residuals: np.ndarray, sigma: np.ndarray) -> float:
    """The per-axis noise ``e`` (units of ``sigma``) that, added in quadrature to ``sigma``, brings
    the median of the stars' ``r^2 / (sigma^2 + e^2)`` to the median of chi^2 with 2 degrees of
    freedom (``2 ln 2``) times ``(2n - 3) / 2n`` (3 degrees of freedom taken by the attitude);
    bisection, the median falls as ``e`` grows; 0 when it is already no larger."""
    n = len(residuals)
    target = 2.0 * np.log(2.0) * (2 * n - 3) / (2 * n)
    r2, s2 = np.asarray(residuals, float) ** 2, np.asarray(sigma, float) ** 2
    if np.median(r2 / s2) <= target:
        return 0.0
    lo, hi = 0.0, float(np.sqrt(np.max(r2)))
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.median(r2 / (s2 + mid * mid)) > target else (lo, mid)
    return hi


def bound_roll(sol: SolveResult, max_roll_sigma: float) -> SolveResult:
    """``sol`` held to low confidence (``roll_limited``) when it is high-confidence but its roll
    sigma (about the boresight, from the attitude covariance) exceeds ``max_roll_sigma`` (rad):
    the identification may be right, but a user reading "high confidence" expects the roll too
    (docs/identification.md)."""
    roll = sol.roll_sigma
    if sol.status is Outcome.HIGH_CONFIDENCE and np.isfinite(roll) and roll > max_roll_sigma:
        sol.status = Outcome.LOW_CONFIDENCE
        sol.roll_limited = True
        sol.reason = (
            f"roll sigma {np.degrees(roll):.3g} deg above the {np.degrees(max_roll_sigma):.3g} deg "
            f"bound for high confidence ({len(sol.matched_det)} stars matched)"
        )
    return sol


def verify_over(
    det: IdentificationInput,
    rows: np.ndarray,
    cat: np.ndarray,
    catalog: OnboardCatalog,
    base: SolveParams,
    timings: IdentifyTimings,
) -> VerifiedMatch | None:
    """The solver's verification (geometry only) of detections ``rows`` matched to catalog stars
    ``cat``, over every detection; its time goes to ``timings.attitude``."""
    t0 = time.perf_counter()
    n = len(det)
    if det.sigma_px is not None:
        sigma_vec = det.sigma_px / det.focal_px
    else:
        sigma_vec = np.broadcast_to(np.asarray(base.sigma_vec, dtype=float), (n,))
    match, _ = verify(
        np.asarray(rows),
        cat,
        det.vectors,
        np.full(n, np.nan),
        np.full(n, np.nan),
        sigma_vec,
        catalog,
        _fov(base, det.vectors),
        0.0,
        0.0,
        base.verify,
    )
    timings.attitude += time.perf_counter() - t0
    timings.verifications += 1
    return match


def searched_confident(n: int, coverage: float, chance: float, cp: ConsensusParams, attempts: int = 1) -> bool:
    """High confidence for stars matched with optics fitted to a search-chosen pattern, the
    attempt ``attempts`` of the search: :func:`consensus.confident`'s rule (a large set, or at
    least ``chance_stars`` whose stars beyond two line up by chance with probability below
    ``chance_alpha``) with the chance multiplied by the attempts (each pattern the search refines
    and verifies is one more chance for a coincidence: a wrong pattern with its fitted focal
    length can verify a few stars at a small chance; docs/identification.md)."""
    cov = coverage if np.isfinite(coverage) else 0.0
    if n >= cp.chance_stars and chance * max(attempts, 1) <= cp.chance_alpha:
        return True
    return n >= cp.confident_stars and cov >= cp.confident_coverage


def hold_searched(sol: SolveResult, cp: ConsensusParams, attempts: int = 1) -> SolveResult:
    """``sol``, an answer found with a camera fitted to a search-chosen pattern (the search's
    attempt ``attempts``), held to low confidence unless :func:`searched_confident`."""
    if sol.status is Outcome.HIGH_CONFIDENCE and not searched_confident(
        len(sol.matched_det), sol.coverage, sol.chance, cp, attempts
    ):
        sol.status = Outcome.LOW_CONFIDENCE
        sol.reason = _searched_reason(len(sol.matched_det), sol.coverage, sol.chance, cp, attempts)
    return sol


def widen_for_estimated_noise(sol: SolveResult, max_roll_sigma: float) -> SolveResult:
    """``sol``, identified with a centroid-noise floor estimated from its own matched stars (the
    residuals of a pattern's refinement), its covariance widened by the Student t factor of a noise
    estimated with ``2n - 3`` degrees of freedom over its ``n`` stars (:func:`estimated_noise_factor`)
    and held to the roll bound again; unchanged without a covariance or when :func:`adapt_noise`
    estimated the noise itself (its own factor applied)."""
    if sol.covariance is None or sol.noise_extra > 0:
        return sol
    sol.covariance = np.asarray(sol.covariance) * estimated_noise_factor(2 * len(sol.matched_det) - 3)
    return bound_roll(sol, max_roll_sigma)


def ranks_above(a: SolveResult | None, b: SolveResult | None) -> bool:
    """Whether answer ``a`` is preferred to ``b`` among answers short of a decision (a search's
    candidates): more stars matched, then the higher confidence (coverage of the predicted stars
    times the share of detections explained); no answer ranks lowest."""
    return _rank(a) > _rank(b)


def _rank(sol: SolveResult | None) -> tuple[int, float]:
    return (0, 0.0) if sol is None else (len(sol.matched_det), sol.confidence)


def _searched_reason(n: int, coverage: float, chance: float, cp: ConsensusParams, attempts: int) -> str:
    return (
        f"{n} stars (coverage {coverage:.2f}, chance {chance:.1g} at search attempt {attempts}) with optics "
        f"fitted to a search-chosen pattern: below the {cp.confident_stars} stars and "
        f"{cp.confident_coverage:g} coverage, or the {cp.chance_alpha:g} chance over the attempts, it needs"
    )


def verify_pattern(
    det: IdentificationInput,
    rows: np.ndarray,
    cat: np.ndarray,
    catalog: OnboardCatalog,
    base: SolveParams,
    timings: IdentifyTimings,
    attempts: int = 1,
) -> SolveResult | None:
    """A pattern match found by a search (the pipeline's optics search, its attempt ``attempts``:
    detections ``rows`` on catalog stars ``cat``) verified over every detection (method
    ``pattern``), or None when verification refuses it; high confidence as
    :func:`searched_confident` grants it on the matched pattern stars, the frame's own noise
    checked (:func:`adapt_noise`). Verified against every catalog star at once (the
    verification-only stars of :func:`match_deep` too: one verification for the usual answer);
    an answer that is not high-confidence is verified again on the pattern stars alone, as every
    other low-confidence answer is."""
    deep = _deep(base, catalog)
    cp = base.consensus
    for params in dict.fromkeys((deep, base)):  # deep first; base alone when that is not high
        match = verify_over(det, rows, cat, catalog, params, timings)
        high = match is not None and searched_confident(match.n_decisive, match.coverage, match.chance, cp, attempts)
        if high:
            break
    if match is None:
        return None
    n = match.n_decisive
    reason = "" if high else _searched_reason(n, match.coverage, match.chance, cp, attempts)
    outcome = Outcome.HIGH_CONFIDENCE if high else Outcome.LOW_CONFIDENCE
    everything = np.arange(len(det))
    sol = bound_roll(
        solution_from_match(match, outcome, reason, everything, catalog, Method.PATTERN, len(det)), base.max_roll_sigma
    )
    return adapt_noise(Identification(sol, everything), det, catalog, deep, timings).solution


def photometric_gate(flux: np.ndarray, sol: SolveResult, catalog: OnboardCatalog, margin_mag: float):
    """Rows (of the solver input) bright enough to be catalog stars, using the zero point of the
    matched stars: ``m_est = median(m_cat + 2.5 log10 F) - 2.5 log10 F`` kept when
    ``m_est <= max(catalog magnitude) + margin_mag``. None when no zero point can be formed."""
    f_matched = flux[sol.matched_det]
    ok = np.isfinite(f_matched) & (f_matched > 0)
    if ok.sum() < 2:
        return None
    zero_point = np.median(catalog.mag[sol.matched_cat][ok] + 2.5 * np.log10(f_matched[ok]))
    with np.errstate(divide="ignore", invalid="ignore"):
        m_est = zero_point - 2.5 * np.log10(flux)
    return np.flatnonzero(np.nan_to_num(m_est, nan=np.inf) <= catalog.pattern_mag_limit + margin_mag)


def agrees(a: SolveResult, b: SolveResult, tol: float = 1e-3) -> bool:
    """Whether two answers are the same attitude: within ``tol`` (rad) or within their covariances
    (:func:`within_covariance`; a noisy frame's answers move with the stars they keep)."""
    return same_attitude(a, b, tol) or (
        a.covariance is not None and within_covariance(quat_matrix(a.q_icrs_to_sensor), a.covariance, b)
    )


def same_attitude(a: SolveResult, b: SolveResult, tol: float) -> bool:
    """Whether two answers' attitudes agree within ``tol`` (rad)."""
    return rotation_angle(quat_matrix(a.q_icrs_to_sensor), quat_matrix(b.q_icrs_to_sensor)) <= tol


def geometric_detection_cap(camera: CameraModel, catalog: OnboardCatalog, factor: float) -> int:
    """Brightest detections given to the brightness-independent 4-star matcher: ``factor``
    times the catalog stars expected in the field (catalog density x field solid angle), at
    least :data:`MIN_GEOMETRIC_DETECTIONS`. Fainter detections are mostly stars below the
    catalog limit, which would fill the 4-star groups with stars it cannot identify."""
    half_x = np.arctan(camera.width / 2.0 / camera.f)
    half_y = np.arctan(camera.height / 2.0 / camera.f)
    solid_angle = 4.0 * np.arcsin(np.sin(half_x) * np.sin(half_y))
    expected = catalog.n_pattern_stars * solid_angle / (4.0 * np.pi)
    return max(MIN_GEOMETRIC_DETECTIONS, int(np.ceil(factor * expected)))


# ------------------------------------------------------------------ one set of star vectors
def choose_method(mode: Mode, frame_colour: bool, catalog: OnboardCatalog) -> Method:
    """``auto``: colour consensus when the frame and the catalog carry colour, else geometric."""
    if mode is Mode.AUTO:
        return Method.COLOUR if frame_colour and catalog.has_colour else Method.GEOMETRIC
    return Method.COLOUR if mode is Mode.COLOUR else Method.GEOMETRIC


def _frame_colour(rg: np.ndarray, bg: np.ndarray) -> bool:
    return bool(np.isfinite(rg).any() and np.isfinite(bg).any())


def _fov(params: SolveParams, v: np.ndarray) -> FieldOfView:
    return params.fov or FieldOfView.cone(float(np.max(np.arccos(np.clip(v[:, 2], -1, 1)))) + 1e-9)


def solve(vectors, rg, bg, catalog: OnboardCatalog, params: SolveParams = SolveParams()) -> SolveResult:
    """Identify the stars of one set of sensor-frame vectors (brightest first; colours or None)
    and estimate the attitude: clean, choose the method, match, decide (module docstring)."""
    t0 = time.perf_counter()
    timings = SolveTimings()
    scene = clean(vectors, rg, bg, catalog, params)
    timings.validate = time.perf_counter() - t0
    if isinstance(scene, str):
        return SolveResult(Outcome.NO_MATCH, scene, timings=timings)
    v, n = scene.v, len(scene.v)

    def no_match(reason: str, method: Method | None = None) -> SolveResult:
        timings.total = time.perf_counter() - t0
        return SolveResult(Outcome.NO_MATCH, reason, method=method, n_used=n, timings=timings, notes=scene.notes)

    try:
        mode = Mode.parse(params.mode)
    except ValueError:
        return no_match(f"unknown mode {params.mode!r}")
    if catalog.n_pairs == 0:
        return no_match("catalog has no star pairs")
    method = choose_method(mode, _frame_colour(scene.rg, scene.bg), catalog)
    if method is Method.COLOUR and not catalog.has_colour:
        return no_match("colour mode forced but the catalog has no colours", method)
    if n < 2:
        return no_match(f"{n} usable detection(s): need at least two", method)
    ang = angle_between(v[:, None, :], v[None, :, :])
    in_range = (ang > catalog.phi_min) & (ang <= catalog.phi_max)
    if not in_range.any():
        return no_match(
            f"no detection pair within the catalog's pair-angle range "
            f"({np.degrees(catalog.phi_min):.3g}-{np.degrees(catalog.phi_max):.3g} deg): "
            f"catalog built for another field of view?",
            method,
        )
    fov = _fov(params, v)
    noise = PairNoise(params.pair_sigma_phi, params.sigma_rg, params.sigma_bg)
    colour = method is Method.COLOUR
    verify_time = [0.0]
    budget = SearchBudget(params.max_verifications, params.deadline)

    def check(det: np.ndarray, cat: np.ndarray) -> tuple[VerifiedMatch | None, str]:
        budget.spend()
        tv = time.perf_counter()
        out = verify(
            det,
            cat,
            v,
            scene.rg,
            scene.bg,
            scene.sigma,
            catalog,
            fov,
            noise.sigma_rg if colour else 0.0,
            noise.sigma_bg if colour else 0.0,
            params.verify,
        )
        verify_time[0] += time.perf_counter() - tv
        return out

    t1 = time.perf_counter()
    if colour:
        res = match_scene(v, scene.rg, scene.bg, catalog, noise, params.consensus, check, budget)
        timings.match = time.perf_counter() - t1 - verify_time[0]
        timings.verify = verify_time[0]
        timings.total = time.perf_counter() - t0
        if res.best is None:
            return _spent(no_match(budget.reason or res.reason, method), budget)
        out = solution_from_match(res.best, res.outcome, res.reason, scene.index_map, catalog, method, n)
        out.attempts, out.hypotheses = res.attempts, res.coincidences
    else:
        if n < 3:
            return no_match(f"geometric mode needs at least three detections, got {n}", method)
        found, groups, hypotheses = match_geometric(v, catalog, noise, params, check, budget)
        timings.match = time.perf_counter() - t1 - verify_time[0]
        timings.verify = verify_time[0]
        timings.total = time.perf_counter() - t0
        if not found:
            why = budget.reason or "no verified identification"
            return _spent(no_match(f"{why} ({groups} 4-star group(s), triangle fallback)", method), budget)
        best, status, reason = decide_geometric(found, n, params.consensus)
        refusal = reason if status is Outcome.NO_MATCH else None
        refusal = refusal or chance_refusal(status, best.n, best.chance, max(hypotheses, budget.used))
        if refusal is not None:
            refused = no_match(refusal, method)
            refused.attempts = groups
            return _spent(refused, budget)
        out = solution_from_match(best, status, reason, scene.index_map, catalog, method, n)
        out.attempts, out.hypotheses = groups, max(hypotheses, budget.used)
    out.timings = timings
    out.notes = scene.notes
    return bound_roll(_spent(out, budget), params.max_roll_sigma)


def _spent(sol: SolveResult, budget: SearchBudget) -> SolveResult:
    """``sol`` with the work its search counted and what stopped it."""
    sol.verifications, sol.stopped = budget.used, budget.stopped
    return sol


def match_geometric(
    v: np.ndarray, catalog: OnboardCatalog, noise: PairNoise, params: SolveParams, check: Check, budget: SearchBudget
) -> tuple[list[VerifiedMatch], int, int]:
    """Verified geometric hypotheses: 4-star matching (Dong et al.), then the triangle fallback
    when it is not conclusive. Returns the verified matches, the 4-star groups tried and the
    hypotheses met (the 4-star answer and the catalog triangles the triads matched)."""
    n = len(v)
    eps = params.four_star.epsilon or params.four_star.epsilon_sigmas * noise.sigma_phi
    found: list[VerifiedMatch] = []
    groups = hypotheses = 0
    if n >= 4:
        fs = match_four_star(v, catalog, eps, params.four_star)
        groups = fs.groups
        if len(fs.det) >= 2:
            hypotheses += 1
            match, _ = check(fs.det, fs.cat)
            if match is not None:
                found.append(match)
    if not (found and geometric_high(found[0], [], n, params.consensus)):
        more, met = match_triangles(v, catalog, eps, check, params.triangle, budget)
        found += more
        hypotheses += met
    return found, groups, hypotheses


def decide_geometric(found: list[VerifiedMatch], n: int, cp: ConsensusParams) -> tuple[VerifiedMatch, Outcome, str]:
    """The best of the verified geometric hypotheses (most stars, then coverage), its confidence
    and the reason when it is not high: rivals with a different attitude and comparable support,
    or too small a share of the ``n`` detections; NO_MATCH for a 3-star answer with a rival (two
    triangles at odds say this frame makes such matches by coincidence)."""
    best = max(found, key=lambda f: (f.n, f.coverage if np.isfinite(f.coverage) else 0.0))
    rivals = [
        f
        for f in found
        if f is not best
        and f.n >= max(3, cp.rival_ratio * best.n)
        and rotation_angle(f.attitude.a, best.attitude.a) >= cp.rival_angle
    ]
    if geometric_high(best, rivals, n, cp):
        return best, Outcome.HIGH_CONFIDENCE, ""
    if rivals and best.n <= 3:  # two triangles at odds: a 3-star match this frame makes by coincidence
        return (
            best,
            Outcome.NO_MATCH,
            (
                f"{NOT_A_STAR_FIELD}: a 3-star match and {len(rivals)} rival(s) as well supported at another attitude "
                "(at least one is a coincidence, so either may be)"
            ),
        )
    if rivals:
        return best, Outcome.LOW_CONFIDENCE, f"{len(rivals)} rival hypothesis(es) with comparable support"
    return best, Outcome.LOW_CONFIDENCE, f"{best.n} of {n} detections matched"


def chance_refusal(status: Outcome, n: int, chance: float, hypotheses: int) -> str | None:
    """Why a low-confidence answer of ``n`` stars is refused (None: it is not): among the
    ``hypotheses`` the search verified, an as well supported wrong one is expected more than
    ``consensus.CHANCE_ANSWERS`` times (each lines up its stars beyond two with probability
    ``chance``: ``consensus.chance_answers``), so its attitude cannot be told from a coincidence (a
    frame of hot pixels, no star in it). The consensus route makes the same test on its seed pairs."""
    expected = chance_answers(chance, hypotheses)
    if status is not Outcome.LOW_CONFIDENCE or expected <= CHANCE_ANSWERS:
        return None
    return (
        f"{NOT_A_STAR_FIELD}: {n}-star match expected {expected:.2g} times by chance "
        f"({hypotheses} hypotheses verified; chance {chance:.2g} beyond the seed pair)"
    )


def geometric_high(best: VerifiedMatch, rivals: list[VerifiedMatch], n: int, cp: ConsensusParams) -> bool:
    """High confidence for a geometric answer: no rival, at least three stars, and the eta test or
    a large well-covering set (as in the colour consensus)."""
    if rivals or best.n < 3:
        return False
    if best.low_coverage and best.n < cp.decisive_stars:
        return False
    return best.n >= cp.eta * n or brightest_eta(best.det, cp) or confident(best, cp)


def brightest_eta(det: np.ndarray, cp: ConsensusParams) -> bool:
    """The eta test on the brightest detections: for some ``k >= eta_prefix_min``, at least
    ``eta k`` of the ``k`` brightest detections (indices below ``k``; detections are brightest
    first) are matched. The fraction is largest just after a matched detection, so only those
    ``k`` are checked."""
    if cp.eta_prefix_min <= 0 or len(det) == 0:
        return False
    k = np.sort(np.asarray(det)) + 1
    matched = np.arange(1, len(k) + 1)
    return bool(np.any((k >= cp.eta_prefix_min) & (matched >= cp.eta * k)))


def check_hypothesis(
    vectors, rg, bg, det, cat, catalog: OnboardCatalog, params: SolveParams = SolveParams()
) -> tuple[VerifiedMatch | None, str]:
    """Run the solver's verification on a given identification (``det`` input rows matched to
    catalog indices ``cat``), with the cleaning, field of view and noise ``solve`` would use.

    For diagnostics (the whole-sky simulation asks whether the true identification of a frame
    that was not solved would have passed verification): returns ``(VerifiedMatch, "")`` with
    indices into the cleaned detections, or ``(None, reason)``.
    """
    scene = clean(vectors, rg, bg, catalog, params)
    if isinstance(scene, str):
        return None, scene
    pos = {int(r): k for k, r in enumerate(scene.index_map.tolist())}
    pairs = [(pos[int(d)], int(c)) for d, c in zip(np.atleast_1d(det), np.atleast_1d(cat)) if int(d) in pos]
    if len(pairs) < 2:
        return None, "fewer than two of the given detections survive input cleaning"
    try:
        colour = choose_method(Mode.parse(params.mode), _frame_colour(scene.rg, scene.bg), catalog) is Method.COLOUR
    except ValueError:
        colour = False  # an unknown mode: verified on geometry
    d = np.array([p[0] for p in pairs], np.int64)
    c = np.array([p[1] for p in pairs], np.int64)
    return verify(
        d,
        c,
        scene.v,
        scene.rg,
        scene.bg,
        scene.sigma,
        catalog,
        _fov(params, scene.v),
        params.sigma_rg if colour else 0.0,
        params.sigma_bg if colour else 0.0,
        params.verify,
    )
