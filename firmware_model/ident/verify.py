"""Verification of an identification hypothesis over all detections (beyond Enright & McVittie).

A hypothesis (detections matched to catalog stars) is accepted only if the attitude it implies
explains the whole frame:

1. **Attitude and residuals**: weighted q-method over the matched stars; a matched star whose
   residual exceeds ``residual_sigmas`` times its predicted scatter is dropped and the attitude
   re-solved (the hypothesis fails if fewer than two stars remain).
2. **Refinement**: every unmatched detection is rotated to ICRS and paired with its nearest
   catalog star when the separation is within ``refine_sigmas`` of the predicted scatter
   ``sqrt(sigma^2 + (tr P - b^T P b)/2)`` (``P`` the a-priori attitude covariance:
   the gates stay in units of the announced noise; the reported one is scaled by the residuals,
   ``attitude`` module docstring) and, when both colours
   are known, the colour distance is below ``colour_gate``. Two passes. The catalog stars are
   its pattern stars, or with ``deep`` every star, verification-only ones included (a decided
   answer's last verification, ``strategy.match_deep``); coverage counts pattern stars either way.
   A matched star with a free detection closer to its prediction (and inside the gates) takes
   that detection instead: a brighter false detection next to a star must not steal its identity.
   Matched stars with a second catalog star inside the same gate (unresolved doubles at this
   noise) are dropped from the answer when ``drop_ambiguous``: their identity cannot be told.
   Then a **final residual test** on each star's own noise (the refinement gate includes the
   attitude covariance, which is wide for a loose early hypothesis): stars beyond
   ``residual_sigmas`` sigma are dropped and the attitude re-solved, and the hypothesis fails if
   the normalised RMS residual exceeds ``max_normalised_rms``.
3. **Coverage (likelihood of non-detections)**: the catalog stars the attitude puts inside the
   field of view (shrunk by ``edge_margin``) and at least ``mag_margin`` brighter than the
   catalog limit should have been detected. With ``coverage_limit = "matched"`` only stars no
   fainter than the faintest matched star count, so a frame cut to its N brightest detections is
   not penalised for the stars below the cut; ``"catalog"`` counts every catalog star in the
   field (frames complete to the catalog limit; much stronger against wrong two-star matches);
   ``"auto"`` (default) uses "matched" for frames of at least ``full_frame`` detections (which
   may have been cut) and "catalog" below (which cannot have been cut there). If fewer than
   ``min_coverage`` of them are matched, the hypothesis is rejected: a wrong match lands on a
   sky patch whose bright stars are missing from the frame. Real frames miss stars (a star near
   the detection limit, one hidden by a hot pixel or a cosmic ray): a hypothesis of at least
   ``coverage_min_matched`` stars below ``min_coverage`` is still accepted when its number of
   missed stars is plausible for a sensor that misses each predicted star with probability
   ``miss_rate``: the binomial tail ``P(misses >= observed)`` is at least ``coverage_alpha``
   (10 % missed stars: 4 of 6, 6 of 9 or 9 of 13 pass, 4 of 12 or 2 of 8 do not). Sets of two or
   three stars keep the fixed ``min_coverage`` floor: with so few stars the coverage is most of
   the evidence against a coincidental match. A match whose stars line up by chance with
   probability at most ``coverage_chance`` (:func:`chance_alignment`) stands whatever its coverage,
   flagged ``low_coverage``: a frame that lost stars (a cloud, a baffle edge; docs/identification.md
   gives the perturbed real frames' case) keeps an identification the geometry has already decided.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numba import njit
from scipy.special import betainc

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog, chord_of_angle
from firmware_model.ident.attitude import AttitudeSolution, solve_attitude, solve_attitude_kernel


@dataclass(frozen=True)
class FieldOfView:
    """Where the sensor sees: a camera array (with an edge margin in pixels) or a cone about +z.

    ``radius`` (rad) bounds the field; it selects catalog stars before the exact test.
    """

    radius: float
    camera: CameraModel | None = None
    edge_margin_px: float = 3.0

    @classmethod
    def from_camera(cls, camera: CameraModel, edge_margin_px: float = 3.0) -> FieldOfView:
        return _camera_field(camera, float(edge_margin_px))

    @classmethod
    def cone(cls, half_angle: float) -> FieldOfView:
        return cls(float(half_angle))

    @property
    def solid_angle(self) -> float:
        """Solid angle of the field (sr): the array through the pinhole part of the camera, or the cone."""
        if self.camera is None:
            return float(2.0 * np.pi * (1.0 - np.cos(self.radius)))
        return float(self.camera.width * self.camera.height / self.camera.f**2)

    def contains(self, v_sensor: np.ndarray) -> np.ndarray:
        """Boolean mask of sensor-frame unit vectors inside the field (with the edge margin)."""
        v = np.asarray(v_sensor, float)
        if self.camera is None:
            return v[:, 2] > np.cos(self.radius)
        ok = v[:, 2] > 1e-6
        out = np.zeros(len(v), bool)
        if ok.any():
            x, y = self.camera.vector_to_pixel(v[ok])
            m = self.edge_margin_px
            out[ok] = (
                (x >= -0.5 + m)
                & (x <= self.camera.width - 0.5 - m)
                & (y >= -0.5 + m)
                & (y <= self.camera.height - 0.5 - m)
            )
        return out


@dataclass(frozen=True)
class VerifyParams:
    """Knobs of the verification (see module docstring)."""

    residual_sigmas: float = 5.0
    max_normalised_rms: float = 3.0
    refine_sigmas: float = 4.0
    refine_passes: int = 2
    colour_gate: float = 4.65
    min_coverage: float = 0.7
    miss_rate: float = 0.1
    coverage_alpha: float = 2e-3
    coverage_min_matched: int = 2
    mag_margin: float = 0.0
    coverage_limit: str = "auto"
    drop_ambiguous: bool = True
    full_frame: int = 20
    enabled: bool = True
    frame_detections: int = 0  #: detections in the whole frame when the solver sees a subset (chance_alignment)
    coverage_chance: float = 1e-9  #: a match this unlikely by chance stands whatever its coverage (step 3)
    deep: bool = False  #: refine against every catalog star, verification-only ones included


@dataclass
class VerifiedMatch:
    """A hypothesis that passed verification: matched detection/catalog indices, attitude,
    coverage = matched / predicted-visible catalog stars, the counts behind it, and whether all
    candidate matches of its seed pair were explored and its seed-pair Delta (set by the matcher)."""

    det: np.ndarray
    cat: np.ndarray
    attitude: AttitudeSolution
    coverage: float
    n_predicted: int
    n_consensus: int
    explored_all: bool = True
    seed_delta: float = 0.0
    confirmed: int = 1
    low_coverage: bool = False
    chance: float = 1.0  #: probability that its stars beyond the first two line up by chance (chance_alignment)
    n_pattern: int = -1  #: matched pattern stars (the verification-only ones left out); -1: every matched star

    @property
    def n_decisive(self) -> int:
        """Matched stars the star-count rules count: the pattern stars (the chance counts all)."""
        return self.n if self.n_pattern < 0 else self.n_pattern

    @property
    def n(self) -> int:
        return len(self.det)


@lru_cache(maxsize=64)
def _camera_field(camera: CameraModel, edge_margin_px: float) -> FieldOfView:
    """:meth:`FieldOfView.from_camera`, kept per camera (each solve asks for it several times)."""
    xs = np.array([-0.5, camera.width - 0.5, -0.5, camera.width - 0.5])
    ys = np.array([-0.5, -0.5, camera.height - 0.5, camera.height - 0.5])
    v = camera.pixel_to_vector(xs, ys)
    radius = float(np.max(np.arccos(np.clip(v[:, 2], -1.0, 1.0))))
    return FieldOfView(radius * 1.02 + 1e-4, camera, edge_margin_px)


def miss_tail(n_pred: int, n_missed: int, miss_rate: float) -> float:
    """``P(X >= n_missed)`` for ``X ~ Binomial(n_pred, miss_rate)``: the chance that a sensor that
    misses each predicted star with probability ``miss_rate`` misses at least this many."""
    if n_missed <= 0:
        return 1.0
    if n_missed > n_pred or miss_rate <= 0.0:
        return 0.0
    return binomial_tail(n_pred, n_missed, min(float(miss_rate), 1.0))


def binomial_tail(n: int, k: int, p: float) -> float:
    """``P(X >= k)`` for ``X ~ Binomial(n, p)``, ``0 < k <= n``: the regularised incomplete beta
    function ``I_p(k, n - k + 1)`` (the sum of the terms to relative 1e-12, and well below 1e-250
    where the sum underflows)."""
    return float(betainc(k, n - k + 1, p))


def chance_alignment(n_det: int, n_pred: int, n_matched: int, gate_rad: float, solid_angle: float) -> float:
    """Probability that a wrong attitude, fixed by two star pairs, still finds ``n_matched - 2`` of
    the other ``max(n_pred, n_matched) - 2`` predicted stars each with some of the ``n_det``
    detections inside a gate of ``gate_rad`` by chance: the binomial tail with the chance
    ``n_det pi gate^2 / solid_angle`` per star (detections spread uniformly over the field)."""
    k, trials = n_matched - 2, max(n_pred, n_matched) - 2
    if k <= 0:
        return 1.0
    return binomial_tail(trials, k, min(1.0, n_det * np.pi * gate_rad**2 / solid_angle))


def coverage_ok(n_pred: int, n_matched: int, params: VerifyParams) -> bool:
    """The coverage test of step 3 (module docstring)."""
    if n_pred == 0 or n_matched >= params.min_coverage * n_pred:
        return True
    if n_matched < params.coverage_min_matched or params.miss_rate <= 0.0:
        return False
    return miss_tail(n_pred, n_pred - n_matched, params.miss_rate) >= params.coverage_alpha


def verify(
    det: np.ndarray,
    cat: np.ndarray,
    vectors: np.ndarray,
    rg: np.ndarray,
    bg: np.ndarray,
    sigma: np.ndarray,
    catalog: OnboardCatalog,
    fov: FieldOfView,
    noise_rg: float,
    noise_bg: float,
    params: VerifyParams,
) -> tuple[VerifiedMatch | None, str]:
    """Check one hypothesis; returns ``(VerifiedMatch, "")`` or ``(None, reason)``."""
    det = np.asarray(det, np.int64)
    cat = np.asarray(cat, np.int64)
    vectors, sigma = np.ascontiguousarray(vectors, float), np.ascontiguousarray(sigma, float)
    n_consensus = len(det)
    if len(det) < 2:
        return None, "fewer than two matched stars"
    if not params.enabled:
        sol = solve_attitude(vectors[det], catalog.vec[cat], sigma[det])
        return VerifiedMatch(det, cat, sol, float("nan"), 0, n_consensus), ""
    # 1. residual test
    keep, boresight = _residual_step(det, cat, vectors, sigma, catalog.vec[cat], float(params.residual_sigmas))
    det, cat = det[keep], cat[keep]
    if len(det) < 2:
        return None, "residual test left fewer than two stars"
    # 2. refinement with all detections, against the catalog stars near the boresight; 2a-2c
    tree = catalog._deep_tree if params.deep else catalog._tree
    near = np.asarray(tree.query_ball_point(boresight, chord_of_angle(min(fov.radius, np.pi))), np.int64)
    if len(near) == 0:
        return None, "no catalog star in the field of view"
    near_vec = catalog.vec[near]
    det, cat, seen, solved = _refine_steps(
        det,
        cat,
        catalog.vec[cat],
        catalog.rg[cat].astype(float),
        catalog.bg[cat].astype(float),
        vectors,
        np.ascontiguousarray(rg, float),
        np.ascontiguousarray(bg, float),
        sigma,
        near,
        near_vec,
        catalog.rg[near].astype(float),
        catalog.bg[near].astype(float),
        float(noise_rg),
        float(noise_bg),
        float(params.refine_sigmas),
        float(params.residual_sigmas),
        int(params.refine_passes),
        float(params.colour_gate),
        bool(params.drop_ambiguous),
    )
    if len(det) < 2:
        return None, "final residual test left fewer than two stars"
    q, a, p, res, rms, s0, p0 = solved
    sol = AttitudeSolution(q, a, p, res, float(rms), float(s0), p0)
    chi = float(np.sqrt(np.mean((res / sigma[det]) ** 2)))
    if chi > params.max_normalised_rms:
        return None, f"residuals {chi:.1f} sigma RMS: inconsistent with the measurement noise"
    # 3. coverage of predicted-visible catalog stars
    mag_limit = catalog.pattern_mag_limit - params.mag_margin
    limit = params.coverage_limit
    if limit == "auto":
        limit = "matched" if len(vectors) >= params.full_frame else "catalog"
    if limit == "matched":
        mag_limit = min(mag_limit, float(np.max(catalog.mag[cat])))
    in_view = fov.contains(near_vec @ sol.a.T)
    bright = (catalog.mag[near] <= mag_limit) & (near < catalog.n_pattern_stars)  # pattern stars, also with deep
    inside = near[bright & in_view]
    n_pred = len(inside)
    matched_inside = int(np.count_nonzero((inside[:, None] == seen[None, :]).any(axis=1)))
    coverage = matched_inside / n_pred if n_pred else 1.0
    gate = params.residual_sigmas * statistics.median(sigma[det].tolist())
    # the chance over every catalog star looked for: with ``deep``, the verification-only ones too
    trials = int(in_view.sum()) if params.deep else n_pred
    chance = chance_alignment(max(len(vectors), params.frame_detections), trials, len(det), gate, fov.solid_angle)
    n_pattern = int(np.count_nonzero(cat < catalog.n_pattern_stars))
    if not coverage_ok(n_pred, matched_inside, params) and not chance <= params.coverage_chance:
        return None, (
            f"coverage {matched_inside}/{n_pred} predicted stars below {params.min_coverage} "
            f"and not explained by a {params.miss_rate:g} miss rate"
        )
    return VerifiedMatch(
        det,
        cat,
        sol,
        float(coverage),
        n_pred,
        n_consensus,
        low_coverage=bool(n_pred and coverage < params.min_coverage),
        chance=chance,
        n_pattern=n_pattern,
    ), ""


def warm_up() -> None:
    """Compile (or load from numba's disk cache) the verification's kernels, with the array types
    a solve passes them, on a five-star field."""
    cam = CameraModel(64, 48, 100.0, 31.5, 23.5)
    v = cam.pixel_to_vector(np.array([5.0, 60.0, 10.0, 50.0, 30.0]), np.array([4.0, 6.0, 40.0, 44.0, 20.0]))
    colour = np.zeros(5)
    catalog = OnboardCatalog.build(np.arange(5), v, np.arange(5.0), colour, colour, phi_min=0.0, phi_max=1.0)
    three = np.arange(3)
    field = FieldOfView.from_camera(cam)
    verify(three, three, v, colour, colour, np.full(5, 1e-3), catalog, field, 0.1, 0.1, VerifyParams())


# --- compiled steps 1-2c (numba, cached on disk): two calls instead of ~60 small array operations
# and up to ten attitude solves a hypothesis; the arithmetic the module docstring states.


@njit(cache=True, nogil=True)
def _scatter(b, sigma, cov):  # pragma: no cover - compiled
    """Per-star 1-sigma angular scatter (rad) of measured vs predicted direction (step 2's
    ``sqrt(sigma^2 + (tr P - b^T P b) / 2)``; inf for an unobservable attitude)."""
    out = np.empty(len(b))
    if not np.all(np.isfinite(cov)):
        out[:] = np.inf
        return out
    tr = cov[0, 0] + cov[1, 1] + cov[2, 2]
    for i in range(len(b)):
        q = 0.0
        for j in range(3):
            for k in range(3):
                q += b[i, j] * cov[j, k] * b[i, k]
        out[i] = np.sqrt(sigma[i] ** 2 + max(0.5 * (tr - q), 0.0))
    return out


@njit(cache=True, nogil=True)
def _colour_ok(rg_d, bg_d, rg_c, bg_c, noise_rg, noise_bg, gate):  # pragma: no cover - compiled
    """Whether a detection's colours lie within ``gate`` of a catalog star's (unknown ones count 0)."""
    a = (rg_d - rg_c) / noise_rg
    b = (bg_d - bg_c) / noise_bg
    d2 = (a * a if np.isfinite(a) else 0.0) + (b * b if np.isfinite(b) else 0.0)
    return np.sqrt(d2) < gate


@njit(cache=True, nogil=True)
def _free(n, det):  # pragma: no cover - compiled
    """Rows of ``n`` detections not in ``det``, ascending."""
    taken = np.zeros(n, np.bool_)
    taken[det] = True
    return np.flatnonzero(~taken)


@njit(cache=True, nogil=True)
def _residual_step(det, cat, vectors, sigma, cvec, residual_sigmas):  # pragma: no cover - compiled
    """Step 1 of :func:`verify` on detections ``det`` matched to catalog stars ``cat`` (directions
    ``cvec``): the stars kept (a mask, fewer than two when the test leaves fewer) and the boresight
    in ICRS."""
    _, a, _, res, _, _, p0 = solve_attitude_kernel(vectors[det], cvec, sigma[det])
    keep = res <= residual_sigmas * np.maximum(_scatter(vectors[det], sigma[det], p0), sigma[det])
    if not np.all(keep) and np.sum(keep) >= 2:
        _, a, _, _, _, _, _ = solve_attitude_kernel(vectors[det[keep]], cvec[keep], sigma[det[keep]])
    return keep, a[2].copy()


@njit(cache=True, nogil=True)
def _refine_steps(
    det,
    cat,
    cvec,
    crg,
    cbg,
    vectors,
    rg,
    bg,
    sigma,
    near,
    near_vec,
    near_rg,
    near_bg,
    noise_rg,
    noise_bg,
    refine_sigmas,
    residual_sigmas,
    refine_passes,
    colour_gate,
    drop_ambiguous,
):  # pragma: no cover - compiled
    """Steps 2, 2a, 2b and 2c of :func:`verify` on a hypothesis past step 1 (detections ``det`` on
    catalog stars ``cat``, their directions and colours ``cvec, crg, cbg``; the catalog stars
    ``near`` the boresight, theirs ``near_vec, near_rg, near_bg``): (matched detections, catalog
    stars, the catalog stars seen before 2b, their attitude solve; fewer than two stars when 2c
    left fewer)."""
    n = len(vectors)
    colour = noise_rg > 0 and noise_bg > 0
    solved = solve_attitude_kernel(vectors[det], cvec, sigma[det])
    _, a, _, res, _, _, p0 = solved
    for _ in range(refine_passes):  # 2. refinement against the catalog stars near the boresight
        free = _free(n, det)
        if len(free) == 0:
            break
        pred = near_vec @ a.T
        tol = refine_sigmas * _scatter(vectors[free], sigma[free], p0)
        add_det = np.empty(len(free), np.int64)
        add_k = np.empty(len(free), np.int64)
        m = 0
        for i in range(len(free)):
            b = vectors[free[i]]
            nearest, best_dot = 0, -np.inf
            for k in range(len(near)):
                dot = b[0] * pred[k, 0] + b[1] * pred[k, 1] + b[2] * pred[k, 2]
                if dot > best_dot:
                    nearest, best_dot = k, dot
            d = b - pred[nearest]
            ang = 2.0 * np.arcsin(min(max(np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / 2.0, 0.0), 1.0))
            if not (ang < tol[i]) or np.any(cat == near[nearest]):
                continue
            if colour and not _colour_ok(
                rg[free[i]], bg[free[i]], near_rg[nearest], near_bg[nearest], noise_rg, noise_bg, colour_gate
            ):
                continue
            add_det[m], add_k[m] = free[i], nearest
            m += 1
        if m == 0:
            break
        # one detection per catalog star, the first, in catalog order
        order = np.argsort(near[add_k[:m]], kind="mergesort")
        first = np.ones(m, np.bool_)
        for j in range(1, m):
            first[j] = near[add_k[order[j]]] != near[add_k[order[j - 1]]]
        k_new = add_k[order[first]]
        det = np.concatenate((det, add_det[order[first]]))
        cat = np.concatenate((cat, near[k_new]))
        cvec = np.concatenate((cvec, near_vec[k_new]))
        crg = np.concatenate((crg, near_rg[k_new]))
        cbg = np.concatenate((cbg, near_bg[k_new]))
        solved = solve_attitude_kernel(vectors[det], cvec, sigma[det])
        _, a, _, res, _, _, p0 = solved
    # 2a. one detection per catalog star, the closest
    free = _free(n, det)
    if len(free):
        pred = cvec @ a.T
        tol = refine_sigmas * _scatter(vectors[free], sigma[free], p0)
        best = np.full(len(cat), -1)
        best_sep = np.full(len(cat), np.inf)
        for i in range(len(free)):
            b = vectors[free[i]]
            for k in range(len(cat)):
                dot = b[0] * pred[k, 0] + b[1] * pred[k, 1] + b[2] * pred[k, 2]
                sep = 2.0 * np.arcsin(min(max(np.sqrt(max(2.0 - 2.0 * dot, 0.0)) / 2.0, 0.0), 1.0))
                if not (sep < min(tol[i], res[k])) or not sep < best_sep[k]:
                    continue
                if colour and not _colour_ok(rg[free[i]], bg[free[i]], crg[k], cbg[k], noise_rg, noise_bg, colour_gate):
                    continue
                best[k], best_sep[k] = i, sep
        if np.any(best >= 0):
            det = det.copy()
            for k in range(len(cat)):
                if best[k] >= 0:
                    det[k] = free[best[k]]
            keep = np.ones(len(det), np.bool_)
            taken = np.zeros(n, np.bool_)
            for k in range(len(det)):
                keep[k] = not taken[det[k]]
                taken[det[k]] = True
            det, cat, cvec, crg, cbg = det[keep], cat[keep], cvec[keep], crg[keep], cbg[keep]
            solved = solve_attitude_kernel(vectors[det], cvec, sigma[det])
            _, a, _, res, _, _, p0 = solved
    seen = cat
    # 2b. identities that cannot be told apart: another catalog star inside the gate
    if drop_ambiguous and len(det) > 2:
        pred = near_vec @ a.T
        gate = 2.0 * np.sin(refine_sigmas * _scatter(vectors[det], sigma[det], p0) / 2.0)
        clear = np.ones(len(det), np.bool_)
        for i in range(len(det)):
            b = vectors[det[i]]
            closest = np.inf
            for k in range(len(near)):
                if near[k] != cat[i]:
                    dot = b[0] * pred[k, 0] + b[1] * pred[k, 1] + b[2] * pred[k, 2]
                    closest = min(closest, np.sqrt(max(2.0 - 2.0 * dot, 0.0)))
            clear[i] = closest >= gate[i]
        if not np.all(clear) and np.sum(clear) >= 2:
            det, cat, cvec = det[clear], cat[clear], cvec[clear]
            solved = solve_attitude_kernel(vectors[det], cvec, sigma[det])
            _, a, _, res, _, _, p0 = solved
    # 2c. final residual test on the measurement noise alone
    for _ in range(refine_passes + 1):
        keep = res <= residual_sigmas * sigma[det]
        if np.all(keep):
            break
        det, cat, cvec = det[keep], cat[keep], cvec[keep]
        if len(det) < 2:
            return det, cat, seen, solved
        solved = solve_attitude_kernel(vectors[det], cvec, sigma[det])
        _, a, _, res, _, _, p0 = solved
    return det, cat, seen, solved
