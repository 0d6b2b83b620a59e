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
   flagged ``low_coverage``: a frame that lost stars (a cloud, a baffle edge, the issue 12 set with
   20 % of the stars dropped: 10 of 17 predicted stars matched) keeps an identification the
   geometry has already decided.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import betainc

from firmware_model.catalog.onboard import OnboardCatalog, chord_of_angle
from firmware_model.ident.attitude import AttitudeSolution, solve_attitude
from firmware_model.pipeline.camera import CameraModel


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
        xs = np.array([-0.5, camera.width - 0.5, -0.5, camera.width - 0.5])
        ys = np.array([-0.5, -0.5, camera.height - 0.5, camera.height - 0.5])
        v = camera.pixel_to_vector(xs, ys)
        radius = float(np.max(np.arccos(np.clip(v[:, 2], -1.0, 1.0))))
        return cls(radius * 1.02 + 1e-4, camera, float(edge_margin_px))

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


def _predicted_scatter(b: np.ndarray, sigma: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Per-star 1-sigma angular scatter (rad) of measured vs predicted direction."""
    if not np.all(np.isfinite(cov)):
        return np.full(len(b), np.inf)
    extra = 0.5 * (np.trace(cov) - np.einsum("ij,jk,ik->i", b, cov, b))
    return np.sqrt(sigma**2 + np.maximum(extra, 0.0))


def _chords(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Chord lengths between every unit vector of ``a`` (N, 3) and of ``b`` (M, 3), (N, M), from
    their dot products (no (N, M, 3) difference array; 4e-8 relative at a 20" chord)."""
    return np.sqrt(np.maximum(2.0 - 2.0 * (a @ b.T), 0.0))


def _sq(x):
    return np.where(np.isfinite(x), x * x, 0.0)


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
    n_consensus = len(det)
    if len(det) < 2:
        return None, "fewer than two matched stars"
    sol = solve_attitude(vectors[det], catalog.vec[cat], sigma[det])
    if not params.enabled:
        return VerifiedMatch(det, cat, sol, float("nan"), 0, n_consensus), ""
    # 1. residual test
    scatter = _predicted_scatter(vectors[det], sigma[det], sol.covariance_apriori)
    bad = sol.residuals > params.residual_sigmas * np.maximum(scatter, sigma[det])
    if bad.any():
        det, cat = det[~bad], cat[~bad]
        if len(det) < 2:
            return None, "residual test left fewer than two stars"
        sol = solve_attitude(vectors[det], catalog.vec[cat], sigma[det])
    # 2. refinement with all detections, against the catalog stars near the boresight
    tree = catalog._deep_tree if params.deep else catalog._tree
    near = np.asarray(tree.query_ball_point(sol.a[2], chord_of_angle(min(fov.radius, np.pi))), np.int64)
    if len(near) == 0:
        return None, "no catalog star in the field of view"
    near_vec = catalog.vec[near]
    for _ in range(params.refine_passes):
        free = np.ones(len(vectors), bool)
        free[det] = False
        free = np.nonzero(free)[0]
        if len(free) == 0:
            break
        b = vectors[free]
        pred = near_vec @ sol.a.T
        nearest = np.argmax(b @ pred.T, axis=1)
        idx = near[nearest]
        ang = 2.0 * np.arcsin(np.clip(np.linalg.norm(b - pred[nearest], axis=1) / 2.0, 0.0, 1.0))
        tol = params.refine_sigmas * _predicted_scatter(b, sigma[free], sol.covariance_apriori)
        ok = (ang < tol) & ~np.isin(idx, cat)
        if ok.any() and noise_rg > 0 and noise_bg > 0:
            d2 = _sq((rg[free] - catalog.rg[idx]) / noise_rg) + _sq((bg[free] - catalog.bg[idx]) / noise_bg)
            ok &= np.sqrt(d2) < params.colour_gate
        if not ok.any():
            break
        add_det, add_cat = free[ok], idx[ok]
        _, first = np.unique(add_cat, return_index=True)  # one detection per catalog star
        det = np.concatenate([det, add_det[first]])
        cat = np.concatenate([cat, add_cat[first]])
        sol = solve_attitude(vectors[det], catalog.vec[cat], sigma[det])
    # 2a. one detection per catalog star, the closest: a false detection near a star (taken
    # first because it is brighter) must give way to the star's own detection
    free = np.setdiff1d(np.arange(len(vectors)), det)
    if len(free):
        pred = catalog.vec[cat] @ sol.a.T
        sep = 2.0 * np.arcsin(np.clip(_chords(vectors[free], pred) / 2.0, 0.0, 1.0))
        tol = params.refine_sigmas * _predicted_scatter(vectors[free], sigma[free], sol.covariance_apriori)
        ok = sep < np.minimum(tol[:, None], sol.residuals[None, :])
        if ok.any() and noise_rg > 0 and noise_bg > 0:
            d2 = _sq((rg[free][:, None] - catalog.rg[cat][None, :]) / noise_rg) + _sq(
                (bg[free][:, None] - catalog.bg[cat][None, :]) / noise_bg
            )
            ok &= np.sqrt(d2) < params.colour_gate
        if ok.any():
            sep = np.where(ok, sep, np.inf)
            best = np.argmin(sep, axis=0)  # per matched star, the closest free detection
            swap = np.isfinite(sep[best, np.arange(len(cat))])
            det = det.copy()
            det[swap] = free[best[swap]]
            _, first = np.unique(det, return_index=True)
            keep = np.zeros(len(det), bool)
            keep[first] = True
            det, cat = det[keep], cat[keep]
            sol = solve_attitude(vectors[det], catalog.vec[cat], sigma[det])
    # 2b. identities that cannot be told apart: another catalog star inside the gate
    seen = cat  # they were seen all the same: coverage counts them
    if params.drop_ambiguous and len(det) > 2:
        b = vectors[det]
        pred = near_vec @ sol.a.T
        d = _chords(b, pred)
        d[near[None, :] == cat[:, None]] = np.inf
        gate = chord_of_angle(params.refine_sigmas * _predicted_scatter(b, sigma[det], sol.covariance_apriori))
        clear = d.min(axis=1) >= gate
        if not clear.all() and clear.sum() >= 2:
            det, cat = det[clear], cat[clear]
            sol = solve_attitude(vectors[det], catalog.vec[cat], sigma[det])
    # 2c. final residual test on the measurement noise alone: refinement gates include the
    # attitude covariance, which is large for a loose early hypothesis, so stars taken in then
    # must still fit the final attitude within residual_sigmas of their own noise
    for _ in range(params.refine_passes + 1):
        bad = sol.residuals > params.residual_sigmas * sigma[det]
        if not bad.any():
            break
        det, cat = det[~bad], cat[~bad]
        if len(det) < 2:
            return None, "final residual test left fewer than two stars"
        sol = solve_attitude(vectors[det], catalog.vec[cat], sigma[det])
    chi = float(np.sqrt(np.mean((sol.residuals / sigma[det]) ** 2)))
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
    matched_inside = int(np.isin(inside, seen).sum())
    coverage = matched_inside / n_pred if n_pred else 1.0
    gate = params.residual_sigmas * float(np.median(sigma[det]))
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
