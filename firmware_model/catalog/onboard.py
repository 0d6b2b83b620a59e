"""The on-board catalog as the device holds it: stars, the sorted pair table and its indices.

One pair table serves both matching designs:

* Enright & McVittie: pairs with ``phi_min < phi <= phi_max`` sorted by angle, with
  the hash index ``P_h`` of eqs 15-16 (``h = floor(H phi)``, ``H = N_h / phi_max``, ``P_h`` the
  smallest pair index with ``phi_p >= h / H - dphi_star``);
* Dong, Xing & You: Mortari's K-vector over ``cos(theta)`` (eqs 5-7). The K-vector is
  defined on the cosines in ascending order, i.e. on the pair table read backwards; query results
  are mapped back to indices of the angle-sorted table.

Both indices answer the same question: the contiguous range ``[start, stop)`` of pair-table rows
whose angle lies in ``[phi - tol, phi + tol]``. Angles are radians; vectors are ICRS unit vectors.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree


def chord_of_angle(phi):
    """Chord length between unit vectors separated by ``phi`` radians."""
    return 2.0 * np.sin(np.asarray(phi, dtype=float) / 2.0)


def angle_between(u, v):
    """Angle in radians between unit vectors (broadcast over leading axes), accurate near 0."""
    d = np.linalg.norm(np.asarray(u) - np.asarray(v), axis=-1)
    return 2.0 * np.arcsin(np.clip(d / 2.0, 0.0, 1.0))


def build_pair_table(vec: np.ndarray, phi_min: float, phi_max: float):
    """All pairs with ``phi_min < phi <= phi_max`` sorted by angle: (i, j, phi), i < j.

    Uses a KD-tree on the unit vectors (chord distance), so it is O(N log N + P), not O(N^2).
    """
    if not 0.0 <= phi_min < phi_max <= np.pi:
        raise ValueError(f"need 0 <= phi_min < phi_max <= pi, got phi_min={phi_min}, phi_max={phi_max}")
    vec = np.asarray(vec, dtype=float)
    tree = cKDTree(vec)
    # a hair above the chord so pairs at exactly phi_max survive floating-point rounding
    ij = tree.query_pairs(chord_of_angle(phi_max) * (1 + 1e-12), output_type="ndarray")
    if len(ij) == 0:
        return np.empty(0, np.int32), np.empty(0, np.int32), np.empty(0, float)
    ij.sort(axis=1)
    phi = angle_between(vec[ij[:, 0]], vec[ij[:, 1]])
    keep = (phi > phi_min) & (phi <= phi_max)
    ij, phi = ij[keep], phi[keep]
    order = np.lexsort((ij[:, 1], ij[:, 0], phi))
    return ij[order, 0].astype(np.int32), ij[order, 1].astype(np.int32), phi[order]


def build_hash_index(pair_phi: np.ndarray, n_h: int, phi_max: float, dphi_star: float = 0.0) -> np.ndarray:
    """Hash index ``P_h`` (Enright & McVittie eq. 16) with one extra entry ``P_{N_h} = len(pair_phi)``."""
    if n_h < 1:
        raise ValueError(f"N_h must be >= 1, got {n_h}")
    h = np.arange(n_h + 1, dtype=float)
    bounds = h * (phi_max / n_h) - dphi_star
    index = np.searchsorted(pair_phi, bounds, side="left").astype(np.int64)
    index[-1] = len(pair_phi)
    return index


def build_kvector(pair_phi: np.ndarray):
    """Mortari K-vector over ``y = cos(phi)`` ascending (Dong et al. eq. 5).

    Returns ``(k, m, q)``: ``k[i]`` (i = 0..n-1, 0-based) is the number of cosines ``<= z(i+1)``
    with the line ``z(x) = m x + q`` through ``(1, y_min - xi)`` and ``(n, y_max + xi)``.
    """
    y = np.cos(pair_phi[::-1])
    n = len(y)
    if n < 2:
        raise ValueError("the K-vector needs at least two pairs")
    xi = np.finfo(float).eps * max(abs(y[0]), abs(y[-1])) * 4
    m = (y[-1] - y[0] + 2 * xi) / (n - 1)
    q = y[0] - xi - m
    z = m * np.arange(1, n + 1) + q
    k = np.searchsorted(y, z, side="right").astype(np.int64)
    return k, float(m), float(q)


@dataclass
class OnboardCatalog:
    """Stars and pair table of an on-board catalog (arrays, radians, ICRS unit vectors).

    ``rg``/``bg`` are the expected colour ratios of each star for the catalog's detector
    (NaN for a monochrome catalog). ``meta`` holds the build parameters (design, epoch, ...).
    Stars ``[0, n_pattern_stars)`` are the pattern stars: the pairs, the patterns and every
    hypothesis test use them alone. The rows after them (0: none) are fainter verification-only
    stars, matched once an answer is decided (``strategy.match_deep``) so the attitude uses
    every star in view.
    """

    star_id: np.ndarray
    vec: np.ndarray
    mag: np.ndarray
    rg: np.ndarray
    bg: np.ndarray
    pair_i: np.ndarray
    pair_j: np.ndarray
    pair_phi: np.ndarray
    phi_min: float
    phi_max: float
    n_h: int = 1024
    dphi_star: float = 0.0
    hash_index: np.ndarray | None = None
    kvector: np.ndarray | None = None
    kv_m: float = 0.0
    kv_q: float = 0.0
    meta: dict = field(default_factory=dict)
    n_pattern_stars: int = 0  #: 0: every star

    def __post_init__(self):
        if self.n_pattern_stars in (0, self.n_stars):
            self.n_pattern_stars = self.n_stars
        elif not 0 < self.n_pattern_stars < self.n_stars:
            raise ValueError(f"n_pattern_stars = {self.n_pattern_stars} outside [0, {self.n_stars}]")
        if self.hash_index is None:
            self.hash_index = build_hash_index(self.pair_phi, self.n_h, self.phi_max, self.dphi_star)
        if self.kvector is None and len(self.pair_phi) >= 2:
            self.kvector, self.kv_m, self.kv_q = build_kvector(self.pair_phi)

    @classmethod
    def build(
        cls,
        star_id,
        vec,
        mag,
        rg=None,
        bg=None,
        *,
        phi_min,
        phi_max,
        n_h=1024,
        dphi_star=0.0,
        meta=None,
        n_pattern_stars=0,
    ):
        """Build pair table and both indices from star arrays; the pairs from the first
        ``n_pattern_stars`` stars (0: all)."""
        vec = np.asarray(vec, dtype=float)
        n = len(vec)
        nan = np.full(n, np.nan, dtype=np.float32)
        pi, pj, phi = build_pair_table(vec[: n_pattern_stars or n], phi_min, phi_max)
        return cls(
            star_id=np.asarray(star_id, dtype=np.int64),
            vec=vec,
            mag=np.asarray(mag, dtype=np.float32),
            rg=nan if rg is None else np.asarray(rg, dtype=np.float32),
            bg=nan if bg is None else np.asarray(bg, dtype=np.float32),
            pair_i=pi,
            pair_j=pj,
            pair_phi=phi,
            phi_min=float(phi_min),
            phi_max=float(phi_max),
            n_h=int(n_h),
            dphi_star=float(dphi_star),
            meta=dict(meta or {}),
            n_pattern_stars=int(n_pattern_stars),
        )

    @property
    def n_stars(self) -> int:
        return len(self.star_id)

    @property
    def n_pairs(self) -> int:
        return len(self.pair_phi)

    @property
    def has_colour(self) -> bool:
        return bool(np.isfinite(self.rg).any())

    @property
    def has_deep_stars(self) -> bool:
        """Whether verification-only stars follow the pattern stars."""
        return self.n_pattern_stars < self.n_stars

    @cached_property
    def pattern_mag_limit(self) -> float:
        """Faintest pattern star's magnitude."""
        return float(np.max(self.mag[: self.n_pattern_stars]))

    # --- pair range queries -------------------------------------------------------------
    def hash_range(self, phi: float, tol: float) -> tuple[int, int]:
        """Rows ``[start, stop)`` with ``|phi_p - phi| <= tol``, located through ``P_h`` (eqs 14-16)."""
        lo, hi = phi - tol, phi + tol
        scale = self.n_h / self.phi_max
        h_lo = int(np.clip(np.floor(scale * lo), 0, self.n_h))
        h_hi = int(np.clip(np.floor(scale * (hi + self.dphi_star)) + 1, 0, self.n_h))
        assert self.hash_index is not None  # set by __post_init__
        a, b = int(self.hash_index[h_lo]), int(self.hash_index[h_hi])
        window = self.pair_phi[a:b]
        return a + int(np.searchsorted(window, lo, "left")), a + int(np.searchsorted(window, hi, "right"))

    def kvector_candidates(self, phi: float, tol: float) -> tuple[int, int]:
        """Raw K-vector range of Dong et al. eqs 6-7, as rows ``[start, stop)`` of the pair table.

        A superset of the exact range (it may hold a few pairs just outside the tolerance).
        """
        n = self.n_pairs
        if n < 2:
            return (0, 0) if n == 0 or abs(self.pair_phi[0] - phi) > tol else (0, 1)
        lo_cos = np.cos(min(phi + tol, np.pi))
        hi_cos = np.cos(max(phi - tol, 0.0))
        k_bot = int(np.clip(np.floor((lo_cos - self.kv_q) / self.kv_m), 1, n))
        k_top = int(np.clip(np.ceil((hi_cos - self.kv_q) / self.kv_m), 1, n))
        assert self.kvector is not None  # __post_init__ builds it whenever there are two pairs
        start_r = int(self.kvector[k_bot - 1])  # 0-based first row in cosine order (ID_start - 1)
        stop_r = int(self.kvector[k_top - 1])  # 0-based one past the last row (ID_end)
        return n - stop_r, n - start_r

    def kvector_range(self, phi: float, tol: float) -> tuple[int, int]:
        """Exact rows ``[start, stop)`` within tolerance, from the K-vector candidates."""
        a, b = self.kvector_candidates(phi, tol)
        window = self.pair_phi[a:b]
        return a + int(np.searchsorted(window, phi - tol, "left")), a + int(np.searchsorted(window, phi + tol, "right"))

    def pair_ranges(self, phi: np.ndarray, tol) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised exact ranges for many angles (binary search; same answer as the indices)."""
        phi = np.asarray(phi, dtype=float)
        return (
            np.searchsorted(self.pair_phi, phi - tol, "left"),
            np.searchsorted(self.pair_phi, phi + tol, "right"),
        )

    # --- spatial queries ----------------------------------------------------------------
    @cached_property
    def _tree(self) -> cKDTree:
        """KD-tree of the pattern stars (row indices are catalog indices)."""
        return cKDTree(self.vec[: self.n_pattern_stars])

    @cached_property
    def _deep_tree(self) -> cKDTree:
        """KD-tree of every star, verification-only ones included."""
        return cKDTree(self.vec) if self.has_deep_stars else self._tree

    def stars_within(self, direction: np.ndarray, radius: float, deep: bool = False) -> np.ndarray:
        """Indices of pattern stars (``deep``: every star) within ``radius`` radians of unit vector
        ``direction``, sorted."""
        tree = self._deep_tree if deep else self._tree
        idx = tree.query_ball_point(np.asarray(direction, dtype=float), chord_of_angle(radius))
        return np.sort(np.asarray(idx, dtype=np.int64))
