"""Solver front: sensor-frame star vectors (+ colours) and the on-board catalog -> attitude.

``solve(vectors, rg, bg, catalog, params)`` picks the method per frame: colour consensus
(Enright & McVittie + backtracking + verification) when the frame and the catalog both carry colour,
4-star K-vector matching (Dong et al.) with a verified triangle fallback (``triangle``) otherwise,
or the one forced by ``params.mode``. It never
raises on bad input: malformed arrays, no usable detections or an impossible geometry give
``status = NO_MATCH`` with a reason.

Input cleaning: rows that are not finite or have zero norm are dropped; vectors are
normalised; detections closer than the catalog's ``phi_min`` (unresolvable duplicates, or a false
detection on a star) are both dropped: which of the two is the star cannot be told; beyond ``max_detections`` the faintest are dropped. Every drop is
counted in ``SolveResult.notes``. Indices in the result refer to the caller's input rows.

Time is bounded: consensus attempts, backtracking depth, look-up windows and 4-star groups are
capped (see the parameter classes) and ``time_budget_s`` is checked between attempts.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from firmware_model.catalog.onboard import OnboardCatalog, angle_between
from firmware_model.ident.consensus import ConsensusParams, Outcome, confident, match_scene
from firmware_model.ident.four_star import FourStarParams, match_four_star
from firmware_model.ident.pair_match import PairNoise, sigma_phi_from_centroid
from firmware_model.ident.triangle import TriangleParams, match_triangles
from firmware_model.ident.verify import FieldOfView, VerifiedMatch, VerifyParams, verify
from firmware_model.reference_frames import rotation_angle

#: Per-axis direction noise of the Enright & McVittie reference design: 0.2 px at f = 7383 px (rad).
REFERENCE_SIGMA_VEC = 0.2 / 7383.1


#: Solver modes (``SolveParams.mode``, the parameter file's ``mode``).
MODES = ("auto", "colour", "geometric")


@dataclass(frozen=True)
class SolveParams:
    """Solver configuration.

    mode: "auto" (colour when available, else geometric), "colour" or "geometric".
    sigma_vec: per-axis direction noise of a detection (rad), scalar or one per detection;
        it weights the q-method and sets the verification gates.
    sigma_phi: pair arc-length noise (rad); None means Enright & McVittie eq. 18, ``2 sigma_vec``.
    sigma_rg, sigma_bg: colour-ratio noise.
    fov: the sensor's field of view for the coverage test; None means a cone through the
        outermost detection.
    time_budget_s: wall-clock budget checked between consensus attempts (hard stop).
    max_detections: detections considered (brightest first); the matchers use fewer.
    """

    mode: str = "auto"
    sigma_vec: float = REFERENCE_SIGMA_VEC
    sigma_phi: float | None = None
    sigma_rg: float = 0.05
    sigma_bg: float = 0.05
    consensus: ConsensusParams = ConsensusParams()
    four_star: FourStarParams = FourStarParams(stop_after=3, max_groups=6)
    triangle: TriangleParams = TriangleParams()
    verify: VerifyParams = VerifyParams()
    fov: FieldOfView | None = None
    time_budget_s: float = 0.05
    max_detections: int = 200

    @property
    def pair_sigma_phi(self) -> float:
        if self.sigma_phi is not None:
            return float(self.sigma_phi)
        return sigma_phi_from_centroid(float(np.median(np.atleast_1d(self.sigma_vec))), 1.0)


@dataclass
class SolveResult:
    """Solution of one frame.

    status: HIGH_CONFIDENCE, LOW_CONFIDENCE or NO_MATCH (Enright & McVittie's three classes);
    reason: why it is not high confidence (empty otherwise);
    q_icrs_to_sensor: scalar-first unit quaternion, ``v_sensor = A(q) @ v_icrs`` (None if no match);
    covariance: 3x3 attitude-error covariance about the sensor axes (rad^2);
    matched_det / matched_cat / matched_star_id: input row, catalog index and catalog star id
    of each matched star; matched_rg / matched_bg: the catalog colours;
    residuals: per matched star, angle (rad) between measured and predicted direction;
    consensus_size: stars in the matcher's consensus set (before refinement);
    consensus_rms: RMS residual (rad) of the final matched set;
    confidence: coverage of predicted stars times matched fraction of used detections, in [0, 1];
    method: "colour" or "geometric"; timings: seconds per stage; notes: input cleaning.
    """

    status: Outcome
    reason: str = ""
    q_icrs_to_sensor: np.ndarray | None = None
    covariance: np.ndarray | None = None
    matched_det: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    matched_cat: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    matched_star_id: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    matched_rg: np.ndarray = field(default_factory=lambda: np.empty(0))
    matched_bg: np.ndarray = field(default_factory=lambda: np.empty(0))
    residuals: np.ndarray = field(default_factory=lambda: np.empty(0))
    consensus_size: int = 0
    consensus_rms: float = float("nan")
    confidence: float = 0.0
    method: str = ""
    n_used: int = 0
    attempts: int = 0
    timings: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    @property
    def matched(self) -> list[tuple[int, int, int]]:
        """(detection index, catalog index, star id) per matched star."""
        return list(zip(self.matched_det.tolist(), self.matched_cat.tolist(), self.matched_star_id.tolist()))

    @property
    def ok(self) -> bool:
        return self.status is not Outcome.NO_MATCH


def _clean(vectors, rg, bg, sigma, catalog: OnboardCatalog, params: SolveParams):
    """Validated arrays (or a reason string). Returns (v, rg, bg, sigma, index_map, notes)."""
    try:
        v = np.asarray(vectors, dtype=float)
    except (TypeError, ValueError):
        return "detection vectors are not numeric"
    if v.ndim != 2 or v.shape[1] != 3:
        return f"detection vectors must have shape (N, 3), got {v.shape}"
    n = len(v)
    cols = []
    for name, c in (("rg", rg), ("bg", bg)):
        if c is None:
            cols.append(np.full(n, np.nan))
            continue
        try:
            c = np.asarray(c, dtype=float).ravel()
        except (TypeError, ValueError):
            return f"{name} is not numeric"
        if len(c) != n:
            return f"{name} has {len(c)} values for {n} detections"
        cols.append(c)
    try:
        s = np.broadcast_to(np.asarray(sigma, dtype=float), (n,)).copy()
    except ValueError:
        return f"sigma_vec must be a scalar or have one value per detection ({n})"
    notes = []
    norm = np.linalg.norm(v, axis=1) if n else np.empty(0)
    good = np.all(np.isfinite(v), axis=1) & (norm > 1e-12) & np.isfinite(s) & (s > 0)
    if (~good).any():
        notes.append(f"dropped {int((~good).sum())} non-finite or zero vector(s)")
    idx = np.nonzero(good)[0]
    v = v[idx] / norm[idx, None]
    if len(v) > 1:
        ang = angle_between(v[:, None, :], v[None, :, :])
        close = np.triu(ang < max(catalog.phi_min, 1e-9), k=1)
        dup = close.any(axis=0) | close.any(axis=1)  # both: which of the two is the star cannot be told
        if dup.any():
            notes.append(f"dropped {int(dup.sum())} detection(s) of pairs closer than phi_min")
            idx, v = idx[~dup], v[~dup]
    if len(idx) > params.max_detections:
        notes.append(f"used the {params.max_detections} brightest of {len(idx)} detections")
        idx, v = idx[: params.max_detections], v[: params.max_detections]
    return v, cols[0][idx], cols[1][idx], s[idx], idx, notes


def solution_from_match(
    match: VerifiedMatch, status: Outcome, reason: str, index_map, catalog, method, n_used
) -> SolveResult:
    """The solution a verified match stands for (``index_map``: input row of each detection)."""
    att = match.attitude
    return SolveResult(
        status=status,
        reason=reason,
        q_icrs_to_sensor=att.q.copy(),
        covariance=att.covariance,
        matched_det=index_map[match.det],
        matched_cat=match.cat,
        matched_star_id=catalog.star_id[match.cat],
        matched_rg=catalog.rg[match.cat].astype(float),
        matched_bg=catalog.bg[match.cat].astype(float),
        residuals=att.residuals,
        consensus_size=match.n_consensus,
        consensus_rms=att.rms,
        confidence=float(match.coverage if np.isfinite(match.coverage) else 1.0) * min(1.0, match.n / max(n_used, 1)),
        method=method,
        n_used=n_used,
    )


def solve(vectors, rg, bg, catalog: OnboardCatalog, params: SolveParams = SolveParams()) -> SolveResult:
    """Identify the stars of one frame and estimate the attitude (module docstring)."""
    t0 = time.perf_counter()
    timings = {}
    cleaned = _clean(vectors, rg, bg, params.sigma_vec, catalog, params)
    timings["validate"] = time.perf_counter() - t0
    if isinstance(cleaned, str):
        return SolveResult(Outcome.NO_MATCH, cleaned, timings=timings)
    v, rg, bg, sigma, index_map, notes = cleaned
    n = len(v)

    def no_match(reason, method=""):
        timings["total"] = time.perf_counter() - t0
        return SolveResult(Outcome.NO_MATCH, reason, method=method, n_used=n, timings=timings, notes=notes)

    if params.mode not in MODES:
        return no_match(f"unknown mode {params.mode!r}")
    if catalog.n_pairs == 0:
        return no_match("catalog has no star pairs")
    frame_colour = bool(np.isfinite(rg).any() and np.isfinite(bg).any())
    method = (
        params.mode if params.mode != "auto" else ("colour" if frame_colour and catalog.has_colour else "geometric")
    )
    if method == "colour" and not catalog.has_colour:
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
    fov = params.fov or FieldOfView.cone(float(np.max(np.arccos(np.clip(v[:, 2], -1, 1)))) + 1e-9)
    noise = PairNoise(params.pair_sigma_phi, params.sigma_rg, params.sigma_bg)
    verify_time = [0.0]

    def check(det, cat):
        tv = time.perf_counter()
        out = verify(
            det,
            cat,
            v,
            rg,
            bg,
            sigma,
            catalog,
            fov,
            noise.sigma_rg if method == "colour" else 0.0,
            noise.sigma_bg if method == "colour" else 0.0,
            params.verify,
        )
        verify_time[0] += time.perf_counter() - tv
        return out

    t1 = time.perf_counter()
    if method == "colour":
        res = match_scene(v, rg, bg, catalog, noise, params.consensus, check, deadline=t0 + params.time_budget_s)
        timings["match"] = time.perf_counter() - t1 - verify_time[0]
        timings["verify"] = verify_time[0]
        timings["total"] = time.perf_counter() - t0
        if res.best is None:
            return no_match(res.reason, method)
        out = solution_from_match(res.best, res.outcome, res.reason, index_map, catalog, method, n)
        out.attempts = res.attempts
    else:
        out = _solve_geometric(v, catalog, noise, params, check, n, t0, t1, timings, verify_time, index_map)
        if isinstance(out, str):
            return no_match(out, method)
    out.timings = timings
    out.notes = notes
    return out


def check_hypothesis(
    vectors, rg, bg, det, cat, catalog: OnboardCatalog, params: SolveParams = SolveParams()
) -> tuple[VerifiedMatch | None, str]:
    """Run the solver's verification on a given identification (``det`` input rows matched to
    catalog indices ``cat``), with the cleaning, field of view and noise ``solve`` would use.

    For diagnostics (the whole-sky simulation asks whether the true identification of a frame
    that was not solved would have passed verification): returns ``(VerifiedMatch, "")`` with
    indices into the cleaned detections, or ``(None, reason)``.
    """
    cleaned = _clean(vectors, rg, bg, params.sigma_vec, catalog, params)
    if isinstance(cleaned, str):
        return None, cleaned
    v, rg, bg, sigma, index_map, _ = cleaned
    pos = {int(r): k for k, r in enumerate(index_map.tolist())}
    pairs = [(pos[int(d)], int(c)) for d, c in zip(np.atleast_1d(det), np.atleast_1d(cat)) if int(d) in pos]
    if len(pairs) < 2:
        return None, "fewer than two of the given detections survive input cleaning"
    frame_colour = bool(np.isfinite(rg).any() and np.isfinite(bg).any())
    method = (
        params.mode if params.mode != "auto" else ("colour" if frame_colour and catalog.has_colour else "geometric")
    )
    fov = params.fov or FieldOfView.cone(float(np.max(np.arccos(np.clip(v[:, 2], -1, 1)))) + 1e-9)
    colour = method == "colour"
    d = np.array([p[0] for p in pairs], np.int64)
    c = np.array([p[1] for p in pairs], np.int64)
    return verify(
        d,
        c,
        v,
        rg,
        bg,
        sigma,
        catalog,
        fov,
        params.sigma_rg if colour else 0.0,
        params.sigma_bg if colour else 0.0,
        params.verify,
    )


def _solve_geometric(v, catalog, noise, params, check, n, t0, t1, timings, verify_time, index_map):
    """4-star matching (Dong et al.), then the triangle fallback when it is not conclusive."""
    if n < 3:
        return f"geometric mode needs at least three detections, got {n}"
    eps = params.four_star.epsilon or params.four_star.epsilon_sigmas * noise.sigma_phi
    cp = params.consensus
    found, groups = [], 0
    if n >= 4:
        fs = match_four_star(v, catalog, eps, params.four_star)
        groups = fs.groups
        if len(fs.det) >= 2:
            match, _ = check(fs.det, fs.cat)
            if match is not None:
                found.append(match)
    if not (found and _geometric_high(found[0], [], n, cp)):
        found += match_triangles(v, catalog, eps, check, params.triangle, deadline=t0 + params.time_budget_s)
    timings["match"] = time.perf_counter() - t1 - verify_time[0]
    timings["verify"] = verify_time[0]
    timings["total"] = time.perf_counter() - t0
    if not found:
        if time.perf_counter() > t0 + params.time_budget_s:
            return f"time budget exhausted ({groups} 4-star group(s), triangle fallback)"
        return f"no verified identification ({groups} 4-star group(s), triangle fallback)"
    best = max(found, key=lambda f: (f.n, f.coverage if np.isfinite(f.coverage) else 0.0))
    rivals = [
        f
        for f in found
        if f is not best
        and f.n >= max(3, cp.rival_ratio * best.n)
        and rotation_angle(f.attitude.a, best.attitude.a) >= cp.rival_angle
    ]
    high = _geometric_high(best, rivals, n, cp)
    if high:
        reason = ""
    elif rivals:
        reason = f"{len(rivals)} rival hypothesis(es) with comparable support"
    else:
        reason = f"{best.n} of {n} detections matched"
    out = solution_from_match(
        best, Outcome.HIGH_CONFIDENCE if high else Outcome.LOW_CONFIDENCE, reason, index_map, catalog, "geometric", n
    )
    out.attempts = groups
    return out


def _geometric_high(best, rivals, n, cp: ConsensusParams) -> bool:
    """High confidence for a geometric answer: no rival, at least three stars, and the eta test or
    a large well-covering set (as in the colour consensus)."""
    if rivals or best.n < 3:
        return False
    if best.low_coverage and best.n < cp.decisive_stars:
        return False
    return best.n >= cp.eta * n or confident(best, cp)
