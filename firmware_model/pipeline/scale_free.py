"""Scale-free first match for uncalibrated optics: 4-star patterns whose edge ratios do not
depend on the focal length, as plate solvers do it (tetra3's patterns, astrometry.net's quads).

A pattern is four stars; its key is the six pairwise angles sorted and divided by the largest
(five numbers in (0, 1]). A focal-length error scales every edge alike and leaves the key
unchanged; radial distortion of a few pixels changes it by well under a per cent for patterns of a
few hundred pixels. Catalog patterns (the module constants say which 4-sets) are built once per
(catalog, field) and kept in a KD-tree (L-infinity ball queries).

``pattern_matches`` matches the frame's patterns (every 4-combination of its brightest detections
no wider than the widest catalog pattern, directions taken through the nominal camera), best key
first; each key match gives a focal length (ratio of the catalog's largest edge to the frame's)
and, when asked for (``PatternMatches.hypotheses``), an attitude (the four stars, best of the 24
assignments). ``refine`` then predicts every catalog star in the field, matches detections within
a shrinking radius and fits focal length (and k1) with the attitude
(``firmware_model.pipeline.camera_fit``). The caller verifies the refined match over the whole
frame and judges it as a search-chosen one, or identifies the frame from scratch with the fitted
camera (``firmware_model.pipeline.run``).

Units: radians for angles, pixels for image positions (docs/CONVENTIONS.md).
"""

from __future__ import annotations

import hashlib
import math
import os
import pickle
from dataclasses import dataclass, field
from functools import cache
from itertools import combinations, permutations
from pathlib import Path
from typing import Protocol

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from firmware_model.camera import CameraModel, vector_to_pixel_kernel
from firmware_model.catalog.onboard import OnboardCatalog, angle_between, chord_of_angle
from firmware_model.ident.attitude import svd_attitude_kernel
from firmware_model.pipeline.frame_fit import fit_frame_kernel, fit_result
from firmware_model.pipeline.pattern_index import PatternIndex
from firmware_model.pipeline.pattern_index import warm_up as pattern_index_warm_up

#: Catalog patterns of two kinds, both scale free: (1) for each region of the sky the size of the
#: field (circles of the minor half-field on a Fibonacci lattice spaced REGION_SPACING of that
#: radius), every 4-combination of its REGION_STARS brightest stars, as tetra3 builds its database
#: (a frame's brightest stars are its region's brightest); (2) for each pattern radius and each
#: star with fewer than PATTERN_STARS_PER_CAP brighter stars within it, three of its
#: CATALOG_NEIGHBOURS brightest neighbours there (sparse fields whose stars sit far apart; the
#: wider radius reaches the frame's opposite corners, the narrower keeps the centres it loses).
REGION_STARS = 10
REGION_SPACING = 1.0
CATALOG_NEIGHBOURS = 10
PATTERN_STARS_PER_CAP = 12
#: Pattern radii over the minor half-field (kind 2; the frame's widest pattern: twice the largest).
PATTERN_RADIUS_FACTORS = (1.5, 2.0)
_PAIRS = list(combinations(range(4), 2))
_PAIRS_IJ = np.array(_PAIRS)
_PAIR_I, _PAIR_J = _PAIRS_IJ.T
_PERMS = np.array(list(permutations(range(4))))
#: For each assignment ``p`` of frame star ``k`` to catalog star ``p[k]``, the catalog edge (index
#: into ``_PAIRS``) under each frame edge: an assignment's edges are a permutation of the six.
_PERM_EDGES = np.array([[_PAIRS.index(tuple(sorted((p[i], p[j])))) for i, j in _PAIRS] for p in _PERMS])


class StarTable(Protocol):
    """What :func:`refine` asks of a catalog: its star directions and a cone search."""

    vec: np.ndarray

    def stars_within(self, direction: np.ndarray, radius: float, deep: bool = False) -> np.ndarray: ...


@dataclass(frozen=True)
class Hypothesis:
    """A pattern match: focal length (px), attitude ``a`` (v_sensor = a @ v_icrs) and the key
    distance (largest difference of the edge ratios)."""

    f: float
    a: np.ndarray
    key_distance: float


def pattern_keys(vectors: np.ndarray, groups: np.ndarray):
    """Sorted normalised edge ratios (G, 5) and the largest edge (G,) of 4-star groups (G, 4)."""
    v = vectors[groups]  # (G, 4, 3)
    edges = angle_between(v[:, _PAIR_I], v[:, _PAIR_J])
    edges.sort(axis=1)
    top = edges[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return edges[:, :-1] / top[:, None], top


def _groups(near: list, brightness_rank: np.ndarray, centres: np.ndarray, neighbours: int) -> np.ndarray:
    """4-star groups: each centre with three of its ``neighbours`` brightest neighbours (``near[c]``:
    the stars within the pattern radius of star ``c``)."""
    out = [np.zeros((0, 4), np.int64)]
    for c in centres:
        near_c = np.array([j for j in near[c] if j != c], dtype=np.int64)
        if len(near_c) < 3:
            continue
        near_c = near_c[np.argsort(brightness_rank[near_c])][:neighbours]
        trios = near_c[_trios(len(near_c))]  # every 3 of them, in itertools.combinations' order
        out.append(np.column_stack([np.full(len(trios), c, np.int64), trios]))
    return np.concatenate(out)


@cache
def _trios(n: int) -> np.ndarray:
    """Every 3-combination of ``range(n)`` (rows, in ``itertools.combinations`` order)."""
    return np.array(list(combinations(range(n), 3)), np.int64).reshape(-1, 3)


def _region_groups(tree: cKDTree, mag: np.ndarray, field_radius: float) -> np.ndarray:
    """Every 4-combination of the :data:`REGION_STARS` brightest stars of each field-sized region."""
    spacing = REGION_SPACING * field_radius
    n = int(np.ceil(4.0 * np.pi / spacing**2))
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    points = np.column_stack([np.sqrt(1.0 - z * z) * np.cos(phi), np.sqrt(1.0 - z * z) * np.sin(phi), z])
    out = [np.zeros((0, 4), np.int64)]
    for near in tree.query_ball_point(points, chord_of_angle(field_radius)):
        near = np.asarray(near, np.int64)
        near = np.sort(near[np.argsort(mag[near], kind="stable")][:REGION_STARS])
        if len(near) >= 4:
            out.append(np.array(list(combinations(near.tolist(), 4)), np.int64))
    return np.concatenate(out)


#: A field's catalog patterns serve cameras whose minor half-field is within this fraction of it.
PATTERN_FIELD_REUSE = 0.02


def pattern_field(camera: CameraModel) -> int:
    """The key (minor half-field, mrad) of the catalog patterns that serve ``camera``: the centre of
    its bin on a fixed logarithmic grid whose bins span :data:`PATTERN_FIELD_REUSE` either side of
    their centres. A function of the camera alone, never of the fields cached before: the same
    camera gets the same patterns, and so the same answer, whatever was solved before it in the
    process (a focal length fitted to one frame moves the field by ~0.1 %: the same bin)."""
    step = math.log((1.0 + PATTERN_FIELD_REUSE) / (1.0 - PATTERN_FIELD_REUSE))
    k = round(math.log(camera.fov_half_angle_minor * 1000.0) / step)
    return max(1, int(round(math.exp(k * step))))


def catalog_patterns(catalog: OnboardCatalog, camera: CameraModel) -> PatternIndex:
    """The catalog's own :class:`PatternIndex` for the camera's field (module constants): what a
    solve given no index of its own matches against (the device's, and its twin's), cached on the
    catalog object per field bin (:func:`pattern_field`: every camera within
    :data:`PATTERN_FIELD_REUSE` of a bin's centre; another field's patterns take seconds to build).
    :func:`pattern_index` builds them; a caller that built them elsewhere (another process: the
    device after a catalog commit) installs them with :func:`set_catalog_patterns`."""
    mrad = pattern_field(camera)
    cache = catalog.__dict__.setdefault("_pattern_cache", {})
    if mrad not in cache:
        cache[mrad] = pattern_index(catalog.vec, catalog.mag, catalog.n_pattern_stars, mrad)
    return cache[mrad]


def unique_rows(groups: np.ndarray) -> np.ndarray:
    """``np.unique(groups, axis=0)`` of 4-star groups: each row packed into one 64-bit number (16
    bits a star, most significant first: the same order) when the star numbers allow, ~5x faster."""
    if len(groups) == 0 or groups.max() >= 1 << 16:
        return np.unique(groups, axis=0)
    g = groups.astype(np.uint64)
    code = np.unique(g[:, 0] << 48 | g[:, 1] << 32 | g[:, 2] << 16 | g[:, 3])
    return np.column_stack([code >> 48, code >> 32 & 0xFFFF, code >> 16 & 0xFFFF, code & 0xFFFF]).astype(np.int64)


def set_catalog_patterns(catalog: OnboardCatalog, mrad: int, index) -> None:
    """Install a :func:`pattern_index` of ``catalog`` for the field ``mrad`` (:func:`pattern_field`)."""
    catalog.__dict__.setdefault("_pattern_cache", {})[mrad] = index


#: Pattern indexes :func:`cached_pattern_index` keeps in its folder (the most recently used).
KEPT_INDEXES = 8


def cached_pattern_index(folder, vec: np.ndarray, mag: np.ndarray, n_pattern_stars: int, mrad: int):
    """:func:`pattern_index`, kept in ``folder``: a file per catalog and field, named by a hash of
    the stars, the field and the code that builds it (this module and ``pattern_index``), loaded
    far faster than it is built (docs/e2e.md); the :data:`KEPT_INDEXES` most
    recently used are kept. A damaged file is built again; a folder that cannot be written only
    costs the keeping."""
    digest = hashlib.sha256(np.ascontiguousarray(vec, float).tobytes())
    digest.update(np.ascontiguousarray(mag, float).tobytes())
    digest.update(f"{n_pattern_stars} {mrad}".encode())
    for source in (Path(__file__), Path(__file__).with_name("pattern_index.py")):  # the code that builds it
        digest.update(source.read_bytes())
    path = Path(folder) / f"{digest.hexdigest()[:24]}.pickle"
    try:
        index = pickle.loads(path.read_bytes())  # this process' own cache folder
        os.utime(path)  # recently used
        return index
    except FileNotFoundError:
        pass
    except Exception:  # noqa: BLE001 - a damaged file: built again
        path.unlink(missing_ok=True)
    index = pattern_index(vec, mag, n_pattern_stars, mrad)
    part = path.with_suffix(f".{os.getpid()}.part")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        part.write_bytes(pickle.dumps(index, protocol=5))
        os.replace(part, path)  # whole or not at all
        kept = sorted(path.parent.glob("*.pickle"), key=lambda p: p.stat().st_mtime)
        for old in kept[:-KEPT_INDEXES]:
            old.unlink(missing_ok=True)
    except OSError:
        part.unlink(missing_ok=True)
    return index


def pattern_index(vec: np.ndarray, mag: np.ndarray, n_pattern_stars: int, mrad: int) -> PatternIndex:
    """The catalog patterns of the stars ``vec``, ``mag`` (the first ``n_pattern_stars`` are the
    pattern stars) for the minor half-field ``mrad`` (mrad). A function of arrays alone, so that
    another process can build it."""
    return PatternIndex.from_patterns(vec[:n_pattern_stars], *field_patterns(vec, mag, n_pattern_stars, mrad / 1000.0))


def field_patterns(
    vec: np.ndarray, mag: np.ndarray, n_pattern_stars: int, field: float, neighbours: int = CATALOG_NEIGHBOURS
):
    """(groups, keys, largest edge) of the patterns (module constants; ``neighbours`` for
    :data:`CATALOG_NEIGHBOURS`) of the first ``n_pattern_stars`` stars for the minor half-field
    ``field`` (rad), each 4-set once."""
    tree = cKDTree(vec[:n_pattern_stars])  # the catalog's own pattern-star tree (OnboardCatalog._tree)
    rank = np.argsort(np.argsort(mag[:n_pattern_stars], kind="stable"), kind="stable")
    parts = [_region_groups(tree, mag[:n_pattern_stars], field)]
    for factor in PATTERN_RADIUS_FACTORS:
        near = tree.query_ball_point(vec[:n_pattern_stars], chord_of_angle(factor * field))
        brighter = np.array([np.count_nonzero(rank[n] < rank[i]) for i, n in enumerate(near)])
        parts.append(_groups(near, rank, np.flatnonzero(brighter < PATTERN_STARS_PER_CAP), neighbours))
    groups = unique_rows(np.sort(np.concatenate(parts), axis=1))  # a 4-set found several ways once
    keys, top = pattern_keys(vec, groups)
    ok = np.isfinite(keys).all(axis=1) & (top > 0)
    return groups[ok], keys[ok], top[ok]


@dataclass
class PatternMatches:
    """Key matches of a frame's patterns, best key distance first: frame 4-sets ``groups`` (rows of
    the frame's brightest detections), focal scale (frame's largest edge over the catalog's), key
    distance and the matched catalog patterns' star directions; attitudes are worked out only for
    the matches :meth:`hypotheses` returns (each costs an assignment and an SVD)."""

    f_nominal: float
    plane: np.ndarray  # (n, 2) ideal normalised coordinates through the nominal focal length
    groups: np.ndarray
    scale: np.ndarray
    distance: np.ndarray
    catalog_vec: np.ndarray  # (M, 4, 3) each match's catalog pattern star directions
    _worked: dict = field(default_factory=dict, init=False, repr=False)  # match -> Hypothesis or None

    @property
    def best_f(self) -> float:
        """Focal length (px) of the best key match; NaN when there is none."""
        return float(self.f_nominal * self.scale[0]) if len(self.scale) else float("nan")

    def hypothesis(self, m: int) -> Hypothesis | None:
        """Match ``m``'s hypothesis (None when no assignment of its stars fits), worked out once."""
        # directions through the hypothesised focal length (the ideal plane scaled by 1 / scale;
        # the distortion's own change with f is far below a pattern's tolerance): with the
        # nominal one, a pattern off the boresight would tilt the attitude by the scale error
        # times its field angle
        if m not in self._worked:  # worked out once: the search asks again for those it has seen
            b = np.column_stack([self.plane[self.groups[m]] / self.scale[m], np.ones(4)])
            a = _assign(b / np.linalg.norm(b, axis=1, keepdims=True), self.catalog_vec[m])
            f = self.f_nominal * float(self.scale[m])
            self._worked[m] = None if a is None else Hypothesis(f, a, float(self.distance[m]))
        return self._worked[m]

    def hypotheses(self, most: int = 64):
        """Up to ``most`` hypotheses, best key first (a generator: attitudes as they are asked for)."""
        given = 0
        for m in range(len(self.scale)):
            if given == most:
                return
            hyp = self.hypothesis(m)
            if hyp is not None:
                given += 1
                yield hyp


def pattern_matches(
    x: np.ndarray,
    y: np.ndarray,
    camera: CameraModel,
    index: PatternIndex,
    n_bright: int,
    tolerance: float,
    focal_range: float,
    first: int = 0,
) -> PatternMatches:
    """Pattern matches of the ``n_bright`` brightest detections (rows of ``x, y``, brightest first)
    against the patterns of ``index`` with key distance below ``tolerance`` and focal length within
    ``focal_range`` (relative) of the nominal camera's, best key distance first. ``first``: only patterns holding a detection
    at or beyond that rank (the caller has tried those of the ``first`` brightest already)."""
    return pattern_matches_many(x, y, [(camera, focal_range)], index, n_bright, tolerance, first)[0]


def pattern_matches_many(
    x: np.ndarray,
    y: np.ndarray,
    cameras: list[tuple[CameraModel, float]],
    index: PatternIndex,
    n_bright: int,
    tolerance: float,
    first: int = 0,
) -> list[PatternMatches]:
    """:func:`pattern_matches` for each (camera, focal range) of ``cameras`` against one index.
    Cameras whose keys of the frame differ by at most :data:`SHARED_LOOKUP` share one lookup
    (with the tolerance widened by that much, each camera's own keys then held to the
    tolerance): on a narrow field a focal-length change bends the keys by far less."""
    n = min(len(x), n_bright)
    groups = np.array(list(combinations(range(n), 4)), np.int64).reshape(-1, 4)
    groups = groups[groups[:, 3] >= first]  # combinations are sorted: the last member is the faintest
    per = []
    for camera, focal_range in cameras:
        v = camera.pixel_to_vector(x[:n], y[:n])
        keys, top = pattern_keys(v, groups)
        wide = top <= 2.0 * max(PATTERN_RADIUS_FACTORS) * camera.fov_half_angle_minor * (1 + focal_range)
        per.append((v, keys, top, wide))
    found: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros(0, np.int64), np.zeros(0, np.int64))] * len(cameras)
    b = 0
    while b < len(cameras) and len(groups):
        leader = per[b][1]
        share = [b]
        while b + len(share) < len(cameras):
            apart = np.max(np.abs(per[b + len(share)][1] - leader), initial=0.0, where=np.isfinite(leader))
            if not apart <= SHARED_LOOKUP:
                break
            share.append(b + len(share))
        wanted = np.flatnonzero(np.any([per[c][3] for c in share], axis=0) & np.isfinite(leader).all(axis=1))
        qi, ci = index.within(leader[wanted], tolerance + SHARED_LOOKUP if len(share) > 1 else tolerance)
        qi = wanted[qi]
        for c in share:
            keys, wide = per[c][1], per[c][3]
            mine = wide[qi] & (np.max(np.abs(keys[qi] - index.keys[ci]), axis=1) <= tolerance)
            found[c] = (qi[mine], ci[mine])
        b += len(share)
    out = []
    for (camera, focal_range), (v, keys, top, _), (gi, cb) in zip(cameras, per, found):
        scale = top[gi] / index.top[cb]
        ok = np.abs(scale - 1.0) <= focal_range
        gi, cb, scale = gi[ok], cb[ok], scale[ok]
        dist = np.max(np.abs(keys[gi] - index.keys[cb]), axis=1)
        order = np.argsort(dist, kind="stable")
        gi, cb = gi[order], cb[order]
        plane = v[:, :2] / v[:, 2:] if len(v) else np.zeros((0, 2))
        out.append(PatternMatches(camera.f, plane, groups[gi], scale[order], dist[order], index.vec[index.groups[cb]]))
    return out


#: How far apart (largest key difference) two cameras' keys of a frame may be to share a lookup.
SHARED_LOOKUP = 0.002


class BrightFirstMatches:
    """The pattern matches of the ``n_bright`` brightest detections, worked out rank by rank as they
    are asked for: the pattern of the 4 brightest, then those whose faintest member is the 5th,
    the 6th, ... (each rank a :func:`pattern_matches` with ``first``, best key first within it), the
    plate solvers' brightness order. A frame whose brightest stars match is not charged the key
    queries of its fainter combinations (70 for the 8 brightest; each query misses the processor's
    cache on the catalog's ~8e5 keys). ``best_f``: the best key match's focal length in
    the first rank with a match (NaN for none), worked out on construction."""

    def __init__(self, x, y, camera: CameraModel, index: PatternIndex, n_bright: int, tolerance, focal_range):
        n = min(len(x), n_bright)
        self._ranks = (
            pattern_matches(x, y, camera, index, k, tolerance, focal_range, first=k - 1) for k in range(4, n + 1)
        )
        self._done: list[PatternMatches] = []
        k = 0  # the ranks up to the first with a match, now: they give best_f
        while (rank := self._rank(k)) is not None and not len(rank.scale):
            k += 1
        self.best_f = float("nan") if rank is None else rank.best_f  # px, the first match's focal length

    def _rank(self, k: int) -> PatternMatches | None:
        while len(self._done) <= k:
            nxt = next(self._ranks, None)
            if nxt is None:
                return None
            self._done.append(nxt)
        return self._done[k]

    def hypotheses(self, most: int = 64):
        """Up to ``most`` hypotheses, rank by rank (a generator)."""
        given, k = 0, 0
        while given < most and (rank := self._rank(k)) is not None:
            for hyp in rank.hypotheses(most - given):
                given += 1
                yield hyp
            k += 1


def _assign(b: np.ndarray, r: np.ndarray):
    """Attitude from the best of the 24 assignments of frame directions ``b`` (through the
    hypothesised focal length) to catalog directions ``r`` (edges compared after a common scale),
    or None when even the best leaves an edge mismatch above 2 % of the largest edge."""
    found, a = _assign_kernel(
        np.ascontiguousarray(b, float), np.ascontiguousarray(r, float), _PAIRS_IJ, _PERM_EDGES, _PERMS
    )
    return a if found else None


@njit(cache=True, nogil=True)
def _edges(v, pairs):  # pragma: no cover - compiled
    """The six angles (rad) between four unit vectors (``angle_between``'s arithmetic)."""
    out = np.empty(len(pairs))
    for e in range(len(pairs)):
        i, j = pairs[e, 0], pairs[e, 1]
        d = np.sqrt((v[i, 0] - v[j, 0]) ** 2 + (v[i, 1] - v[j, 1]) ** 2 + (v[i, 2] - v[j, 2]) ** 2)
        out[e] = 2.0 * np.arcsin(min(max(d / 2.0, 0.0), 1.0))
    return out


@njit(cache=True, nogil=True)
def _assign_kernel(b, r, pairs, perm_edges, perms):  # pragma: no cover - compiled
    """:func:`_assign`'s numbers: (found, attitude)."""
    eb, er = _edges(b, pairs), _edges(r, pairs)
    best, best_mismatch = 0, np.inf
    for p in range(len(perms)):
        total = 0.0
        for e in range(6):
            total += er[perm_edges[p, e]]
        scale = eb.sum() / total
        sq = 0.0
        for e in range(6):
            sq += (er[perm_edges[p, e]] * scale - eb[e]) ** 2
        mismatch = np.sqrt(sq / 6.0)
        if mismatch < best_mismatch:
            best, best_mismatch = p, mismatch
    if not best_mismatch <= 0.02 * eb.max():
        return False, np.eye(3)
    return True, svd_attitude_kernel(b, r[perms[best]], np.ones(4))


def refine(
    x: np.ndarray,
    y: np.ndarray,
    camera: CameraModel,
    hyp: Hypothesis,
    catalog: StarTable,
    radii_px: tuple[float, ...] = (30.0, 10.0, 4.0, 2.5),
    min_stars: int = 4,
    k1_min_stars: int = 6,
):
    """Predict-match-fit from a pattern hypothesis: the camera with the hypothesis' focal length,
    then for each radius in ``radii_px`` match every detection to the nearest predicted catalog
    star within it (one detection per star) and fit f, k1 (with enough stars) and the attitude
    (not again when a radius matches the same stars as the last fit).
    Returns (camera, detection rows, catalog indices, the last fit) or None with fewer than
    ``min_stars``."""
    near = catalog.stars_within(hyp.a[2], camera.fov_half_angle_diagonal * 1.2)
    c = camera
    try:
        found, det, cat, fitted = _refine(
            np.asarray(x, float),
            np.asarray(y, float),
            near,
            catalog.vec[near],
            hyp.f,
            c.cx,
            c.cy,
            np.array([c.k1, c.k2, c.k3, c.p1, c.p2]),
            c.width,
            c.height,
            np.ascontiguousarray(hyp.a, float),
            np.asarray(radii_px, float),
            min_stars,
            k1_min_stars,
        )
    except np.linalg.LinAlgError:  # a parameter no star constrains
        return None
    res = fit_result(camera, fitted) if found else None
    return None if res is None else (res.camera, det, cat, res)


@njit(cache=True, nogil=True)
def _refine(
    x, y, near, near_vec, f, cx, cy, dist, width, height, a, radii, min_stars, k1_min_stars
):  # pragma: no cover - compiled
    """:func:`refine`'s numbers: (found, detection rows, catalog indices, the last fit's
    ``frame_fit.fit_frame_kernel`` numbers)."""
    dist = dist.copy()
    det, cat = np.empty(0, np.int64), np.empty(0, np.int64)
    fitted = (False, f, dist[0], a, np.empty(0), np.empty(0), np.empty((3, 3)), 0.0, 0)
    moved = True  # the camera or attitude changed since the last prediction
    for radius in radii:
        if moved:  # predict, and each detection's nearest predicted star and its distance
            px, py = vector_to_pixel_kernel(near_vec @ a.T, f, cx, cy, dist[0], dist[1], dist[2], dist[3], dist[4])
            inside = np.isfinite(px) & (px >= -0.5) & (px < width - 0.5) & (py >= -0.5) & (py < height - 0.5)
            if inside.sum() < min_stars:
                return False, det, cat, fitted
            ci, vi = near[inside], near_vec[inside]
            j, nearest = _nearest(x, y, px[inside], py[inside])
            moved = False
        rows = np.flatnonzero(nearest < radius)
        order = np.argsort(j[rows], kind="mergesort")  # the brightest detection per star, in star order
        first = np.ones(len(rows), np.bool_)
        for k in range(1, len(rows)):
            first[k] = j[rows[order[k]]] != j[rows[order[k - 1]]]
        rows = rows[order[first]]
        if len(rows) < min_stars:
            return False, det, cat, fitted
        if fitted[0] and len(rows) == len(det) and np.all(rows == det) and np.all(ci[j[rows]] == cat):
            continue  # the same stars as the last fit: fitting them again gives the same camera
        det, cat = rows, ci[j[rows]]
        fitted = fit_frame_kernel(x[det], y[det], vi[j[rows]], f, cx, cy, dist, k1_min_stars)
        if not fitted[0]:
            return False, det, cat, fitted
        f, dist[0], a, moved = fitted[1], fitted[2], fitted[3], True
    return fitted[0], det, cat, fitted


@njit(cache=True, nogil=True)
def _nearest(x, y, px, py):  # pragma: no cover - compiled
    """For each detection ``(x, y)`` (px), the nearest predicted star of ``(px, py)`` (the first of
    equals) and its distance (px; NaN for a detection without a position)."""
    j, d = np.zeros(len(x), np.int64), np.full(len(x), np.nan)
    for i in range(len(x)):
        if not (np.isfinite(x[i]) and np.isfinite(y[i])):
            continue
        for k in range(len(px)):
            dk = np.hypot(x[i] - px[k], y[i] - py[k])
            if not dk >= d[i]:
                j[i], d[i] = k, dk
    return j, d


def warm_up() -> None:
    """Compile (or load from numba's disk cache) the kernels of a pattern hypothesis, of the key
    lookup and of :func:`refine`."""
    pattern_index_warm_up()
    cam = CameraModel(64, 48, 100.0, 31.5, 23.5)
    x, y = np.array([5.0, 60.0, 10.0, 50.0, 30.0, 20.0]), np.array([4.0, 6.0, 40.0, 44.0, 20.0, 30.0])
    v = cam.pixel_to_vector(x, y)
    a = _assign(v[:4], v[:4])
    near, dist = np.arange(6), np.zeros(5)
    _refine(x, y, near, v, cam.f, cam.cx, cam.cy, dist, cam.width, cam.height, a, np.array([3.0, 1.0]), 4, 6)
