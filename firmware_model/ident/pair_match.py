"""Colour star-pair matching of Enright & McVittie (Enright & McVittie 2013, section 3.1-3.2).

An observed pair ``(k, l)`` gives the tuple of eq. 1, ``T = [rg_k, bg_k, phi_kl, rg_l, bg_l]``
(colour ratios ``rg = S_r/S_g``, ``bg = S_b/S_g``; ``phi`` in radians). It is compared with the
catalog tuples by the Mahalanobis distance of eq. 4 with a diagonal covariance, in both
orderings (``k -> i, l -> j`` and ``k -> j, l -> i``). A colour term is left out when either the
observed or the catalog value is NaN, so a monochrome frame or catalog reduces to ``|dphi|/sigma_phi``.

Candidate rows come from the pair table's hash index (eqs 14-16). The search half-width is
``sigma_phi * Delta*``: every tuple with ``Delta < Delta*`` has ``|dphi| < sigma_phi Delta*``, so the
window is exact (the paper's eq. 14 uses ``delta_phi* = sigma_phi Delta*/2``, which would drop
valid matches whose colour terms are small).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.special import erfinv

from firmware_model.catalog.onboard import OnboardCatalog


@lru_cache(maxsize=64)
def critical_distance(p_correct: float) -> float:
    """``Delta* = -2 sqrt(2) erfinv(1 - 2 P_correct)`` (Enright & McVittie eq. 7); 4.65 for P = 0.99."""
    if not 0.5 < p_correct < 1.0:
        raise ValueError(f"P_correct must be in (0.5, 1), got {p_correct}")
    return float(-2.0 * np.sqrt(2.0) * erfinv(1.0 - 2.0 * p_correct))


def consistency_tolerance(sigma_phi: float, delta_star: float) -> float:
    """Geometric consistency bound ``delta_phi* = sigma_phi Delta* / 2`` (Enright & McVittie eq. 9), radians."""
    return 0.5 * sigma_phi * delta_star


def sigma_phi_from_centroid(sigma_pix: float, focal_px: float) -> float:
    """Arc-length noise ``sigma_phi ~ 2 sigma_pix / f`` (Enright & McVittie eq. 18, ``gamma = 1`` px), radians."""
    return 2.0 * sigma_pix / focal_px


@dataclass(frozen=True)
class PairNoise:
    """Diagonal measurement noise of a pair tuple: arc length (rad) and colour ratios."""

    sigma_phi: float
    sigma_rg: float = 0.05
    sigma_bg: float = 0.05

    def __post_init__(self):
        for name in ("sigma_phi", "sigma_rg", "sigma_bg"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")


def pair_angle(s_k: np.ndarray, s_l: np.ndarray) -> float:
    """``phi_kl`` of eq. 2 in radians, computed from the chord (accurate for small angles)."""
    d = float(np.linalg.norm(np.asarray(s_k) - np.asarray(s_l)))
    return 2.0 * float(np.arcsin(min(d / 2.0, 1.0)))


def pair_tuple(s_k, s_l, rg_k, bg_k, rg_l, bg_l) -> np.ndarray:
    """The 5-element tuple of eq. 1: ``[rg_k, bg_k, phi_kl, rg_l, bg_l]``."""
    return np.array([rg_k, bg_k, pair_angle(s_k, s_l), rg_l, bg_l], dtype=float)


def _colour_term(observed, expected, sigma):
    """Squared normalised colour difference; zero where either side is unknown (NaN)."""
    d = (observed - expected) / sigma
    return np.where(np.isfinite(d), d * d, 0.0)


def tuple_distance(t_a: np.ndarray, rg_i, bg_i, phi, rg_j, bg_j, noise: PairNoise) -> np.ndarray:
    """Mahalanobis distance of eq. 4 between ``t_a`` and catalog tuples ``(rg_i, bg_i, phi, rg_j, bg_j)``
    in the ordering ``k -> i, l -> j`` (arrays broadcast)."""
    d2 = ((t_a[2] - phi) / noise.sigma_phi) ** 2
    d2 = d2 + _colour_term(t_a[0], rg_i, noise.sigma_rg) + _colour_term(t_a[1], bg_i, noise.sigma_bg)
    d2 = d2 + _colour_term(t_a[3], rg_j, noise.sigma_rg) + _colour_term(t_a[4], bg_j, noise.sigma_bg)
    return np.sqrt(d2)


@dataclass(frozen=True)
class PairCandidates:
    """Catalog matches of one observed pair with ``Delta < Delta*``, best first.

    ``cat_k[m], cat_l[m]`` are the catalog star indices assigned to the observed stars ``k`` and
    ``l`` by candidate ``m``; ``row`` its pair-table row, ``swapped`` whether ``k -> pair_j``;
    ``delta`` its Mahalanobis distance. ``truncated`` is set when the search window was capped.
    """

    row: np.ndarray
    swapped: np.ndarray
    cat_k: np.ndarray
    cat_l: np.ndarray
    delta: np.ndarray
    truncated: bool = False

    def __len__(self) -> int:
        return len(self.delta)


def _empty_candidates(truncated=False) -> PairCandidates:
    e = np.empty(0, np.int64)
    return PairCandidates(e, np.empty(0, bool), e, e, np.empty(0), truncated)


def match_pair(
    t_a: np.ndarray, catalog: OnboardCatalog, noise: PairNoise, delta_star: float, max_window: int = 4096
) -> PairCandidates:
    """All catalog tuples within ``Delta*`` of ``t_a`` in either ordering, sorted by ``Delta``.

    The candidate rows are located through the hash index (eqs 14-16). If more than
    ``max_window`` rows fall in the window, only the ``max_window`` nearest in angle are scored
    (a bound on the work per call) and the result is flagged ``truncated``.
    """
    phi = float(t_a[2])
    a, b = catalog.hash_range(phi, noise.sigma_phi * delta_star)
    truncated = b - a > max_window
    if truncated:
        centre = int(np.searchsorted(catalog.pair_phi, phi))
        a = max(a, min(centre - max_window // 2, b - max_window))
        b = a + max_window
    if b <= a:
        return _empty_candidates(truncated)
    rows = np.arange(a, b)
    ci, cj, cphi = catalog.pair_i[a:b], catalog.pair_j[a:b], catalog.pair_phi[a:b]
    rg, bg = catalog.rg, catalog.bg
    d_fwd = tuple_distance(t_a, rg[ci], bg[ci], cphi, rg[cj], bg[cj], noise)
    d_rev = tuple_distance(t_a, rg[cj], bg[cj], cphi, rg[ci], bg[ci], noise)
    delta = np.concatenate([d_fwd, d_rev])
    keep = np.nonzero(delta < delta_star)[0]
    if len(keep) == 0:
        return _empty_candidates(truncated)
    keep = keep[np.argsort(delta[keep], kind="stable")]
    n = len(rows)
    swapped = keep >= n
    sel = keep % n
    cat_k = np.where(swapped, cj[sel], ci[sel]).astype(np.int64)
    cat_l = np.where(swapped, ci[sel], cj[sel]).astype(np.int64)
    return PairCandidates(rows[sel], swapped, cat_k, cat_l, delta[keep], truncated)


def best_match(t_a: np.ndarray, catalog: OnboardCatalog, noise: PairNoise, delta_star: float):
    """Maximum-likelihood match ``(cat_k, cat_l, Delta)`` of eq. 4 over both orderings, or None."""
    c = match_pair(t_a, catalog, noise, delta_star)
    if len(c) == 0:
        return None
    return int(c.cat_k[0]), int(c.cat_l[0]), float(c.delta[0])
