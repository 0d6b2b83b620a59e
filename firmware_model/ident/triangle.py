"""Geometric fallback beyond the papers: triangle candidates checked by verification.

Seed 001's 4-star voting needs pair-angle errors of about 0.01 deg; with larger errors every
angle has hundreds of candidate pairs and no signature row is unique. This matcher keeps the
K-vector look-up but lets the whole frame decide: for a triad of bright detections ``(i, j, k)``
it joins the candidate pairs of the three sides into catalog triangles (``a-b`` for ``i-j``,
``a-c`` for ``i-k``, ``b-c`` for ``j-k``) with the same handedness as the measured triad, and
passes each triangle (best angle fit first) to the verification (attitude, refinement with all
detections, coverage). The largest verified set wins; work is bounded by ``max_triads`` and
``max_triangles`` per triad.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from typing import Callable

import numpy as np

from firmware_model.onboard_catalog import OnboardCatalog, angle_between, chord_of_angle


@dataclass(frozen=True)
class TriangleParams:
    """max_stars: brightest detections forming triads; max_triads: triads tried;
    max_triangles: catalog triangles verified per triad (best fit first); max_pairs: candidate
    pairs per side above which the triad is skipped; decisive_stars: a verified set this large
    ends the search; probe_stars, probe_gate: before the full verification a triangle must put at
    least one of the next ``probe_stars`` bright detections within ``probe_gate_eps * eps`` of some
    catalog star (when the frame has such detections): a cheap filter for wrong triangles."""

    max_stars: int = 8
    max_triads: int = 12
    max_triangles: int = 40
    max_pairs: int = 20000
    decisive_stars: int = 6
    probe_stars: int = 6
    probe_gate_eps: float = 2.0


def _side(catalog: OnboardCatalog, theta: float, eps: float, max_pairs: int):
    lo, hi = catalog.kvector_range(theta, eps)
    if hi - lo > max_pairs or hi <= lo:
        return None
    i, j = catalog.pair_i[lo:hi].astype(np.int64), catalog.pair_j[lo:hi].astype(np.int64)
    return np.concatenate([i, j]), np.concatenate([j, i])  # both orientations: (first, second)


def triangles(v3: np.ndarray, catalog: OnboardCatalog, eps: float, max_pairs: int = 20000) -> np.ndarray:
    """Catalog triangles ``(a, b, c)`` matching detections ``v3[0], v3[1], v3[2]`` within ``eps``
    on all sides, same handedness, sorted by summed angle error; shape (M, 3)."""
    ij = _side(catalog, float(angle_between(v3[0], v3[1])), eps, max_pairs)
    ik = _side(catalog, float(angle_between(v3[0], v3[2])), eps, max_pairs)
    jk = _side(catalog, float(angle_between(v3[1], v3[2])), eps, max_pairs)
    if ij is None or ik is None or jk is None:
        return np.empty((0, 3), np.int64)
    n = catalog.n_stars
    order = np.argsort(ik[0], kind="stable")
    ik_a, ik_c = ik[0][order], ik[1][order]
    lo = np.searchsorted(ik_a, ij[0], "left")
    hi = np.searchsorted(ik_a, ij[0], "right")
    count = hi - lo
    if count.sum() == 0:
        return np.empty((0, 3), np.int64)
    rows = np.repeat(np.arange(len(ij[0])), count)
    pos = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count) + np.repeat(lo, count)
    a, b, c = ij[0][rows], ij[1][rows], ik_c[pos]
    keys = np.sort(jk[0] * n + jk[1])
    hit = np.isin(b * n + c, keys, assume_unique=False) & (c != b)
    tri = np.stack([a[hit], b[hit], c[hit]], axis=1)
    if len(tri) == 0:
        return tri
    cv = catalog.vec
    hand = np.sign(np.linalg.det(np.stack([cv[tri[:, 0]], cv[tri[:, 1]], cv[tri[:, 2]]], axis=1)))
    tri = tri[hand == np.sign(np.linalg.det(v3))]
    if len(tri) == 0:
        return tri
    meas = np.array([angle_between(v3[0], v3[1]), angle_between(v3[0], v3[2]), angle_between(v3[1], v3[2])])
    err = (np.abs(angle_between(cv[tri[:, 0]], cv[tri[:, 1]]) - meas[0])
           + np.abs(angle_between(cv[tri[:, 0]], cv[tri[:, 2]]) - meas[1])
           + np.abs(angle_between(cv[tri[:, 1]], cv[tri[:, 2]]) - meas[2]))
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


def match_triangles(vectors: np.ndarray, catalog: OnboardCatalog, eps: float,
                    verify: Callable[[np.ndarray, np.ndarray], tuple[object | None, str]],
                    params: TriangleParams = TriangleParams(), deadline: float | None = None):
    """Verified hypotheses from triangle candidates, best (most stars) first; ``deadline`` is a
    ``time.perf_counter`` value."""
    import time

    found = []
    n = min(len(vectors), params.max_stars)
    for t, (i, j, k) in enumerate(combinations(range(n), 3)):
        if t >= params.max_triads or (deadline is not None and time.perf_counter() > deadline):
            break
        det = np.array([i, j, k])
        others = np.setdiff1d(np.arange(min(len(vectors), 3 + params.probe_stars + 3)), det)[: params.probe_stars]
        tris = triangles(vectors[det], catalog, eps, params.max_pairs)[: params.max_triangles]
        if len(tris) and len(others):
            tris = tris[_probe(vectors[det], tris, vectors[others], catalog, chord_of_angle(params.probe_gate_eps * eps))]
        for tri in tris:
            if any(set(tri.tolist()) <= set(f.cat.tolist()) for f in found):
                continue  # already part of a verified set
            match, _ = verify(det, tri)
            if match is not None:
                found.append(match)
        if found and max(f.n for f in found) >= params.decisive_stars:
            break
    return sorted(found, key=lambda f: (-f.n, -(f.coverage if np.isfinite(f.coverage) else 0.0)))
