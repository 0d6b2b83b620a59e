"""Consensus scene matching of Enright & McVittie section 3.3, with bounded backtracking.

Paper algorithm (greedy RANSAC-style):

1. Take a seed pair of detections ``(k, l)``, find its best catalog pair match (``pair_match``);
   the two stars start the consensus set ``S``.
2. For every other detection ``i``, match the pair ``(i, s)`` with an anchor ``s`` in ``S`` under
   the constraint that ``s`` keeps its catalog star; accept the best constrained match with
   ``Delta < Delta*``.
3. Accept ``i`` into ``S`` only if it is geometrically consistent with every member of ``S``:
   ``|phi_is - phi_rk| < delta_phi* = sigma_phi Delta*/2`` (eqs 8-9).
4. If ``N_S >= eta N_A`` stop (high confidence), otherwise try another seed pair, at most
   ``3 N_A`` attempts; keep the largest set. Outcomes: high confidence, low confidence, no match.

Beyond the paper (every knob in ``ConsensusParams``):

* **Backtracking**: for each seed pair the ``k_best`` best catalog matches are grown, and both
  assignments of a symmetric pair are separate candidates (a colour-swapped pair no longer
  dooms the attempt).
* Growth tries up to ``anchors`` members of ``S`` as the anchor and, among constrained matches
  below ``Delta*``, takes the best one that passes eqs 8-9 (not just the best).
* Every grown set goes through ``verify`` (``firmware_model.ident.verify``): attitude residuals,
  refinement with all detections, coverage of predicted-visible catalog stars. Sets that fail
  are discarded, not reported as low confidence.
* **Confidence**: high only if no verified rival with a different attitude has comparable
  support (``rival_ratio``), and either the verified set has ``N >= eta N_A`` (a two-star answer
  only from a seed pair whose candidates were all explored) or it has at least
  ``confident_stars`` stars covering ``confident_coverage`` of the predicted stars.
* Bounded work: the ``max_stars`` brightest detections are used, at most
  ``min(ceil(attempts_per_star N_A), max_attempts)`` seed pairs, ``k_best`` growths per seed,
  ``max_window`` scored rows per pair look-up, and the solve's counted verifications
  (``budget.SearchBudget``: the search stops when they run out, whatever the machine).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from firmware_model.catalog.onboard import OnboardCatalog, angle_between
from firmware_model.ident.budget import SearchBudget
from firmware_model.ident.pair_match import (
    PairCandidates,
    PairNoise,
    consistency_tolerance,
    critical_distance,
    match_pair,
)
from firmware_model.ident.verify import VerifiedMatch


class Outcome(StrEnum):
    """The three result classes of Enright & McVittie section 3.3."""

    HIGH_CONFIDENCE = "HIGH_CONFIDENCE"
    LOW_CONFIDENCE = "LOW_CONFIDENCE"
    NO_MATCH = "NO_MATCH"


@dataclass(frozen=True)
class ConsensusParams:
    """Consensus matching knobs (defaults: Enright & McVittie values where it gives them).

    p_correct: pair-match success probability defining ``Delta*`` (eq. 7; 0.99 -> 4.65).
    eta: consensus fraction for a high-confidence match (paper: 0.6-0.7).
    attempts_per_star, max_attempts: seed-pair attempts ``min(ceil(attempts_per_star N_A),
        max_attempts)``; the paper's 3 N_A runs out in frames whose brightest detections are
        false (three false among the four brightest leave true pairs only past attempt 3 N_A),
        so the default is 6 N_A, which reaches every pair of up to 12 detections.
    k_best: catalog matches grown per seed pair (backtracking; 1 = paper).
    k_best_sparse: the same for scenes of at most three detections, where the seed pair is
        nearly all the evidence there is.
    anchors: members of ``S`` tried as anchor for a constrained match (1 = paper).
    max_stars: brightest detections used for matching (the rest join in verification).
    max_window: cap on pair-table rows scored per look-up.
    rival_ratio: a distinct verified set with at least this fraction of the best's stars (and at
        least three stars when the best has three or more) makes the answer low confidence.
    rival_angle: attitudes closer than this (rad) are the same hypothesis.
    decisive_stars: a verified set this large (and >= eta N_A) ends the backtracking over the
        remaining candidates of its seed pair.
    min_consensus_rich: in scenes of at least ``rich_scene`` detections, grown sets smaller than
        this are dropped without verification (they could never be high confidence).
    confirmations: the search stops once the best set has been found from this many seed pairs
        (bounds the time of scenes that cannot reach ``eta``, e.g. many false stars).
    confident_stars, confident_coverage: a verified set of at least this many stars that matches
        at least this fraction of the predicted stars is high confidence even below ``eta``
        (false detections do not make an answer that explains the sky less certain).
    chance_stars, chance_alpha: so is a set of at least ``chance_stars`` stars whose stars
        beyond the first two would line up by chance with probability below ``chance_alpha``
        (``verify.chance_alignment``: a sparse field among clutter, where a few stars matched to a
        fraction of a pixel are all the evidence there is).
    last_resort: in rich scenes, up to this many two-star sets skipped by ``min_consensus_rich``
        are verified (the pairs with fewest catalog neighbours first, i.e. the sparsest sky, then
        by seed ``Delta``) when no larger set verified: a frame
        can hold only two true stars among false detections. Such an answer is below ``eta``,
        so it is low confidence.
    adaptive_seeds: seed pairs move away from detections whose seeds failed (``SeedOrder``);
        False is the fixed brightest-first order.
    eta_prefix_min: the geometric matcher's eta test is also passed when, for some ``k`` of at
        least this many, at least ``eta k`` of the ``k`` brightest detections are matched (the
        brightest detections are the ones most likely to be catalog stars; this replaces the
        4/6/8 ladder of solves on the brightest detections, which applied eta to each; 0: off).
    """

    p_correct: float = 0.99
    eta: float = 0.65
    attempts_per_star: float = 6.0
    max_attempts: int = 60
    k_best: int = 4
    k_best_sparse: int = 16
    anchors: int = 2
    max_stars: int = 24
    max_window: int = 4096
    rival_ratio: float = 0.5
    rival_angle: float = 1e-3
    decisive_stars: int = 4
    min_consensus_rich: int = 3
    rich_scene: int = 5
    confirmations: int = 3
    confident_stars: int = 6
    confident_coverage: float = 0.8
    chance_stars: int = 4
    chance_alpha: float = 1e-9
    last_resort: int = 12
    adaptive_seeds: bool = True
    eta_prefix_min: int = 4


@dataclass
class ConsensusResult:
    """Outcome of a scene match: class, best verified match (or None), attempts used, reason."""

    outcome: Outcome
    best: VerifiedMatch | None
    reason: str
    attempts: int = 0
    hypotheses: int = 0
    rivals: list[VerifiedMatch] = field(default_factory=list)
    coincidences: int = 0  #: catalog pairs the seed pairs met as well as the answer's (:func:`pair_hypotheses`)


def detection_angles(vectors: np.ndarray) -> np.ndarray:
    """Matrix of pair angles (rad) between sensor unit vectors."""
    return angle_between(vectors[:, None, :], vectors[None, :, :])


def seed_pairs(n: int):
    """Seed pairs brightest first: (0,1), (0,2), (1,2), (0,3), (1,3), (2,3), ..."""
    for l in range(1, n):
        for k in range(l):
            yield k, l


class SeedOrder:
    """Seed pairs, brightest first, that move away from detections whose seeds failed.

    With ``adaptive`` off this is ``seed_pairs``. With it on, the next pair is the untried one
    whose two detections have taken part in the fewest failed seeds (ties: brightest-first
    order). In a frame whose brightest detections are false, the fixed order spends its attempts
    on pairs of false stars ((0,1), (0,2), (1,2), ... all contain one); after (0,1) fails this
    order tries (2,3), (4,5), ..., so a pair of true stars comes up after a few attempts. A frame
    whose first seed succeeds sees the fixed order.
    """

    def __init__(self, n: int, adaptive: bool = True):
        pairs = list(seed_pairs(n))
        self.k = np.array([p[0] for p in pairs], np.int64)
        self.l = np.array([p[1] for p in pairs], np.int64)
        self.untried = np.ones(len(pairs), bool)
        self.fails = np.zeros(n, np.int64)
        self.adaptive = adaptive
        self._rank = np.arange(len(pairs))

    def __iter__(self):
        return self

    def __next__(self) -> tuple[int, int]:
        if not self.untried.any():
            raise StopIteration
        if self.adaptive:
            score = (self.fails[self.k] + self.fails[self.l]) * len(self._rank) + self._rank
            i = int(np.argmin(np.where(self.untried, score, np.iinfo(np.int64).max)))
        else:
            i = int(np.argmax(self.untried))
        self.untried[i] = False
        return int(self.k[i]), int(self.l[i])

    def failed(self, k: int, l: int) -> None:
        """Report that the seed (k, l) gave no verified set holding both detections."""
        self.fails[k] += 1
        self.fails[l] += 1


def neighbour_table(catalog: OnboardCatalog):
    """Per-star neighbour lists from the pair table (CSR): ``(indptr, neighbour, phi)``.

    Built once per catalog and kept on the instance (``_ident_neighbours``).
    """
    cached = catalog.__dict__.get("_ident_neighbours")
    if cached is not None:
        return cached
    src = np.concatenate([catalog.pair_i, catalog.pair_j]).astype(np.int64)
    dst = np.concatenate([catalog.pair_j, catalog.pair_i]).astype(np.int64)
    phi = np.concatenate([catalog.pair_phi, catalog.pair_phi])
    order = np.argsort(src, kind="stable")
    indptr = np.searchsorted(src[order], np.arange(catalog.n_stars + 1))
    table = (indptr, dst[order], phi[order], catalog.rg.astype(float), catalog.bg.astype(float))
    catalog.__dict__["_ident_neighbours"] = table
    return table


def _sq(x):
    return np.where(np.isfinite(x), x * x, 0.0)


def grow(
    seed_det,
    seed_cat,
    vectors,
    rg,
    bg,
    ang,
    catalog: OnboardCatalog,
    noise: PairNoise,
    delta_star: float,
    params: ConsensusParams,
):
    """Grow a consensus set from a matched seed pair (steps 2-3); returns (det, cat) arrays.

    The constrained pair match of detection ``i`` with anchor ``s`` scores the catalog
    neighbours of ``s``'s catalog star (eq. 4 with the anchor's colour terms); the anchors are
    the first ``params.anchors`` seed stars. Candidates below ``Delta*`` are tried best first and
    the first one consistent with all of ``S`` (eqs 8-9) is accepted.
    """
    indptr, nbr, nphi, crg, cbg = neighbour_table(catalog)
    s_det = list(seed_det)
    s_cat = list(seed_cat)
    dphi_star = consistency_tolerance(noise.sigma_phi, delta_star)
    det_parts: list[np.ndarray] = []
    star_parts: list[np.ndarray] = []
    d_parts: list[np.ndarray] = []
    for s, cs in list(zip(seed_det, seed_cat))[: params.anchors]:
        a, b = indptr[cs], indptr[cs + 1]
        nb = nbr[a:b]
        d2 = ((ang[:, s][:, None] - nphi[None, a:b]) / noise.sigma_phi) ** 2
        d2 += _sq((rg[:, None] - crg[nb][None, :]) / noise.sigma_rg) + _sq(
            (bg[:, None] - cbg[nb][None, :]) / noise.sigma_bg
        )
        d2 += _sq((rg[s] - crg[cs]) / noise.sigma_rg) + _sq((bg[s] - cbg[cs]) / noise.sigma_bg)
        ii, jj = np.nonzero(d2 < delta_star * delta_star)
        det_parts.append(ii)
        star_parts.append(nb[jj])
        d_parts.append(d2[ii, jj])
    cand_det = np.concatenate(det_parts)
    if len(cand_det) == 0:
        return np.array(s_det, np.int64), np.array(s_cat, np.int64)
    cand_star = np.concatenate(star_parts)
    cand_d = np.concatenate(d_parts)
    cvec = catalog.vec
    # eqs 8-9 against the two seed stars, for every candidate at once
    cv = cvec[cand_star]
    keep = (cand_star != s_cat[0]) & (cand_star != s_cat[1]) & (cand_det != s_det[0]) & (cand_det != s_det[1])
    for s, cs in zip(s_det, s_cat):
        keep &= np.abs(ang[cand_det, s] - angle_between(cv, cvec[cs])) < dphi_star
    if not keep.any():
        return np.array(s_det, np.int64), np.array(s_cat, np.int64)
    cand_det, cand_star, cand_d = cand_det[keep], cand_star[keep], cand_d[keep]
    order = np.lexsort((cand_d, cand_det))
    det_list, star_list = cand_det[order].tolist(), cand_star[order].tolist()
    # greedy growth in brightness order; candidates of one detection best first
    extra_det: list[int] = []
    extra_cat: list[int] = []
    k = 0
    while k < len(det_list):
        i = det_list[k]
        stars = []
        while k < len(det_list) and det_list[k] == i:
            stars.append(star_list[k])
            k += 1
        for c in stars:
            if c in extra_cat:
                continue
            if extra_det:
                cat_ang = angle_between(cvec[c], cvec[extra_cat])
                if not np.all(np.abs(ang[i, extra_det] - cat_ang) < dphi_star):
                    continue
            extra_det.append(i)
            extra_cat.append(c)
            break
    return np.array(s_det + extra_det, np.int64), np.array(s_cat + extra_cat, np.int64)


def match_scene(
    vectors: np.ndarray,
    rg: np.ndarray,
    bg: np.ndarray,
    catalog: OnboardCatalog,
    noise: PairNoise,
    params: ConsensusParams,
    verify: Callable[[np.ndarray, np.ndarray], tuple[VerifiedMatch | None, str]],
    budget: SearchBudget | None = None,
) -> ConsensusResult:
    """Consensus match of a scene (module docstring); detections ordered brightest first.

    ``verify(det, cat)`` returns ``(match, "")`` with ``match.n``, ``match.attitude.a`` and
    ``match.attitude.rms``, or ``(None, reason)``; ``budget`` counts the calls to ``verify`` (the
    caller spends it there) and stops the search when it is exhausted.
    """
    n_all = len(vectors)
    n = min(n_all, params.max_stars)
    vectors, rg, bg = vectors[:n], rg[:n], bg[:n]
    if n < 2:
        return ConsensusResult(Outcome.NO_MATCH, None, f"{n_all} detection(s): need at least two")
    delta_star = critical_distance(params.p_correct)
    ang = detection_angles(vectors)
    max_attempts = min(int(np.ceil(params.attempts_per_star * n)), params.max_attempts)
    tol = noise.sigma_phi * delta_star
    k_best = params.k_best_sparse if n <= 3 else params.k_best
    verified: list = []
    small: list = []  # (seed Delta, det, cat, explored_all) of sets skipped as too small
    attempts = 0
    met: list[PairCandidates] = []  # every seed pair's catalog candidates (each one a hypothesis)
    seeded = False
    last_reason = _NO_PAIR
    best = None
    order = SeedOrder(n, params.adaptive_seeds)
    for k, l in order:
        if attempts >= max_attempts:
            break
        if budget is not None and budget.exhausted:
            last_reason = budget.reason
            break
        phi = ang[k, l]
        if not catalog.phi_min - tol < phi <= catalog.phi_max + tol:
            continue
        attempts += 1
        cands = match_pair(np.array([rg[k], bg[k], phi, rg[l], bg[l]]), catalog, noise, delta_star, params.max_window)
        if len(cands) == 0:
            order.failed(k, l)
            if not seeded:
                last_reason = "no seed pair matched the catalog within Delta*"
            continue
        seeded = True
        met.append(cands)
        explored_all = len(cands) <= k_best and not cands.truncated
        good = False
        for m in range(min(k_best, len(cands))):
            det, cat = grow(
                (k, l),
                (int(cands.cat_k[m]), int(cands.cat_l[m])),
                vectors,
                rg,
                bg,
                ang,
                catalog,
                noise,
                delta_star,
                params,
            )
            if n >= params.rich_scene and len(det) < params.min_consensus_rich:
                small.append((float(cands.delta[m]), det, cat, explored_all))
                continue
            if best is not None and len(det) < params.rival_ratio * best.n:
                continue  # can be neither the best nor a rival
            if best is not None and _same_set(best, det, cat):
                best.confirmed += 1
                good = True
                continue
            if budget is not None and budget.exhausted:
                break
            match, why = verify(det, cat)
            if match is None:
                last_reason = f"hypotheses failed verification ({why})"
                continue
            good = good or bool(np.isin([k, l], match.det).all())
            match.explored_all = explored_all
            match.seed_delta = float(cands.delta[m])
            _add_distinct(verified, match, params.rival_angle)
            if match.n >= max(params.decisive_stars, params.eta * n):
                break  # a decisive set: lesser candidates of this seed cannot rival it
        if not good:
            order.failed(k, l)
        if verified:
            best = max(verified, key=_rank)
            if _is_high(best, verified, n, params):
                return ConsensusResult(Outcome.HIGH_CONFIDENCE, best, "", attempts, len(verified))
            if best.confirmed >= params.confirmations:
                break
    if not verified and small:
        # last resort: the frame may hold only two true stars among false ones; a two-star
        # answer is never high confidence here (it is below eta of a rich scene)
        if last_reason == _NO_PAIR:
            last_reason = f"only two-star hypotheses ({len(small)}), none verified"
        # sparse sky first: a frame with two true stars looks at a patch with few catalog stars,
        # and a pair in a dense patch would fail the coverage test anyway
        indptr = neighbour_table(catalog)[0]
        seen_sets, ranked = set(), []
        for delta, det, cat, explored in small:
            key = (tuple(det.tolist()), tuple(cat.tolist()))
            if key not in seen_sets:
                seen_sets.add(key)
                density = int(indptr[cat[0] + 1] - indptr[cat[0]] + indptr[cat[1] + 1] - indptr[cat[1]])
                ranked.append((density, delta, det, cat, explored))
        ranked.sort(key=lambda t: (t[0], t[1]))
        for _, delta, det, cat, explored in ranked[: params.last_resort]:
            if budget is not None and budget.exhausted:
                last_reason = budget.reason
                break
            match, why = verify(det, cat)
            if match is None:
                last_reason = f"two-star hypotheses failed verification ({why})"
                continue
            match.explored_all = explored
            match.seed_delta = delta
            _add_distinct(verified, match, params.rival_angle)
    if not verified:
        return ConsensusResult(Outcome.NO_MATCH, None, last_reason, attempts, 0)
    best = max(verified, key=_rank)
    rivals = _rivals(best, verified, params)
    if rivals:
        reason = f"{len(rivals)} rival hypothesis(es) with comparable support"
    elif best.n < params.eta * n:
        reason = f"consensus {best.n} of {n} detections below eta = {params.eta}"
    elif best.n < 3 and not best.explored_all:
        reason = "two-star match from a seed pair with unexplored candidates"
    else:
        reason = last_reason
    if _is_high(best, verified, n, params):
        return ConsensusResult(Outcome.HIGH_CONFIDENCE, best, "", attempts, len(verified))
    coincidences = pair_hypotheses(met, best.seed_delta)
    expected = chance_answers(best.chance, coincidences)
    if expected > CHANCE_ANSWERS:
        return ConsensusResult(Outcome.NO_MATCH, None, _chance_reason(best, coincidences, expected), attempts, 0)
    return ConsensusResult(Outcome.LOW_CONFIDENCE, best, reason, attempts, len(verified), rivals, coincidences)


#: A low-confidence answer is refused (NO_MATCH) when the search is expected to have met more than
#: this many wrong hypotheses as well supported as it (odds against it) (:func:`chance_answers`): its attitude
#: cannot then be told from a coincidence (a frame of hot pixels or random blobs, no star in it).
CHANCE_ANSWERS = 1.0
#: The reason's opening words for such a refusal.
NOT_A_STAR_FIELD = "not a star field"


def pair_hypotheses(met: list[PairCandidates], max_delta: float = np.inf) -> int:
    """Distinct catalog pairs among the seed pairs' candidates ``met`` that matched their seed pair
    at least as well as ``max_delta`` (Mahalanobis distance: a wrong hypothesis whose seed pair fits
    worse than the answer's is not as well supported); both assignments of one catalog pair are
    one hypothesis of where the pair lies; a truncated window counts what it holds."""
    keys = [
        np.minimum(c.cat_k, c.cat_l)[c.delta <= max_delta] * (1 << 32)
        + np.maximum(c.cat_k, c.cat_l)[c.delta <= max_delta]
        for c in met
        if len(c)
    ]
    return len(np.unique(np.concatenate(keys))) if keys else 0


def chance_answers(chance: float, coincidences: int) -> float:
    """Expected number of wrong hypotheses as well supported as an answer among those the search
    met: each catalog pair a seed pair matched at least as well as the answer's
    (``coincidences``, :func:`pair_hypotheses`, the answer's own excluded) is a hypothesis, and a
    wrong one lines up as many stars beyond its two with probability ``chance``
    (``verify.chance_alignment``; 1 for a two-star answer: its seed pair is all its evidence)."""
    return max(coincidences - 1, 0) * float(chance)


def _chance_reason(best, coincidences: int, expected: float) -> str:
    return (
        f"{NOT_A_STAR_FIELD}: {best.n}-star match expected {expected:.2g} times by chance "
        f"({coincidences} catalog pairs matched the seed pairs as well as its own; chance {best.chance:.2g} "
        "beyond the seed pair)"
    )


_NO_PAIR = "no detection pair within the catalog's pair-angle range"


def _is_high(best, verified: list, n: int, params: ConsensusParams) -> bool:
    """High confidence: no rival, and either the paper's eta test (a two-star set only when its
    seed pair's candidates were all explored) or a large, well-covering verified set."""
    if _rivals(best, verified, params):
        return False
    if getattr(best, "low_coverage", False) and best.n < params.decisive_stars:
        return False  # few stars and many predicted ones missed: plausible, not certain
    if best.n >= params.eta * n and (best.n >= 3 or best.explored_all):
        return True
    return confident(best, params)


def confident(best, params: ConsensusParams) -> bool:
    """The tests beyond eta: a large set covering the predicted stars, or one of at least
    ``chance_stars`` whose alignment by chance is negligible (its missed stars passed
    verification's miss-rate test) (``ConsensusParams``)."""
    if best.n >= params.chance_stars and best.chance <= params.chance_alpha:
        return True
    return large_set(best, params)


def large_set(best, params: ConsensusParams) -> bool:
    """At least ``confident_stars`` matched, covering at least ``confident_coverage`` of the
    predicted stars (an unknown coverage counts as none)."""
    cov = best.coverage if np.isfinite(best.coverage) else 0.0
    return best.n >= params.confident_stars and cov >= params.confident_coverage


def _same_set(match, det, cat) -> bool:
    """Whether the grown set (det, cat) is contained in an already verified match."""
    pairs = set(zip(match.det.tolist(), match.cat.tolist()))
    return all((d, c) in pairs for d, c in zip(det.tolist(), cat.tolist()))


def _rank(v):
    """Preference among verified hypotheses: more stars, better coverage, smaller seed Delta."""
    return v.n, (v.coverage if np.isfinite(v.coverage) else 1.0), -v.seed_delta


def _add_distinct(verified: list, match, rival_angle: float) -> None:
    """Add ``match`` unless a hypothesis with the same attitude is there (keep the larger)."""
    for idx, v in enumerate(verified):
        if _angle(v.attitude.a, match.attitude.a) < rival_angle:
            if _rank(match) > _rank(v):
                match.explored_all = match.explored_all or v.explored_all
                match.confirmed = v.confirmed + 1
                verified[idx] = match
            else:
                v.explored_all = v.explored_all or match.explored_all
                v.confirmed += 1
            return
    verified.append(match)


def _rivals(best, verified: list, params: ConsensusParams) -> list:
    need = max(params.rival_ratio * best.n, min(best.n, 3))  # two-star sets cannot rival a verified triple
    return [
        v
        for v in verified
        if v is not best and v.n >= need and _angle(v.attitude.a, best.attitude.a) >= params.rival_angle
    ]


def _angle(a1: np.ndarray, a2: np.ndarray) -> float:
    c = (np.trace(a1 @ a2.T) - 1.0) / 2.0
    return float(np.arccos(min(1.0, max(-1.0, c))))
