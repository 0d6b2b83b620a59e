"""The device's detection-to-attitude pipeline on one frame, and its result-structure fields.

``run_pipeline(frame, camera, catalog, params) -> PipelineOutput`` chains extraction
(detection, centroid and colour fit, camera model), the optional eq. 24 colour correction,
identification and attitude (``firmware_model.ident.solver``). It never raises on bad frames:
the output carries a :class:`protocol.result.Status` and a reason.
:func:`result_fields` maps an output onto the result structure (docs/ICD.md): the COSMOS
sections (quaternion, centroid and matching telemetry for image 1) and our extension region.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.extract import ExtractParams, StarList, extract_stars
from firmware_model.frame import Frame
from firmware_model.frames import quat_to_matrix, rotation_angle
from firmware_model.ident.consensus import Outcome
from firmware_model.ident.solver import SolveParams, SolveResult, solve
from firmware_model.ident.verify import FieldOfView
from firmware_model.onboard_catalog import OnboardCatalog
from firmware_model.star_flags import UNTRUSTED, StarFlag
from protocol import result
from protocol.result import ReturnBits, Status

#: Floor on the per-axis centroid noise fed to the solver (px): covers camera-model and
#: optical residuals that the photon-noise covariance of the fit does not know about.
CENTROID_SIGMA_FLOOR_PX = 0.1

#: Centroid noise assumed when the fit gave no covariance (centre-of-gravity fallback), px.
UNKNOWN_CENTROID_SIGMA_PX = 1.0
#: Floor for stars whose fit is flagged untrusted (saturated, blended, poor fit, edge), px. Such
#: stars keep their place in the geometry with this weight; saturated or blended stars lose
#: their colour (the identification then uses their geometry alone).
UNTRUSTED_CENTROID_FLOOR_PX = 0.5

#: Fewest detections given to the geometric matcher.
MIN_GEOMETRIC_DETECTIONS = 8
#: Brightest-detection counts tried in turn by the 4-star matcher before the density cap: a
#: small set of bright stars is most likely all in the catalog (beyond seed 001, which takes
#: its groups from the frame centre whatever their brightness).
GEOMETRIC_STEPS = (4, 6, 8)

#: Method codes of the result extension (``ext.method``).
METHOD_CODES = {"colour": 1, "geometric": 2, "geometric-consensus": 3}

#: Stage names reported in the result extension, in order.
STAGES = ("detect", "fit", "vectors", "identify", "attitude", "total")


@dataclass(frozen=True)
class PipelineParams:
    """Pipeline configuration. ``colour_beta`` is the eq. 24 correction (6 numbers) or None;
    ``solve`` is the solver configuration (its colour sigmas are raised to the catalog's design
    values, its field of view defaults to the camera's); the per-detection direction noise is derived from
    the fit covariance (with :data:`CENTROID_SIGMA_FLOOR_PX`) unless ``fixed_sigma_px`` is set.

    ``photometric_gate`` (mag, or None to disable): a low-confidence consensus may be caused by
    detections fainter than the catalog holds, which the eta test of seed 000 counts against the
    match. The pipeline then estimates every detection's magnitude from the zero point of the
    matched stars, drops those fainter than the catalog limit plus this margin, and solves
    again; the second answer is taken only if it is high-confidence and agrees with the first.

    ``geometric_density_factor``: the geometric (4-star) method sees only the brightest
    detections: first :data:`GEOMETRIC_STEPS` of them, then this factor times the catalog
    stars expected in the field (:func:`geometric_detection_cap`). ``geometric_fallback``: when that 4-star match finds
    nothing, the consensus matcher of seed 000 runs on geometry alone (colours unknown), which
    tolerates missing and extra stars far better; its answers are labelled
    ``geometric-consensus``. ``colour_fallback``: in ``auto`` mode a colour frame that the colour
    matcher cannot solve (colours biased beyond the catalog's noise model, e.g. through the
    atmosphere before calibration) is solved on geometry alone, as a mono frame would be."""

    extract: ExtractParams = ExtractParams()
    solve: SolveParams = SolveParams()
    colour_beta: tuple | None = None
    fixed_sigma_px: float | None = None
    photometric_gate: float | None = 0.1
    geometric_density_factor: float = 1.5
    geometric_fallback: bool = True
    colour_fallback: bool = True


@dataclass
class PipelineOutput:
    status: Status
    reason: str = ""
    stars: StarList | None = None
    used: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))  #: star rows given to the solver
    solution: SolveResult | None = None
    timings: dict = field(default_factory=dict)  #: seconds per stage (STAGES)
    colour_beta: tuple | None = None  #: the eq. 24 correction the matcher's colours went through

    @property
    def ok(self) -> bool:
        return self.status is Status.OK


def with_psf_sigma(params: PipelineParams, sigma_px: float | None) -> PipelineParams:
    """``params`` with the PSF Gaussian sigma fixed to ``sigma_px`` (an override of the per-frame
    measurement; None measures again)."""
    return replace(params, extract=replace(params.extract, psf_sigma_px=sigma_px))


def apply_colour_correction(rg, bg, beta):
    """Eq. 24 with ``beta = [b1..b6]``: ``rg' = b1 rg + b2 bg + b5``, ``bg' = b3 rg + b4 bg + b6``."""
    b = np.asarray(beta, dtype=float)
    return b[0] * rg + b[1] * bg + b[4], b[2] * rg + b[3] * bg + b[5]


def run_pipeline(frame: Frame, camera: CameraModel, catalog: OnboardCatalog,
                 params: PipelineParams = PipelineParams()) -> PipelineOutput:
    """Frame -> stars -> identification -> attitude (module docstring)."""
    t0 = time.perf_counter()
    if (frame.width, frame.height) != (camera.width, camera.height):
        return PipelineOutput(Status.BAD_FRAME, f"frame is {frame.width} x {frame.height} but the camera is "
                                                f"{camera.width} x {camera.height}")
    try:
        stars = extract_stars(frame, camera, params.extract)
    except ValueError as exc:
        return PipelineOutput(Status.BAD_FRAME, f"frame rejected: {exc}")
    out = identify_stars(stars, camera, catalog, params)
    out.timings["total"] = time.perf_counter() - t0
    return out


def identify_stars(stars: StarList, camera: CameraModel, catalog: OnboardCatalog,
                   params: PipelineParams = PipelineParams()) -> PipelineOutput:
    """Identification and attitude from extracted stars (``stars.vectors`` from ``camera``)."""
    t0 = time.perf_counter()
    timings = {"detect": stars.timings.get("detect_s", 0.0), "fit": stars.timings.get("fit_s", 0.0),
               "vectors": stars.timings.get("vectors_s", 0.0)}
    used = np.flatnonzero(np.isfinite(stars.vectors).all(axis=1)) if len(stars) else np.empty(0, np.int64)
    if len(used) < 2:
        why = stars.reason or f"{len(stars)} detection(s)"
        return PipelineOutput(Status.TOO_FEW_STARS, f"too few stars: {why}", stars, used, timings=timings)
    geometric = params.solve.mode == "geometric" or (params.solve.mode == "auto" and (
        not catalog.has_colour or not np.isfinite(stars.rg[used]).any()))
    if geometric:
        sol, rows = _solve_geometric(used, stars, camera, catalog, params, timings)
    else:
        sol, rows = _solve_rows(used, stars, camera, catalog, params, params.solve.mode, True, timings)
        if sol.status is Outcome.NO_MATCH and params.colour_fallback and params.solve.mode == "auto":
            geometric = True  # colours biased beyond the catalog's noise model: try geometry alone
            sol, rows = _solve_geometric(used, stars, camera, catalog, replace(params, solve=replace(
                params.solve, mode="geometric")), timings)
    if geometric and sol.status is Outcome.NO_MATCH and params.geometric_fallback and catalog.has_colour:
        sol2, rows2 = _solve_rows(used, stars, camera, catalog, params, "colour", False, timings)
        if sol2.status is not Outcome.NO_MATCH:
            sol2.method = "geometric-consensus"
            sol, rows = sol2, rows2
    used = rows
    timings["total"] = time.perf_counter() - t0 + stars.timings.get("total_s", 0.0)
    if sol.status is Outcome.NO_MATCH:
        return PipelineOutput(Status.NO_MATCH, sol.reason, stars, used, sol, timings, params.colour_beta)
    status = Status.OK if sol.status is Outcome.HIGH_CONFIDENCE else Status.LOW_CONFIDENCE
    return PipelineOutput(status, sol.reason, stars, used, sol, timings, params.colour_beta)


def _solve_rows(rows, stars: StarList, camera: CameraModel, catalog: OnboardCatalog, params: PipelineParams,
                mode: str, use_colour: bool, timings: dict):
    """Solve on ``rows`` of ``stars`` (adds to ``timings``); returns (solution, rows it refers to).

    Saturated or blended stars keep their geometry but lose their colour; the per-star
    direction noise comes from the fit covariance with a floor, larger for untrusted fits. The
    colour noise given to the matcher is the largest of the solver setting, the catalog's
    design value and the median colour sigma the fit measured on this frame (a small aperture
    leaves 4th-magnitude stars with ~0.1 colour noise; matching them at 0.05 rejects true
    matches). A low-confidence answer is retried with the photometric gate
    (:class:`PipelineParams`)."""
    flags = stars.flags[rows]
    colour_ok = ((flags & int(StarFlag.SATURATED | StarFlag.BLEND)) == 0) & use_colour
    rg = np.where(colour_ok, stars.rg[rows], np.nan)
    bg = np.where(colour_ok, stars.bg[rows], np.nan)
    if params.colour_beta is not None:
        rg, bg = apply_colour_correction(rg, bg, params.colour_beta)
    if params.fixed_sigma_px is not None:
        sigma_px = np.full(len(rows), float(params.fixed_sigma_px))
    else:
        var = 0.5 * (stars.cov_xy[rows, 0, 0] + stars.cov_xy[rows, 1, 1])
        var = np.where(np.isfinite(var), var, UNKNOWN_CENTROID_SIGMA_PX ** 2)
        floor = np.where((flags & int(UNTRUSTED)) != 0, UNTRUSTED_CENTROID_FLOOR_PX, CENTROID_SIGMA_FLOOR_PX)
        sigma_px = np.sqrt(var + floor ** 2)
    measured = np.sqrt(np.where(colour_ok[:, None], stars.cov_colour[rows][:, [0, 1], [0, 1]], np.nan))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN: no colour measured
        frame_rg, frame_bg = np.nanmedian(measured, axis=0)
    solve_params = replace(
        params.solve, mode=mode, sigma_vec=sigma_px / camera.f, fov=params.solve.fov or FieldOfView.from_camera(camera),
        sigma_rg=float(np.nanmax([params.solve.sigma_rg, catalog.meta.get("sigma_rg", np.nan), frame_rg])),
        sigma_bg=float(np.nanmax([params.solve.sigma_bg, catalog.meta.get("sigma_bg", np.nan), frame_bg])))

    def run(sub):
        out = solve(stars.vectors[rows[sub]], rg[sub], bg[sub], catalog,
                    replace(solve_params, sigma_vec=solve_params.sigma_vec[sub]))
        timings["identify"] = timings.get("identify", 0.0) + out.timings.get("match", 0.0) + out.timings.get("validate", 0.0)
        timings["attitude"] = timings.get("attitude", 0.0) + out.timings.get("verify", 0.0)
        return out

    sol = run(np.arange(len(rows)))
    if sol.status is Outcome.LOW_CONFIDENCE and params.photometric_gate is not None:
        gated = _photometric_gate(stars.flux[rows], sol, catalog, params.photometric_gate)
        if gated is not None and 2 <= len(gated) < len(rows):
            sol2 = run(gated)
            if sol2.status is Outcome.HIGH_CONFIDENCE and _same_attitude(sol, sol2, 5 * float(np.max(sigma_px)) / camera.f):
                return sol2, rows[gated]
    return sol, rows


def _solve_geometric(used, stars, camera, catalog, params: PipelineParams, timings: dict):
    """4-star matching on the brightest detections, widening the set (:data:`GEOMETRIC_STEPS`,
    then :func:`geometric_detection_cap`) until a high-confidence answer; the best answer else."""
    cap = geometric_detection_cap(camera, catalog, params.geometric_density_factor)
    best = None
    for k in sorted({min(k, cap, len(used)) for k in (*GEOMETRIC_STEPS, cap)}):
        sol, rows = _solve_rows(used[:k], stars, camera, catalog, params, params.solve.mode, False, timings)
        if sol.status is Outcome.HIGH_CONFIDENCE:
            return sol, rows
        if best is None or (best[0].status is Outcome.NO_MATCH and sol.status is not Outcome.NO_MATCH):
            best = (sol, rows)
    return best


def geometric_detection_cap(camera: CameraModel, catalog: OnboardCatalog, factor: float) -> int:
    """Brightest detections given to the brightness-independent 4-star matcher: ``factor``
    times the catalog stars expected in the field (catalog density x field solid angle), at
    least :data:`MIN_GEOMETRIC_DETECTIONS`. Fainter detections are mostly stars below the
    catalog limit, which would fill the 4-star groups with stars it cannot identify."""
    half_x = np.arctan(camera.width / 2.0 / camera.f)
    half_y = np.arctan(camera.height / 2.0 / camera.f)
    solid_angle = 4.0 * np.arcsin(np.sin(half_x) * np.sin(half_y))
    expected = catalog.n_stars * solid_angle / (4.0 * np.pi)
    return max(MIN_GEOMETRIC_DETECTIONS, int(np.ceil(factor * expected)))


def _photometric_gate(flux, sol: SolveResult, catalog: OnboardCatalog, margin_mag: float):
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
    return np.flatnonzero(np.nan_to_num(m_est, nan=np.inf) <= float(np.max(catalog.mag)) + margin_mag)


def _same_attitude(a: SolveResult, b: SolveResult, tol: float) -> bool:
    return rotation_angle(quat_to_matrix(a.q_icrs_to_sensor), quat_to_matrix(b.q_icrs_to_sensor)) <= tol


def _sigma_axes(cov) -> np.ndarray:
    if cov is None:
        return np.zeros(3)
    return np.sqrt(np.clip(np.diag(np.asarray(cov, dtype=float)), 0.0, None))


def result_fields(out: PipelineOutput) -> dict:
    """Result-structure fields (dotted paths of ``protocol.result.RESULT``) for one output."""
    bits = ReturnBits.FULL_PROCESSING
    fields: dict = {}
    stars, sol = out.stars, out.solution
    if stars is not None and len(stars):
        bits |= ReturnBits.IMAGE1_QUALITY
        top = np.arange(min(10, len(stars)))
        cen = np.zeros((10, 2))
        cen[top] = np.column_stack([stars.x[top], stars.y[top]])
        vec = np.zeros((10, 3))
        if stars.vectors is not None:
            vec[top] = stars.vectors[top]
        fields.update({"centroid.0.initialized": 1, "centroid.0.good_stars": int(stars.trusted.sum()),
                       "centroid.0.centroids": cen, "centroid.0.unit_vectors": vec,
                       "image.0.initialized": 1, "image.0.peak_count": len(stars)})
    n_matched = 0
    ext_stars = np.zeros(result.EXT_MAX_STARS, dtype=result.EXT_STAR)
    ext_stars["catalog_id"] = -1
    if stars is not None:
        n_rep = min(len(stars), result.EXT_MAX_STARS)
        for name in ("x", "y", "flux", "rg", "bg"):
            ext_stars[name][:n_rep] = getattr(stars, name)[:n_rep]
        ext_stars["rg_sigma"][:n_rep] = np.sqrt(stars.cov_colour[:n_rep, 0, 0])
        ext_stars["bg_sigma"][:n_rep] = np.sqrt(stars.cov_colour[:n_rep, 1, 1])
        ext_stars["flags"][:n_rep] = ((stars.flags[:n_rep] & int(StarFlag.SATURATED)) != 0).astype(np.uint32) << 1
        fields["ext.n_detected"] = len(stars)
        fields["ext.n_reported"] = n_rep
    if sol is not None and sol.q_icrs_to_sensor is not None:
        q = np.asarray(sol.q_icrs_to_sensor, dtype=float)
        rows = out.used[sol.matched_det]
        n_matched = len(rows)
        for k, row in enumerate(rows):
            if row < result.EXT_MAX_STARS:
                ext_stars["catalog_id"][row] = sol.matched_star_id[k]
                ext_stars["residual"][row] = sol.residuals[k]
                ext_stars["flags"][row] |= 1
        matched10 = np.full(10, -1, dtype=np.int32)
        matched10[:min(10, n_matched)] = sol.matched_star_id[:10]
        bits |= ReturnBits.IMAGE1_SUCCESS
        if out.status is Status.OK:
            bits |= ReturnBits.CONSISTENT_SOLUTION
        fields.update({
            "quaternion": q, "matching.0.initialized": 1, "matching.0.quaternion": q,
            "matching.0.consensus_size": int(sol.consensus_size), "matching.0.consensus_rms": float(sol.consensus_rms),
            "matching.0.confidence": float(sol.confidence), "matching.0.matched_stars": matched10,
            "matching.0.set_tests": int(sol.attempts),
            "ext.quaternion": q, "ext.sigma": _sigma_axes(sol.covariance),
            "ext.residual_rms": float(sol.consensus_rms),
        })
        if n_matched and out.stars is not None and np.isfinite(out.stars.rg[rows]).any():
            obs_rg, obs_bg = out.stars.rg[rows], out.stars.bg[rows]
            if out.colour_beta is not None:
                obs_rg, obs_bg = apply_colour_correction(obs_rg, obs_bg, out.colour_beta)
            d = np.concatenate([obs_rg - sol.matched_rg, obs_bg - sol.matched_bg])
            fields["ext.colour_rms"] = float(np.sqrt(np.nanmean(d ** 2)))
    fields["ext.n_matched"] = n_matched
    fields["ext.stars"] = ext_stars
    fields["ext.stage_times"] = np.array([out.timings.get(s, 0.0) for s in STAGES], dtype=np.float32)
    fields["ext.method"] = METHOD_CODES.get(sol.method if sol else "", 0)
    fields["return_code"] = result.make_return_code(out.status, int(bits))
    return fields
