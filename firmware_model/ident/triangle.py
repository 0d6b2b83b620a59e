"""Geometric fallback beyond the papers: triangle candidates checked by verification.

Dong et al.'s 4-star voting needs pair-angle errors of about 0.01 deg; with larger errors every
angle has hundreds of candidate pairs and no signature row is unique. This matcher keeps the
K-vector look-up but lets the whole frame decide: for a triad of bright detections ``(i, j, k)``
it joins the candidate pairs of the three sides into catalog triangles (``a-b`` for ``i-j``,
``a-c`` for ``i-k``, ``b-c`` for ``j-k``) with the same handedness as the measured triad, and
passes each triangle (best angle fit first) to the verification (attitude, refinement with all
detections, coverage). The largest verified set wins; work is bounded by ``max_triads`` and
``max_triangles`` per triad.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from firmware_model.catalog.onboard import OnboardCatalog, angle_between, chord_of_angle
from firmware_model.ident.budget import SearchBudget
from firmware_model.ident.verify import VerifiedMatch


@dataclass(frozen=True)
class TriangleParams:
    """max_stars: brightest detections forming triads; max_triads: triads tried;
    max_triangles: catalog triangles verified per triad (best fit first); max_pairs: candidate
    pairs per side above which the triad is skipped; decisive_stars: a verified set this large
    ends the search; probe_stars, probe_gate: before the full verification a triangle must put at
    least one of the next ``probe_stars`` bright detections within ``probe_gate_eps * eps`` of some
    catalog star (when the frame has such detections): a cheap filter for wrong triangles, used
    when the triad has more than ``probe_below`` candidate triangles;
    adaptive: triads move away from detections whose triads failed (``TriadOrder``), False is
    the base order."""

    max_stars: int = 12
    max_triads: int = 40
    max_triangles: int = 40
    max_pairs: int = 20000
    decisive_stars: int = 6
    probe_stars: int = 6
    probe_gate_eps: float = 2.0
    probe_below: int = 3
    adaptive: bool = True


def _side(catalog: OnboardCatalog, theta: float, eps: float, max_pairs: int):
    lo, hi = catalog.kvector_range(theta, eps)
    if hi - lo > max_pairs or hi <= lo:
        return None
    i, j = catalog.pair_i[lo:hi].astype(np.int64), catalog.pair_j[lo:hi].astype(np.int64)
    return np.concatenate([i, j]), np.concatenate([j, i])  # both orientations: (first, second)


def _side_key(a: int, b: int) -> tuple[int, int]:
    """The key of the triangle side between corners ``a`` and ``b`` (smaller corner first)."""
    return (a, b) if a < b else (b, a)


def triangles(v3: np.ndarray, catalog: OnboardCatalog, eps: float, max_pairs: int = 20000) -> np.ndarray:
    """Catalog triangles ``(a, b, c)`` matching detections ``v3[0], v3[1], v3[2]`` within ``eps``
    on all sides, same handedness, sorted by summed angle error; shape (M, 3).

    Two sides sharing a vertex come from the pair table (the first vertex, in detection order,
    whose two sides are in the catalog's pair-angle range); the third side is checked on the
    catalog vectors directly, so it may be longer than ``phi_max`` (a wide field's diagonal
    exceeds the catalog's pair range)."""
    meas = {
        (0, 1): float(angle_between(v3[0], v3[1])),
        (0, 2): float(angle_between(v3[0], v3[2])),
        (1, 2): float(angle_between(v3[1], v3[2])),
    }
    lo_ok, hi_ok = catalog.phi_min - eps, catalog.phi_max + eps
    in_range = {k: lo_ok <= m <= hi_ok for k, m in meas.items()}
    empty = np.empty((0, 3), np.int64)
    for p, q, r in ((0, 1, 2), (1, 0, 2), (2, 0, 1)):
        if in_range[_side_key(p, q)] and in_range[_side_key(p, r)]:
            break
    else:
        return empty
    pq = _side(catalog, meas[_side_key(p, q)], eps, max_pairs)
    pr = _side(catalog, meas[_side_key(p, r)], eps, max_pairs)
    if pq is None or pr is None:
        return empty
    order = np.argsort(pr[0], kind="stable")
    pr_a, pr_c = pr[0][order], pr[1][order]
    lo = np.searchsorted(pr_a, pq[0], "left")
    hi = np.searchsorted(pr_a, pq[0], "right")
    count = hi - lo
    if count.sum() == 0:
        return empty
    rows = np.repeat(np.arange(len(pq[0])), count)
    pos = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count) + np.repeat(lo, count)
    sp, sq, sr = pq[0][rows], pq[1][rows], pr_c[pos]
    cv = catalog.vec
    keep = (sq != sr) & (np.abs(angle_between(cv[sq], cv[sr]) - meas[(q, r)]) <= eps)
    cols = {p: sp[keep], q: sq[keep], r: sr[keep]}
    tri = np.stack([cols[0], cols[1], cols[2]], axis=1)
    if len(tri) == 0:
        return tri
    hand = np.sign(np.linalg.det(np.stack([cv[tri[:, 0]], cv[tri[:, 1]], cv[tri[:, 2]]], axis=1)))
    tri = tri[hand == np.sign(np.linalg.det(v3))]
    if len(tri) == 0:
        return tri
    err = (
        np.abs(angle_between(cv[tri[:, 0]], cv[tri[:, 1]]) - meas[(0, 1)])
        + np.abs(angle_between(cv[tri[:, 0]], cv[tri[:, 2]]) - meas[(0, 2)])
        + np.abs(angle_between(cv[tri[:, 1]], cv[tri[:, 2]]) - meas[(1, 2)])
    )
    return tri[np.argsort(err, kind="stable")]


def _probe(b3: np.ndarray, tris: np.ndarray, others: np.ndarray, catalog: OnboardCatalog, gate: float) -> np.ndarray:
    """Per triangle: whether its attitude (batched SVD solution) puts any of ``others`` on a
    catalog star within chord ``gate``."""
    bm = np.einsum("ki,mkj->mij", b3, catalog.vec[tris])
    u, _, vt = np.linalg.svd(bm)
    d = np.linalg.det(u) * np.linalg.det(vt)
    u[:, :, 2] *= d[:, None]
    a = u @ vt
    r_est = np.einsum("kj,mji->mki", others, a)  # A^T b for every triangle and probe star
    dist, _ = catalog._tree.query(r_est.reshape(-1, 3), k=1)
    return np.any(dist.reshape(len(tris), len(others)) < gate, axis=1)


class TriadOrder:
    """Triads of the ``n`` brightest detections, fewest failed detections first.

    The base order grows the set of detections one at a time ((0,1,2), (0,1,3), (0,2,3),
    (1,2,3), (0,1,4), ...: every triad of the five brightest comes before any triad with the
    sixth). With ``adaptive`` the next triad is the untried one whose detections took part in
    the fewest failed triads (ties: base order), so false detections among the brightest stop
    spoiling triad after triad. A frame whose first triad succeeds sees the base order.
    """

    def __init__(self, n: int, adaptive: bool = True):
        tri = sorted(combinations(range(n), 3), key=lambda t: (t[2], t[1], t[0]))
        self.tri = np.array(tri, np.int64).reshape(-1, 3)
        self.untried = np.ones(len(self.tri), bool)
        self.fails = np.zeros(max(n, 1), np.int64)
        self.adaptive = adaptive

    def __iter__(self):
        return self

    def __next__(self) -> tuple[int, int, int]:
        if not self.untried.any():
            raise StopIteration
        if self.adaptive:
            score = self.fails[self.tri].sum(axis=1) * len(self.tri) + np.arange(len(self.tri))
            t = int(np.argmin(np.where(self.untried, score, np.iinfo(np.int64).max)))
        else:
            t = int(np.argmax(self.untried))
        self.untried[t] = False
        i, j, k = (int(x) for x in self.tri[t])
        return i, j, k

    def failed(self, det) -> None:
        """Report a triad that gave no verified set containing its three detections."""
        self.fails[np.asarray(det, np.int64)] += 1


def match_triangles(
    vectors: np.ndarray,
    catalog: OnboardCatalog,
    eps: float,
    verify: Callable[[np.ndarray, np.ndarray], tuple[VerifiedMatch | None, str]],
    params: TriangleParams = TriangleParams(),
    budget: SearchBudget | None = None,
):
    """Verified hypotheses from triangle candidates, best (most stars) first, and how many catalog
    triangles the detection triads met (each a hypothesis of where they lie: the chance test's
    count); ``budget`` counts the calls to ``verify`` (the caller spends it there) and stops the
    search when it is exhausted."""
    found: list[VerifiedMatch] = []
    met = 0
    n = min(len(vectors), params.max_stars)
    order = TriadOrder(n, params.adaptive)
    for t, (i, j, k) in enumerate(order):
        if t >= params.max_triads or (budget is not None and budget.exhausted):
            break
        det = np.array([i, j, k])
        n_found = len(found)
        others = np.setdiff1d(np.arange(min(len(vectors), 3 + params.probe_stars + 3)), det)[: params.probe_stars]
        tris = triangles(vectors[det], catalog, eps, params.max_pairs)[: params.max_triangles]
        met += len(tris)
        if len(tris) > params.probe_below and len(others):
            # the probe needs a true star among the others: a triad with few candidates is
            # verified in full (a frame with three true stars among false ones)
            tris = tris[
                _probe(vectors[det], tris, vectors[others], catalog, chord_of_angle(params.probe_gate_eps * eps))
            ]
        for tri in tris:
            if budget is not None and budget.exhausted:
                break
            if any(set(tri.tolist()) <= set(f.cat.tolist()) for f in found):
                continue  # already part of a verified set
            match, _ = verify(det, tri)
            if match is not None:
                found.append(match)
        if not any(np.isin(det, f.det).all() for f in found[n_found:]):
            order.failed(det)
        if found and max(f.n for f in found) >= params.decisive_stars:
            break
    return sorted(found, key=lambda f: (-f.n, -(f.coverage if np.isfinite(f.coverage) else 0.0))), met
