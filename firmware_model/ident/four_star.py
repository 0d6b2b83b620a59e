"""Brightness-independent 4-star matching of Dong et al. (Dong, Xing & You 2006, section 2).

For a group of four detections ``S1..S4`` the six pair angles are ``p1 = (S1,S2), p2 = (S1,S3),
p3 = (S1,S4), p4 = (S2,S3), p5 = (S2,S4), p6 = (S3,S4)``. Each angle's candidate catalog pairs
``|theta' - theta| <= epsilon`` come from the K-vector (eqs 6-7, trimmed to the exact range).
The ``N x 6`` vote matrix ``M`` counts, for every catalog star (row) and pair angle (column), how
often the star appears in that angle's candidates. ``S1`` is identified iff exactly one row equals
``[1 1 1 0 0 0]``; ``S2``: ``[1 0 0 1 1 0]``, ``S3``: ``[0 1 0 1 0 1]``, ``S4``: ``[0 0 1 0 1 1]``.

Groups start at the frame centre (detections sorted by off-axis angle, as the paper asks);
identified stars leave the pool and the group is refilled with the next stars; if a group
identifies nothing, its most central star is discarded; when fewer than four unidentified stars
remain, identified stars fill the group (paper step 6). The loop is bounded by ``max_groups``.

Beyond the paper (``check_consistency``, on by default): a unique signature row can be a
coincidence of a wrong star when the true star's row is spoiled (wide groups have hundreds of
candidates per angle). An identification is accepted only if its catalog star's angle to every
other identified star (this group and earlier ones) matches the measured angle within
``epsilon``, and it has at least one such consistent partner. ``check_consistency=False`` runs
the paper's procedure unchanged (together with ``resolve_ambiguous=False``, see
``identify_group``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware_model.catalog.onboard import OnboardCatalog, angle_between

#: Pair columns p1..p6 as detection positions within the group.
GROUP_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
#: Row signature of S1..S4 (Dong et al. step 5).
SIGNATURES = np.array([[1, 1, 1, 0, 0, 0], [1, 0, 0, 1, 1, 0], [0, 1, 0, 1, 0, 1], [0, 0, 1, 0, 1, 1]])


@dataclass(frozen=True)
class FourStarParams:
    """epsilon: angular measurement accuracy (rad); None means ``epsilon_sigmas * sigma_phi``.
    max_groups: bound on 4-star groups per frame. max_candidates: cap on candidate pairs per angle
    (a larger range leaves that angle without votes, so nothing it touches can be identified).
    check_consistency / resolve_ambiguous: the two additions to the paper (module docstring);
    both False is the paper's procedure.
    stop_after: stop once this many stars are identified (the solver needs three, the attitude
    then identifies the rest); None iterates over the whole frame as the paper does."""

    epsilon: float | None = None
    epsilon_sigmas: float = 3.0
    max_groups: int = 24
    max_candidates: int = 50000
    check_consistency: bool = True
    resolve_ambiguous: bool = True
    stop_after: int | None = None


def group_angles(group_vectors: np.ndarray) -> np.ndarray:
    """The six pair angles p1..p6 (rad) of a 4-star group."""
    g = np.asarray(group_vectors, float)
    return angle_between(g[[a for a, _ in GROUP_PAIRS]], g[[b for _, b in GROUP_PAIRS]])


def vote_matrix(group_vectors: np.ndarray, catalog: OnboardCatalog, epsilon: float, max_candidates: int):
    """Vote matrix restricted to touched rows: ``(rows, M[rows])`` with ``M`` of shape (len(rows), 6)."""
    col_parts: list[np.ndarray] = []
    star_parts: list[np.ndarray] = []
    for r, theta in enumerate(group_angles(group_vectors).tolist()):
        lo, hi = catalog.kvector_range(theta, epsilon)
        if hi - lo > max_candidates:
            continue
        s = np.concatenate([catalog.pair_i[lo:hi], catalog.pair_j[lo:hi]])
        star_parts.append(s)
        col_parts.append(np.full(len(s), r))
    if not star_parts:
        return np.empty(0, np.int64), np.zeros((0, 6), np.int64)
    stars = np.concatenate(star_parts).astype(np.int64)
    cols = np.concatenate(col_parts)
    rows, inverse = np.unique(stars, return_inverse=True)
    m = np.zeros((len(rows), 6), np.int64)
    np.add.at(m, (inverse, cols), 1)
    return rows, m


def identify_group(
    group_vectors: np.ndarray,
    catalog: OnboardCatalog,
    epsilon: float,
    max_candidates: int = 50000,
    resolve_ambiguous: bool = True,
    max_combinations: int = 4096,
) -> np.ndarray:
    """Catalog index of each of the four stars, or -1 where no or several rows match (step 5).

    With ``resolve_ambiguous`` (beyond the paper), a group the signatures leave incomplete is
    retried with relaxed rows (at least one vote in each of the star's three columns, which
    admits the true star when a second pair within ``epsilon`` spoils its exact row): among at
    most ``max_combinations`` assignments, one whose six catalog angles all match the measured
    angles within ``epsilon`` is taken if it is the only one.
    """
    rows, m = vote_matrix(group_vectors, catalog, epsilon, max_candidates)
    out = np.full(4, -1, np.int64)
    if len(rows) == 0:
        return out
    for s in range(4):
        hit = np.nonzero(np.all(m == SIGNATURES[s], axis=1))[0]
        if len(hit) == 1:
            out[s] = rows[hit[0]]
    if resolve_ambiguous and (out < 0).any():
        unique = _unique_consistent(group_vectors, rows, m, catalog, epsilon, max_combinations)
        if unique is not None:
            out = unique
    return out


def _unique_consistent(group_vectors, rows, m, catalog: OnboardCatalog, epsilon: float, max_combinations: int):
    """The only assignment of relaxed candidate rows consistent in all six angles, or None."""
    cands = [rows[np.all(m[:, SIGNATURES[s] == 1] >= 1, axis=1)] for s in range(4)]
    sizes = [len(c) for c in cands]
    if min(sizes) == 0 or np.prod(sizes, dtype=float) > max_combinations:
        return None
    combo = np.stack([g.ravel() for g in np.meshgrid(*cands, indexing="ij")], axis=1)
    ok = np.ones(len(combo), bool)
    for (a, b), theta in zip(GROUP_PAIRS, group_angles(group_vectors).tolist()):
        ok &= combo[:, a] != combo[:, b]
        ok &= np.abs(angle_between(catalog.vec[combo[:, a]], catalog.vec[combo[:, b]]) - theta) <= epsilon
    good = np.nonzero(ok)[0]
    return combo[good[0]].astype(np.int64) if len(good) == 1 else None


@dataclass(frozen=True)
class FourStarResult:
    """Identified detections and their catalog indices, groups tried, detections never identified."""

    det: np.ndarray
    cat: np.ndarray
    groups: int
    unidentified: np.ndarray


def match_four_star(
    vectors: np.ndarray, catalog: OnboardCatalog, epsilon: float, params: FourStarParams = FourStarParams()
) -> FourStarResult:
    """Iterate 4-star groups over the frame (module docstring); ``vectors`` are sensor unit vectors."""
    n = len(vectors)
    centre_order = list(np.argsort(-vectors[:, 2], kind="stable"))  # +z boresight first
    ident: dict[int, int] = {}
    pool = list(centre_order)  # unidentified, not discarded, centre first
    groups = 0
    while n >= 4 and pool and groups < params.max_groups:
        if params.stop_after is not None and len(ident) >= params.stop_after:
            break
        group = pool[:4]
        if len(group) < 4:
            fill = [d for d in centre_order if d in ident][: 4 - len(group)]
            if len(group) + len(fill) < 4:
                break
            group = group + fill
        groups += 1
        ids = identify_group(
            vectors[np.array(group)], catalog, epsilon, params.max_candidates, params.resolve_ambiguous
        )
        newly = [(d, int(c)) for d, c in zip(group, ids) if c >= 0 and d not in ident and c not in ident.values()]
        if params.check_consistency:
            newly = _consistent(newly, ident, vectors, catalog, epsilon)
        for d, c in newly:
            ident[d] = c
            pool.remove(d)
        if not newly:
            pool.remove(group[0] if group[0] in pool else pool[0])
    det = np.array(sorted(ident), np.int64)
    cat = np.array([ident[d] for d in det], np.int64)
    return FourStarResult(det, cat, groups, np.setdiff1d(np.arange(n), det))


def _consistent(newly, ident, vectors, catalog: OnboardCatalog, epsilon: float):
    """The largest subset of the new identifications that is consistent (catalog angle = measured
    angle within ``epsilon``) with every earlier identification and within itself; a subset
    needs two members when nothing was identified before."""
    if not newly:
        return []
    everyone = list(ident.items()) + newly
    det = np.array([d for d, _ in everyone])
    cat = np.array([c for _, c in everyone])
    measured = angle_between(vectors[det][:, None, :], vectors[det][None, :, :])
    expected = angle_between(catalog.vec[cat][:, None, :], catalog.vec[cat][None, :, :])
    ok = np.abs(measured - expected) <= epsilon
    n_old = len(ident)
    fits_old = [k for k in range(n_old, len(everyone)) if ok[k, :n_old].all()]
    best: list[int] = []
    for mask in range(1, 1 << len(fits_old)):
        subset = [fits_old[b] for b in range(len(fits_old)) if mask >> b & 1]
        if len(subset) > len(best) and ok[np.ix_(subset, subset)].all():
            best = subset
    if n_old == 0 and len(best) < 2:
        return []
    return [everyone[k] for k in best]
