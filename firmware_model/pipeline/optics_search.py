"""The optics search: lost in space with a datasheet camera (focal length off by a few per cent,
radial distortion and principal-point offset not modelled), as plate solvers do it, and the fit of
focal length and k1 to every answer's stars. Its settings are
:class:`~firmware_model.pipeline.solve_types.OpticsSearch`; the stages of ``run.SOLVE_PLAN``
call it.

1. Pattern seeds (:func:`pattern_seeds`): the brightest detections matched as scale-free 4-star
   patterns (``scale_free``): the first tier's first matches rank by rank
   (``scale_free.BrightFirstMatches``: the 4 brightest, then the patterns adding the 5th, ...; a
   frame's brightest stars are its catalog's brightest), then the best among all ``n_bright``
   (clutter such as a foreground tree can hold the brightest detections); blended, failed-fit and
   edge detections are left out (:func:`pattern_rows`).
2. The first seed (:func:`first_seed`) is refined before anything else: when its optics would
   refit the nominal camera (:func:`nominal_off`) the search goes first, since a nominal camera
   that cannot match would spend its matchers' whole search failing; on the geometric route it is
   verified with the nominal camera (:func:`verify_seed`).
3. The search (:func:`search_optics`): each seed, best first, refined by predict-match-fit of the
   focal length (and k1 with enough stars) with the attitude (:class:`Refinement`); the refined
   match verified over every detection and taken when high-confidence as a search-chosen match
   (``strategy.searched_confident``: the chance of a coincidence counted over the search's
   attempts), else the frame identified from scratch with the fitted camera and a noise floor
   raised to the refinement's residuals (held to the same rule).
4. The optics of every answer (:func:`refine_optics`, :func:`with_optics`): focal length and k1
   fitted to its matched stars (:func:`fit_optics`), the attitude re-solved through them and its
   covariance widened by their uncertainty; when they replace the camera (:func:`refit_due`) the
   frame is identified again with them so stars the first camera missed are matched.

Bounded by counted work, never by the clock (``OpticsSearch.max_seeds`` seeds,
``max_verifications`` verifications a frame); docs/identification.md ("The solve plan") gives the
worst case.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.ident.attitude import solve_attitude
from firmware_model.ident.budget import Stop, stop_reason
from firmware_model.ident.strategy import (
    agrees,
    bound_roll,
    hold_searched,
    ranks_above,
    verify_pattern,
    widen_for_estimated_noise,
)
from firmware_model.pipeline import scale_free
from firmware_model.pipeline.camera_fit import CalibrationResult, StarObservations
from firmware_model.pipeline.extract import StarList
from firmware_model.pipeline.frame_fit import fit_frame
from firmware_model.pipeline.frame_identification import (
    centroid_sigma_px,
    identification_input,
    identify_with_camera,
    output_status,
    solve_params,
    usable_rows,
    with_solution_confidence,
)
from firmware_model.pipeline.pattern_index import PatternIndex
from firmware_model.pipeline.solve_types import (
    OpticsFit,
    OpticsSearch,
    PipelineOutput,
    PipelineParams,
    SolveInput,
    StageTimings,
    through_camera,
)
from firmware_model.reference_frames import rotation_angle
from protocol.result import Status
from protocol.star_flags import StarFlag

#: Star residual (px) beyond which a star is left out of the optics fit (with 5 x the median).
OPTICS_OUTLIER_PX = 1.0
#: The frame is identified again with the fitted optics when they fit this much better (RMS ratio).
REFIT_RMS_RATIO = 1.5
#: Detections left out of the pattern search's brightest stars (saturated stars stay: they are real).
_PATTERN_EXCLUDE = int(StarFlag.BLEND | StarFlag.FIT_FAILED | StarFlag.EDGE)
#: Pattern seeds whose attitudes differ by less than this (rad) lead to the same refined answer.
_SAME_SEED_RAD = np.radians(0.2)


class Refinement(NamedTuple):
    """A pattern hypothesis refined by predict-match-fit (``scale_free.refine``): the fitted
    ``camera``, the matched detection ``rows`` and catalog indices ``cat``, and the last ``fit``."""

    camera: CameraModel
    rows: np.ndarray
    cat: np.ndarray
    fit: CalibrationResult


@dataclass(frozen=True)
class FirstSeed:
    """The first tier's first pattern hypothesis and its refinement (None: it found too few stars,
    so that the search does not refine it again)."""

    hypothesis: scale_free.Hypothesis
    refined: Refinement | None


def refine(
    seen: SolveInput, hyp: scale_free.Hypothesis, search: OpticsSearch, timings: StageTimings
) -> Refinement | None:
    """``hyp`` refined on the stars of ``seen`` (``scale_free.refine``; its time goes to
    ``timings.attitude``, one more seed counted), or None when it finds too few stars."""
    t1 = time.perf_counter()
    stars = seen.stars
    refined = scale_free.refine(stars.x, stars.y, seen.camera, hyp, seen.catalog, k1_min_stars=search.k1_min_stars)
    timings.attitude += time.perf_counter() - t1
    timings.seeds += 1
    return None if refined is None else Refinement(*refined)


def pattern_index(seen: SolveInput) -> PatternIndex:
    """The pattern index the frame's patterns are looked up in: the solve's own
    (``seen.patterns``), else the catalog's for the camera's field (``scale_free.catalog_patterns``)."""
    return seen.patterns if seen.patterns is not None else scale_free.catalog_patterns(seen.catalog, seen.camera)


def pattern_rows(stars: StarList) -> np.ndarray:
    """Rows of the detections fit to make patterns of (blended, failed-fit and edge ones left out)."""
    return np.flatnonzero((stars.flags & _PATTERN_EXCLUDE) == 0)


def first_tier(
    seen: SolveInput, search: OpticsSearch | None, timings: StageTimings
) -> scale_free.BrightFirstMatches | None:
    """The first pattern matches of ``search`` (the ``first_tier`` brightest clean detections,
    rank by rank; None without one); the caller has the pattern index ready (:func:`pattern_index`)
    and at least four usable detections."""
    if search is None or search.first_tier <= 0 or search.first_tier_hypotheses <= 0:
        return None
    t1 = time.perf_counter()
    stars = seen.stars
    clean = pattern_rows(stars)
    peek = scale_free.BrightFirstMatches(
        stars.x[clean],
        stars.y[clean],
        seen.camera,
        pattern_index(seen),
        search.first_tier,
        search.pattern_tolerance,
        search.focal_range,
    )
    timings.identify += time.perf_counter() - t1
    return peek


def first_seed(
    seen: SolveInput,
    search: OpticsSearch | None,
    timings: StageTimings,
    peek: scale_free.BrightFirstMatches | None,
) -> FirstSeed | None:
    """The first tier's first hypothesis and its refinement (:func:`refine`: focal length and k1
    fitted to every star it predicts), or None (no search, no match)."""
    if search is None or peek is None:
        return None
    t1 = time.perf_counter()
    hyp = next(peek.hypotheses(1), None)
    timings.identify += time.perf_counter() - t1
    if hyp is None:
        return None
    return FirstSeed(hyp, refine(seen, hyp, search, timings))


def nominal_off(
    peek: scale_free.BrightFirstMatches | None, seed: FirstSeed | None, seen: SolveInput, search: OpticsSearch
) -> bool:
    """Whether the nominal camera would be refitted (:func:`refit_due`, :func:`refine_optics`'s
    rule) on the first pattern match's refined stars (:func:`first_seed`): a nominal camera that
    cannot match would spend its matchers' whole search failing, and one whose answer is refitted
    identifies the frame twice, so the search goes first. The refined camera decides, not the
    pattern's own scale (one pattern's scale is known too roughly); without a refinement, the first
    tier's best key's focal length decides."""
    camera = seen.camera
    if seed is None or seed.refined is None:
        if peek is None or not np.isfinite(peek.best_f):
            return False
        return corner_shift_px(camera, replace(camera, f=peek.best_f)) > search.refit_px
    fitted, rows, cat, fit = seed.refined
    refined = OpticsFit(fitted, fit.sigmas, fit.residual_rms_px, fit.n_observations, rows=rows, cat=cat)
    return refit_due(seen, refined, search)


def refined_noise(params: PipelineParams, fit: CalibrationResult) -> PipelineParams:
    """``params`` without the search, the floor of the centroid noise raised to the per-axis RMS of
    a refinement's stars (``fit``, with the fitted unknowns' degrees of freedom): the refined
    optics leave residuals no centroid covariance knows about (coma, an unmodelled distortion,
    centroids noisier than announced), and the identification's gates and covariance must know."""
    dof = 2 * fit.n_observations - len(fit.sigmas) - 3
    rms_px = fit.residual_rms_px * np.sqrt(2 * fit.n_observations / max(dof, 1))
    return replace(params, optics=None, centroid_floor_px=max(params.centroid_floor_px, rms_px / np.sqrt(2.0)))


def verify_seed(
    refined: Refinement, seen: SolveInput, params: PipelineParams, timings: StageTimings
) -> PipelineOutput | None:
    """The first pattern match's refinement (:func:`first_seed`): its stars verified over the frame
    with the nominal camera of ``seen`` and the refinement's noise floor
    (:func:`verify_refinement`, the search's first attempt)."""
    noise = refined_noise(params, refined.fit)
    out = verify_refinement(seen, refined, noise, timings, 1)
    return None if out is None else with_estimated_floor(out, noise, params)


def verify_refinement(
    seen: SolveInput, refined: Refinement, params: PipelineParams, timings: StageTimings, attempts: int
) -> PipelineOutput | None:
    """A refined pattern match (its detection rows on its catalog stars, the search's attempt
    ``attempts``), verified over every usable detection with the camera of ``seen`` and the noise
    model of ``params`` and judged by ``strategy.verify_pattern`` (method "pattern"), or None when
    verification refuses it."""
    stars = seen.stars
    used = usable_rows(stars)
    rows, cat = np.asarray(refined.rows), np.asarray(refined.cat)
    usable = np.zeros(len(stars), bool)
    usable[used] = True
    inside = usable[rows]
    sol = verify_pattern(
        identification_input(used, stars, seen.camera.f, params),
        np.searchsorted(used, rows[inside]),
        cat[inside],
        seen.catalog,
        solve_params(seen, params),
        timings,
        attempts,
    )
    if sol is None:
        return None
    return PipelineOutput(
        output_status(sol), sol.reason, stars, used, sol, colour_beta=params.colour_beta, camera=seen.camera
    )


def search_optics(
    seen: SolveInput,
    params: PipelineParams,
    timings: StageTimings,
    peek: scale_free.BrightFirstMatches | None = None,
    seed: FirstSeed | None = None,
) -> PipelineOutput | None:
    """The search (module docstring, step 3): the first pattern match that leads to a
    high-confidence answer with the fitted camera, else the low-confidence answer of a pattern
    match that explains the most stars (``strategy.ranks_above``; None when no pattern match
    verifies). ``peek``: the first tier's pattern matches when the caller has them
    (:func:`first_tier`); ``seed``: its first hypothesis and its refinement, already made
    (:func:`first_seed`)."""
    search = params.optics
    assert search is not None  # called with the optics search on (the caller built its patterns)
    camera = seen.camera
    tried: list[np.ndarray] = []
    best: SearchAnswer | None = None
    for hyp in pattern_seeds(seen, search, timings, peek):
        if search_spent(search, params.solve.deadline, timings):
            break
        if any(rotation_angle(hyp.a, a) < _SAME_SEED_RAD for a in tried):
            continue
        if seed is not None and hyp is seed.hypothesis:  # the first tier keeps its hypotheses: the same object
            refined = seed.refined
        else:
            refined = refine(seen, hyp, search, timings)
        if refined is None:
            continue
        tried.append(hyp.a)  # a seed near one that refined to a failed identification leads there too
        fitted = seen.with_camera(refined.camera)
        tight = refined_noise(params, refined.fit)
        # the refined pattern match verified over the frame first (one verification); the frame
        # identified from scratch with the fitted camera only when that is not high-confidence
        pattern = verify_refinement(fitted, refined, tight, timings, len(tried))
        if pattern is not None and pattern.status is Status.OK:
            out = pattern
        else:
            out = identify_with_camera(fitted, tight, timings)
            if out.solution is not None and out.status is Status.OK:
                out.solution = hold_searched(out.solution, params.solve.consensus, len(tried))
                out = with_solution_confidence(out)
            if pattern is not None and ranks_above(pattern.solution, out.solution):
                out = pattern
        if out.status is Status.OK:
            return with_optics(SearchAnswer(out, hyp.f / camera.f, tight), seen.catalog, params, refined)
        if out.solution is not None and ranks_above(out.solution, best.answer.solution if best else None):
            best = SearchAnswer(out, hyp.f / camera.f, tight)
    if best is None:
        return None
    return with_optics(best, seen.catalog, params)  # the optics of the answer only


class SearchAnswer(NamedTuple):
    """An answer of the search: the answer, its pattern's focal length over the nominal one, and
    the parameters (noise floor) it was identified with."""

    answer: PipelineOutput
    focal_scale: float
    noise: PipelineParams


def search_spent(search: OpticsSearch, deadline: float | None, timings: StageTimings) -> bool:
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


def with_optics(
    found: SearchAnswer, catalog: OnboardCatalog, params: PipelineParams, known: Refinement | None = None
) -> PipelineOutput:
    """The search's answer with the optics fitted to its matched stars and its focal scale, its
    covariance widened by their uncertainty (:func:`with_fitted_camera_uncertainty`, with the
    parameters it was identified with) and for its estimated noise floor
    (:func:`with_estimated_floor`); ``known``: a refinement of some stars already made."""
    assert params.optics is not None  # the search's answers
    out, noise = found.answer, found.noise
    out.optics = fit_optics(out, catalog, params.optics, known)
    if out.optics is not None:
        out.optics.focal_scale = found.focal_scale
    return with_estimated_floor(with_fitted_camera_uncertainty(out, catalog, noise), noise, params)


def with_estimated_floor(out: PipelineOutput, noise: PipelineParams, params: PipelineParams) -> PipelineOutput:
    """``out`` with its covariance widened for a centroid-noise floor estimated from a refinement's
    stars (``noise``'s floor above ``params``', :func:`refined_noise`;
    ``strategy.widen_for_estimated_noise``)."""
    sol = out.solution
    if sol is None or noise.centroid_floor_px <= params.centroid_floor_px:
        return out
    widen_for_estimated_noise(sol, params.solve.max_roll_sigma)
    return with_solution_confidence(out)


def pattern_seeds(
    seen: SolveInput,
    search: OpticsSearch,
    timings: StageTimings,
    peek: scale_free.BrightFirstMatches | None = None,
):
    """Pattern hypotheses (``scale_free.pattern_matches``) from the brightest clean detections, then, when
    poor fits were among them (hot-pixel clusters and other unblurred clutter can outshine the
    stars), from the brightest detections that also fit the PSF well. ``peek``: the first tier's
    pattern matches of the first pass, already computed."""
    stars, camera, index = seen.stars, seen.camera, pattern_index(seen)
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
                    stars.x[rows], stars.y[rows], camera, index, n, search.pattern_tolerance, search.focal_range
                )
            else:
                t1 = time.perf_counter()
                found = scale_free.pattern_matches(
                    stars.x[rows], stars.y[rows], camera, index, n, search.pattern_tolerance, search.focal_range
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


def refine_optics(
    out: PipelineOutput, seen: SolveInput, params: PipelineParams, timings: StageTimings
) -> PipelineOutput | None:
    """Attach the optics fit to a high-confidence ``out``; identify again with the fitted camera when
    it replaces the camera of ``seen`` (:func:`refit_due`: a focal length and k1 fitted to a few
    noisy stars move the corners by chance, and a camera fitted to the noise would hide it from the
    identification's noise check); keep that answer if it is high-confidence and agrees
    (``strategy.agrees``): its camera fits the stars better by construction."""
    search, sol = params.optics, out.solution
    assert search is not None and sol is not None  # called with the optics fit on, for an answer
    fit = fit_optics(out, seen.catalog, search)
    out.optics = fit
    if fit is None or not refit_due(seen, fit, search):
        return None
    again = identify_with_camera(seen.with_camera(fit.camera), params, timings)
    if again.status is Status.OK and again.solution is not None and agrees(again.solution, sol):
        again.optics = fit_optics(again, seen.catalog, search) or fit
        return with_fitted_camera_uncertainty(again, seen.catalog, params)
    return None


def fit_optics(
    out: PipelineOutput, catalog: OnboardCatalog, search: OpticsSearch, known: Refinement | None = None
) -> OpticsFit | None:
    """Focal length (and k1 with enough stars) fitted with the attitude to the matched stars of
    ``out`` (on their ``catalog`` stars); stars off by more than :data:`OPTICS_OUTLIER_PX` (or
    5 x the median) after a first fit (a blend, a saturated or badly fitted star the answer keeps
    with a wide noise floor) are left out of a second. ``known``: a refinement already made (the
    search's), used for the first fit when it is of the same stars."""
    sol, stars, camera = out.solution, out.stars, out.camera
    if sol is None or len(sol.matched_det) < search.min_stars:
        return None
    assert stars is not None and camera is not None  # a solution comes with both
    rows, cat = out.used[sol.matched_det], sol.matched_cat
    res = None
    for _ in range(2):
        if known is not None and _same_stars(known.rows, known.cat, rows, cat):
            res, known = known.fit, None
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


def with_fitted_camera_uncertainty(
    out: PipelineOutput, catalog: OnboardCatalog, params: PipelineParams
) -> PipelineOutput:
    """``out``, an answer found with a camera fitted to this frame's stars, with its attitude solved
    again (same stars, same weights) through the camera of its optics fit (fitted to every matched
    star), that camera as the answer's, and the covariance the fitted parameters' uncertainty adds
    (``OpticsFit.attitude_covariance``), held to the roll bound again. The answer was identified
    with the camera the search fitted to a few stars; a focal length off by a few pixels tilts the
    attitude of an off-centre star field, and the solution's covariance treats its camera as exact
    (docs/identification.md, "The optics search")."""
    sol, fit, stars = out.solution, out.optics, out.stars
    if sol is None or sol.covariance is None or fit is None or fit.attitude_covariance is None or stars is None:
        return out
    added = np.asarray(fit.attitude_covariance)
    if not np.all(np.isfinite(added)):
        return out
    moved = through_camera(stars, fit.camera)
    rows = out.used[sol.matched_det]
    sigma = np.hypot(centroid_sigma_px(rows, stars, params), sol.noise_extra * fit.camera.f) / fit.camera.f
    assert moved.vectors is not None  # through_camera sets them
    att = solve_attitude(moved.vectors[rows], catalog.vec[sol.matched_cat], sigma)
    sol.q_icrs_to_sensor, sol.residuals = att.q, att.residuals
    sol.covariance = np.asarray(sol.covariance) + added
    out.stars, out.camera = moved, fit.camera
    bound_roll(sol, params.solve.max_roll_sigma)
    return with_solution_confidence(out)


def _same_stars(rows_a, cat_a, rows_b, cat_b) -> bool:
    """Whether two matched sets pair the same detections with the same catalog stars."""
    a = sorted(zip(np.asarray(rows_a).tolist(), np.asarray(cat_a).tolist()))
    return a == sorted(zip(np.asarray(rows_b).tolist(), np.asarray(cat_b).tolist()))


def corner_shift_px(a: CameraModel, b: CameraModel) -> float:
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
    shift = corner_shift_px(camera, fit.camera)
    return shift > search.refit_px and shift > 3.0 * _corner_shift_sigma_px(fit)


def refit_due(seen: SolveInput, fit: OpticsFit, search: OpticsSearch) -> bool:
    """Whether fitted optics replace the camera of ``seen``: they move the array's corners
    (:func:`_moves_corners`) or fit their stars (``fit.rows`` of the stars on ``fit.cat``)
    :data:`REFIT_RMS_RATIO` times better than that camera with its best attitude does: the same
    stars both ways (an answer's own RMS counts the stars the optics fit leaves out)."""
    camera = seen.camera
    if _moves_corners(camera, fit, search):
        return True
    assert fit.rows is not None and fit.cat is not None  # every OpticsFit of a solve names its stars
    x, y = seen.stars.x[fit.rows], seen.stars.y[fit.rows]
    nominal = solve_attitude(camera.pixel_to_vector(x, y), seen.catalog.vec[fit.cat], 1.0)
    return nominal.rms * camera.f > REFIT_RMS_RATIO * fit.residual_rms_px
