"""A pipeline output mapped onto the result structure (docs/ICD.md): the COSMOS sections
(quaternion, return bits, good rows, centroid and matching telemetry for image 1, the bright
bodies inside their exclusion angles in ``hardware.status`` bits 9-11) and our extension region (stars, stage times, method, the optics and search blocks).

``result_fields(out) -> {dotted path: value}`` for ``protocol.result.build``.
"""

from __future__ import annotations

import numpy as np

from firmware_model.ident.budget import Stop
from firmware_model.ident.solver import method_code
from firmware_model.pipeline.frame_identification import apply_colour_correction
from firmware_model.pipeline.solve_types import STAGES, PipelineOutput
from protocol import result
from protocol.result import ReturnBits, Status
from protocol.star_flags import StarFlag


def _sigma_axes(cov) -> np.ndarray:
    if cov is None:
        return np.zeros(3)
    return np.sqrt(np.clip(np.diag(np.asarray(cov, dtype=float)), 0.0, None))


def _optics_fields(out: PipelineOutput) -> dict:
    """The extension's optics block: PSF sigma and the fitted focal length and distortion."""
    stars, fit = out.stars, out.optics
    flags = result.PSF_MEASURED if stars is not None and stars.psf_source == "measured" else 0
    fields = {
        "ext.psf_sigma": stars.psf_sigma_px if stars is not None else np.nan,
        "ext.focal_px": out.camera.f if out.camera is not None else np.nan,
        "ext.focal_sigma": np.nan,
        "ext.k1": out.camera.k1 if out.camera is not None else np.nan,
        "ext.k1_sigma": np.nan,
        "ext.optics_rms": np.nan,
        "ext.focal_scale": np.nan,
    }
    if fit is not None:
        flags |= result.OPTICS_FITTED | (result.OPTICS_SEARCHED if np.isfinite(fit.focal_scale) else 0)
        fields.update(
            {
                "ext.focal_px": fit.camera.f,
                "ext.focal_sigma": fit.sigmas.get("f", np.nan),
                "ext.k1": fit.camera.k1,
                "ext.k1_sigma": fit.sigmas.get("k1", np.nan),
                "ext.optics_rms": fit.residual_rms_px,
                "ext.optics_stars": fit.n_stars,
                "ext.focal_scale": fit.focal_scale,
            }
        )
    fields["ext.optics_flags"] = flags
    return fields


def _search_fields(out: PipelineOutput) -> dict:
    """The extension's search block: what stopped a search early, and the frame's counted work."""
    flags = {Stop.COUNT: result.SEARCH_BUDGET_REACHED, Stop.DEADLINE: result.DEADLINE_MISSED}.get(out.stopped, 0)
    return {
        "ext.search_flags": flags,
        "ext.seeds": min(out.timings.seeds, 0xFFFF),
        "ext.verifications": out.timings.verifications,
    }


#: Statuses of a frame that went through every stage: extraction, identification (and attitude
#: when it matched); BAD_FRAME stops before extraction, TOO_FEW_STARS before identification.
FULLY_PROCESSED = (Status.OK, Status.LOW_CONFIDENCE, Status.NO_MATCH)


def return_bits(out: PipelineOutput) -> int:
    """COSMOS return-code bits of one output (docs/ICD.md section 10.2): IMAGE1_SUCCESS the frame
    was read and its stars extracted, IMAGE1_QUALITY enough usable stars to identify, FULL_PROCESSING
    every stage ran, CONSISTENT_SOLUTION a high-confidence attitude. There is no image 2, and the
    sequence adds DETECTOR_IMAGE."""
    bits = 0
    if out.stars is not None:
        bits |= ReturnBits.IMAGE1_SUCCESS
        if out.status is not Status.TOO_FEW_STARS:
            bits |= ReturnBits.IMAGE1_QUALITY
    if out.status in FULLY_PROCESSED:
        bits |= ReturnBits.FULL_PROCESSING
    if out.status is Status.OK and out.solution is not None and out.solution.q_icrs_to_sensor is not None:
        bits |= ReturnBits.CONSISTENT_SOLUTION
    return bits


def upper_triangle(covariance) -> np.ndarray:
    """A 3x3 covariance's six distinct terms in the extension's order: xx, yy, zz, xy, xz, yz."""
    c = np.asarray(covariance, dtype=float)
    return np.array([c[0, 0], c[1, 1], c[2, 2], c[0, 1], c[0, 2], c[1, 2]])


def upper_triangle_by_rows(covariance) -> np.ndarray:
    """The upper triangle of a 3x3 covariance row by row, as the ICD's matching telemetry holds the
    attitude covariance (page 1-35920): xx, xy, xz, yy, yz, zz."""
    c = np.asarray(covariance, dtype=float)
    return c[np.triu_indices(3)]


def omega_fields(omega, covariance) -> dict:
    """The rate (rad/s, sensor axes) in the standard structure's ``omega`` and its 3x3 covariance
    ((rad/s)^2) in the extension's ``omega_covariance`` (docs/ICD.md section 10)."""
    return {"omega": np.asarray(omega, dtype=float), "ext.omega_covariance": upper_triangle(covariance)}


def star_entries(out: PipelineOutput, first: int, count: int) -> np.ndarray:
    """``count`` extension star entries (``protocol.result.EXT_STAR``) of the detections ``first``,
    ``first + 1``, ...: position, flux, colour, the matched catalog id and residual, the saturated
    and planet flags; entries past the last detection stay empty (catalog id -1). The result record
    holds the first :data:`protocol.result.EXT_MAX_STARS` (the brightest); an offline solve may
    list the rest the same way."""
    entries = np.zeros(count, dtype=result.EXT_STAR)
    entries["catalog_id"] = -1
    stars, sol = out.stars, out.solution
    if stars is None:
        return entries
    rows = np.arange(first, min(len(stars), first + count))
    n = len(rows)
    for name in ("x", "y", "flux", "rg", "bg"):
        entries[name][:n] = getattr(stars, name)[rows]
    for k, name in enumerate(("rg_sigma", "bg_sigma")):
        var = stars.cov_colour[rows, k, k]
        # a degenerate colour fit (a negative variance: a star on glare) has no sigma: NaN, as unmeasured
        entries[name][:n] = np.sqrt(np.where(var >= 0, var, np.nan))
    entries["flags"][:n] = ((stars.flags[rows] & int(StarFlag.SATURATED)) != 0).astype(np.uint32) << 1
    if sol is not None and sol.q_icrs_to_sensor is not None:
        for k, row in enumerate(out.used[sol.matched_det]):
            if first <= row < first + n:
                entries["catalog_id"][row - first] = sol.matched_star_id[k]
                entries["residual"][row - first] = sol.residuals[k]
                entries["flags"][row - first] |= 1
    for lab in out.planets:
        if first <= lab.index < first + n:
            entries["flags"][lab.index - first] |= 4 | (1 + result.BODIES.index(lab.body)) << 8
    return entries


def result_fields(out: PipelineOutput) -> dict:
    """Result-structure fields (dotted paths of ``protocol.result.RESULT``) for one output."""
    fields: dict = {}
    stars, sol = out.stars, out.solution
    if stars is not None and len(stars):
        top = np.arange(min(10, len(stars)))
        cen = np.zeros((10, 2))
        cen[top] = np.column_stack([stars.x[top], stars.y[top]])
        vec = np.zeros((10, 3))
        if stars.vectors is not None:
            vec[top] = stars.vectors[top]
        fields.update(
            {
                "centroid.0.initialized": 1,
                "centroid.0.good_stars": int(stars.trusted.sum()),
                "centroid.0.centroids": cen,
                "centroid.0.unit_vectors": vec,
                "image.0.initialized": 1,
                "image.0.peak_count": len(stars),
            }
        )
    n_matched = 0
    ext_stars = star_entries(out, 0, result.EXT_MAX_STARS)
    if stars is not None:
        fields["ext.n_detected"] = len(stars)
        fields["ext.n_reported"] = min(len(stars), result.EXT_MAX_STARS)
    if sol is not None and sol.q_icrs_to_sensor is not None:
        q = np.asarray(sol.q_icrs_to_sensor, dtype=float)
        rows = out.used[sol.matched_det]
        n_matched = len(rows)
        matched10 = np.full(10, -1, dtype=np.int32)
        matched10[: min(10, n_matched)] = sol.matched_star_id[:10]
        fields.update(
            {
                "quaternion": q,
                "matching.0.initialized": 1,
                "matching.0.quaternion": q,
                "matching.0.consensus_size": int(sol.consensus_size),
                "matching.0.consensus_rms": float(sol.consensus_rms),
                "matching.0.confidence": float(sol.confidence),
                "matching.0.matched_stars": matched10,
                "matching.0.set_tests": int(sol.attempts),
                "ext.quaternion": q,
                "ext.sigma": _sigma_axes(sol.covariance),
                "matching.0.attitude_covariance": np.zeros(6)
                if sol.covariance is None
                else upper_triangle_by_rows(sol.covariance),
                "ext.residual_rms": float(sol.consensus_rms),
            }
        )
        if n_matched and out.stars is not None and np.isfinite(out.stars.rg[rows]).any():
            obs_rg, obs_bg = out.stars.rg[rows], out.stars.bg[rows]
            if out.colour_beta is not None:
                obs_rg, obs_bg = apply_colour_correction(obs_rg, obs_bg, out.colour_beta)
            d = np.concatenate([obs_rg - sol.matched_rg, obs_bg - sol.matched_bg])
            fields["ext.colour_rms"] = float(np.sqrt(np.nanmean(d**2)))
    if out.omega is not None and out.omega_covariance is not None:
        fields.update(omega_fields(out.omega, out.omega_covariance))
    fields["ext.n_planets"] = min(len(out.planets), 255)
    fields["ext.n_matched"] = n_matched
    fields.update(_optics_fields(out))
    fields.update(_search_fields(out))
    fields["ext.stars"] = ext_stars
    fields["ext.stage_times"] = np.array([getattr(out.timings, name) for name in STAGES], dtype=np.float32)
    fields["ext.method"] = method_code(sol.method if sol else None)
    if stars is not None and out.camera is not None:
        fields["statistics.good_rows"] = [out.camera.height, 0]  # every row of image 1 read; no image 2
    fields["return_code"] = result.make_return_code(out.status, return_bits(out))
    if out.in_fov:
        fields["hardware.status"] = sum(int(result.exclusion_bit(body)) for body in out.in_fov)
    return fields
