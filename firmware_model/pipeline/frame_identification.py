"""A frame's stars identified with one camera model: what identification sees of them
(``strategy.IdentificationInput``: usable rows, directions, colours through the eq. 24
correction, centroid noise), the solver's configuration for them, and ``strategy``'s answer as a
:class:`~firmware_model.pipeline.solve_types.PipelineOutput`. The decisions (order of methods,
fallbacks, confidence, ranking) are ``firmware_model.ident.strategy``'s; this module only carries
them across.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from firmware_model.ident.consensus import Outcome
from firmware_model.ident.solver import SolveParams, SolveResult
from firmware_model.ident.strategy import (
    IdentificationInput,
    StrategyParams,
    geometric_detection_cap,
    geometric_fallback,
    identify,
)
from firmware_model.ident.verify import FieldOfView
from firmware_model.pipeline.extract import StarList
from firmware_model.pipeline.solve_types import (
    MAX_CENTROID_SIGMA_PX,
    UNKNOWN_CENTROID_SIGMA_PX,
    UNTRUSTED_CENTROID_FLOOR_PX,
    PipelineOutput,
    PipelineParams,
    SolveInput,
    StageTimings,
)
from protocol.result import Status
from protocol.star_flags import UNTRUSTED, StarFlag


def apply_colour_correction(rg, bg, beta):
    """Eq. 24 with ``beta = [b1..b6]``: ``rg' = b1 rg + b2 bg + b5``, ``bg' = b3 rg + b4 bg + b6``."""
    b = np.asarray(beta, dtype=float)
    return b[0] * rg + b[1] * bg + b[4], b[2] * rg + b[3] * bg + b[5]


def identify_with_camera(
    seen: SolveInput,
    params: PipelineParams,
    timings: StageTimings,
    defer_fallback: bool = False,
    fallback_only: bool = False,
) -> PipelineOutput:
    """One identification with one camera model (``strategy.identify``: the order of methods and
    fallbacks). ``defer_fallback``: leave the mono consensus fallback out (``fallback_due`` on the
    answer says it would have run); ``fallback_only``: run that fallback alone
    (``strategy.geometric_fallback``)."""
    stars, camera, catalog = seen.stars, seen.camera, seen.catalog
    used = usable_rows(stars)
    if len(used) < 2:
        why = stars.reason or f"{len(stars)} detection(s)"
        return PipelineOutput(Status.TOO_FEW_STARS, f"too few stars: {why}", stars, used, camera=camera)
    strategy = StrategyParams(
        solve=solve_params(seen, params),
        photometric_gate=params.photometric_gate,
        geometric_cap=geometric_detection_cap(camera, catalog, params.geometric_density_factor),
        geometric_fallback=params.geometric_fallback,
        colour_fallback=params.colour_fallback,
        defer_fallback=defer_fallback,
    )
    det = identification_input(used, stars, camera.f, params)
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
    return PipelineOutput(
        output_status(sol), sol.reason, stars, rows, sol, colour_beta=params.colour_beta, camera=camera
    )


def output_status(sol: SolveResult) -> Status:
    """The answer's status for a solution that matched: OK when ``strategy`` granted it high
    confidence, else LOW_CONFIDENCE."""
    return Status.OK if sol.status is Outcome.HIGH_CONFIDENCE else Status.LOW_CONFIDENCE


def with_solution_confidence(out: PipelineOutput) -> PipelineOutput:
    """``out`` low confidence, with its solution's reason, when it was OK but a later rule of
    ``strategy`` (the roll bound, the searched-confidence rule, a widened covariance) held its
    solution below high confidence."""
    sol = out.solution
    if out.status is Status.OK and sol is not None and output_status(sol) is not Status.OK:
        out.status, out.reason = Status.LOW_CONFIDENCE, sol.reason
    return out


def solve_params(seen: SolveInput, params: PipelineParams) -> SolveParams:
    """The solver configuration for ``seen``: the field of view defaults to the camera's, the
    colour noise is at least the catalog's design value (``strategy.identify`` raises it further to
    the median colour sigma the fit measured), verification knows the frame's detection count
    (the solver may see only the brightest)."""
    meta = seen.catalog.meta
    return replace(
        params.solve,
        fov=params.solve.fov or FieldOfView.from_camera(seen.camera),
        sigma_rg=_larger(params.solve.sigma_rg, meta.get("sigma_rg")),
        sigma_bg=_larger(params.solve.sigma_bg, meta.get("sigma_bg")),
        verify=replace(params.solve.verify, frame_detections=len(seen.stars)),
    )


def _larger(value: float, design: float | None) -> float:
    """The larger of a configured noise and a catalog's design value (None or NaN: not set)."""
    known = [float(v) for v in (value, design) if v is not None and not math.isnan(v)]
    return max(known) if known else float("nan")


def identification_input(
    used: np.ndarray, stars: StarList, focal_px: float, params: PipelineParams
) -> IdentificationInput:
    """What identification sees of the ``used`` rows of ``stars`` (directions through a camera of
    focal length ``focal_px``).

    Saturated or blended stars keep their geometry but lose their colour; colours go through the
    eq. 24 correction; the per-star centroid noise comes from the fit covariance with a floor,
    larger for untrusted fits (or is ``fixed_sigma_px``); the measured colour sigmas let the
    matcher widen its colour noise (faint stars through a small aperture are noisier in colour
    than the catalog's design value)."""
    flags = stars.flags[used]
    colour_ok = (flags & int(StarFlag.SATURATED | StarFlag.BLEND)) == 0
    rg = np.where(colour_ok, stars.rg[used], np.nan)
    bg = np.where(colour_ok, stars.bg[used], np.nan)
    if params.colour_beta is not None:
        rg, bg = apply_colour_correction(rg, bg, params.colour_beta)
    colour_sigma = np.sqrt(np.where(colour_ok[:, None], stars.cov_colour[used][:, [0, 1], [0, 1]], np.nan))
    assert stars.vectors is not None  # extracted with a camera
    return IdentificationInput(
        vectors=stars.vectors[used],
        rg=rg,
        bg=bg,
        sigma_px=centroid_sigma_px(used, stars, params),
        focal_px=focal_px,
        flux=stars.flux[used],
        colour_sigma=colour_sigma,
        measured_colour=has_colour(stars, used),
    )


def centroid_sigma_px(rows: np.ndarray, stars: StarList, params: PipelineParams) -> np.ndarray:
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


def has_colour(stars: StarList, used: np.ndarray | None = None) -> bool:
    """Whether the frame measured colour on its ``used`` rows (default: the usable ones)."""
    return bool(np.isfinite(stars.rg[usable_rows(stars) if used is None else used]).any())


def usable_rows(stars: StarList) -> np.ndarray:
    """Rows with a direction and a centroid known to better than :data:`MAX_CENTROID_SIGMA_PX` (a
    degenerate fit can report a finite centre with a covariance of tens of px^2, or a negative
    variance, with no flag)."""
    if not len(stars):
        return np.empty(0, np.int64)
    diag = stars.cov_xy[:, [0, 1], [0, 1]]
    var = 0.5 * diag.sum(axis=1)
    known = ~(var > MAX_CENTROID_SIGMA_PX**2) & ~(diag < 0).any(axis=1)  # NaN (no covariance) stays: 1 px
    assert stars.vectors is not None  # extracted with a camera
    return np.flatnonzero(np.isfinite(stars.vectors).all(axis=1) & known)
