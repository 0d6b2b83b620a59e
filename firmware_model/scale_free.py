"""Scale-free first match for uncalibrated optics: 4-star patterns whose edge ratios do not
depend on the focal length, as plate solvers do it (tetra3's patterns, astrometry.net's quads).

A pattern is a star and three of its brightest neighbours within ``radius``; its key is
the six pairwise angles sorted and divided by the largest (five numbers in (0, 1]). A focal-length
error scales every edge alike and leaves the key unchanged; radial distortion of a few pixels
changes it by well under a per cent for patterns of a few hundred pixels. Catalog patterns are
built once per (catalog, radius) and kept in a KD-tree (L-infinity ball queries).

``hypotheses`` matches the frame's patterns (from its brightest detections, directions taken
through the nominal camera) and turns each key match into a focal length (ratio of the
catalog's largest edge to the frame's) and an attitude (the four stars, best of the 24
assignments). ``refine`` then predicts every catalog star in the field, matches detections
within a shrinking radius and fits focal length (and k1) with the attitude
(``firmware_model.camera_fit``). The caller identifies the frame again from scratch with the
fitted camera: a pattern match is only a seed.

Units: radians for angles, pixels for image positions (docs/CONVENTIONS.md).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import combinations, permutations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from firmware_model.camera import CameraModel
from firmware_model.camera_fit import StarObservations, fit_frame
from firmware_model.onboard_catalog import OnboardCatalog, angle_between

#: Neighbours per pattern centre (the brightest within the radius), three of which join it: in the
#: catalog, and among the frame's detections.
CATALOG_NEIGHBOURS = 10
FRAME_NEIGHBOURS = 8
#: Catalog stars that centre patterns: those with fewer brighter stars than this within the pattern
#: radius (a frame's brightest detections are among its region's brightest stars); bounds the
#: patterns per area of sky, not per star.
PATTERN_STARS_PER_CAP = 12
_PAIRS = list(combinations(range(4), 2))
_PERMS = np.array(list(permutations(range(4))))


@dataclass
class Hypothesis:
    """A pattern match: focal length (px), attitude ``a`` (v_sensor = a @ v_icrs) and the key
    distance (largest difference of the edge ratios)."""

    f: float
    a: np.ndarray
    key_distance: float


def _keys(vectors: np.ndarray, groups: np.ndarray):
    """Sorted normalised edge ratios (G, 5) and the largest edge (G,) of 4-star groups (G, 4)."""
    v = vectors[groups]  # (G, 4, 3)
    edges = np.stack([angle_between(v[:, i], v[:, j]) for i, j in _PAIRS], axis=1)
    edges.sort(axis=1)
    top = edges[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return edges[:, :-1] / top[:, None], top


def _groups(vectors: np.ndarray, brightness_rank: np.ndarray, radius: float, centres: np.ndarray,
            neighbours: int) -> np.ndarray:
    """4-star groups: each centre with three of its ``neighbours`` brightest neighbours within ``radius``."""
    tree = cKDTree(vectors)
    chord = 2.0 * np.sin(radius / 2.0)
    out = []
    for c, near in zip(centres, tree.query_ball_point(vectors[centres], chord)):
        near = np.array([j for j in near if j != c], dtype=np.int64)
        if len(near) < 3:
            continue
        near = near[np.argsort(brightness_rank[near])][:neighbours]
        out.extend((c, *trio) for trio in combinations(near.tolist(), 3))
    return np.array(out, dtype=np.int64).reshape(-1, 4)


def catalog_patterns(catalog: OnboardCatalog, radius: float):
    """(groups, keys, largest edge, KD-tree of keys) of the catalog's patterns of ``radius`` (rad),
    cached on the catalog object per radius (to 1 mrad)."""
    cache = catalog.__dict__.setdefault("_pattern_cache", {})
    mrad = int(round(radius * 1000.0))
    if mrad not in cache:
        rank = np.argsort(np.argsort(catalog.mag, kind="stable"), kind="stable")
        tree = cKDTree(catalog.vec)
        near = tree.query_ball_point(catalog.vec, 2.0 * np.sin(mrad / 2000.0))
        brighter = np.array([np.count_nonzero(rank[n] < rank[i]) for i, n in enumerate(near)])
        centres = np.flatnonzero(brighter < PATTERN_STARS_PER_CAP)
        groups = _groups(catalog.vec, rank, mrad / 1000.0, centres, CATALOG_NEIGHBOURS)
        groups = np.unique(np.sort(groups, axis=1), axis=0)  # a 4-set found from several of its stars once
        keys, top = _keys(catalog.vec, groups)
        ok = np.isfinite(keys).all(axis=1) & (top > 0)
        cache[mrad] = (groups[ok], keys[ok], top[ok], cKDTree(keys[ok]))
    return cache[mrad]


def pattern_radius(camera: CameraModel) -> float:
    """Pattern radius for a camera: three quarters of the field of view across the minor axis (rad),
    so that a sparse field whose catalog stars sit far apart still forms patterns."""
    return 1.5 * camera.fov_half_angle_minor


def hypotheses(x: np.ndarray, y: np.ndarray, camera: CameraModel, catalog: OnboardCatalog, n_bright: int = 12,
               tolerance: float = 0.015, focal_range: float = 0.1, max_hypotheses: int = 64) -> list[Hypothesis]:
    """Pattern matches of the ``n_bright`` brightest detections (rows of ``x, y``, brightest first)
    with key distance below ``tolerance`` and focal length within ``focal_range`` (relative) of
    the nominal camera's, best key distance first."""
    n = min(len(x), n_bright)
    if n < 4:
        return []
    radius = pattern_radius(camera)
    groups_c, keys_c, top_c, tree = catalog_patterns(catalog, radius)
    v = camera.pixel_to_vector(x[:n], y[:n])
    groups = _groups(v, np.arange(n), radius * (1 + focal_range), np.arange(n), FRAME_NEIGHBOURS)
    if len(groups) == 0:
        return []
    keys, top = _keys(v, groups)
    found = tree.query_ball_point(keys, tolerance, p=np.inf)
    gi = np.repeat(np.arange(len(groups)), [len(f) for f in found])
    ci = np.fromiter((k for f in found for k in f), dtype=np.int64, count=len(gi))
    scale = top[gi] / top_c[ci]
    ok = np.abs(scale - 1.0) <= focal_range
    gi, ci, scale = gi[ok], ci[ok], scale[ok]
    dist = np.max(np.abs(keys[gi] - keys_c[ci]), axis=1)
    out = []
    for m in np.argsort(dist, kind="stable"):  # best key first; attitudes only for those returned
        g = groups[gi[m]]
        # directions through the hypothesised focal length: with the nominal one, a pattern off
        # the boresight would tilt the attitude by the scale error times its field angle
        b = replace(camera, f=camera.f * scale[m]).pixel_to_vector(x[g], y[g])
        a = _assign(b, catalog.vec[groups_c[ci[m]]])
        if a is not None:
            out.append(Hypothesis(camera.f * scale[m], a, float(dist[m])))
            if len(out) == max_hypotheses:
                break
    return out


def _assign(b: np.ndarray, r: np.ndarray):
    """Attitude from the best of the 24 assignments of frame directions ``b`` (through the
    hypothesised focal length) to catalog directions ``r`` (edges compared after a common scale),
    or None when even the best leaves an edge mismatch above 2 % of the largest edge."""
    eb = np.stack([angle_between(b[i], b[j]) for i, j in _PAIRS])
    rp = r[_PERMS]  # (24, 4, 3)
    er = np.stack([angle_between(rp[:, i], rp[:, j]) for i, j in _PAIRS], axis=1)
    scale = eb.sum() / er.sum(axis=1)
    mismatch = np.sqrt(np.mean((er * scale[:, None] - eb) ** 2, axis=1))
    best = int(np.argmin(mismatch))
    if mismatch[best] > 0.02 * eb.max():
        return None
    rot, _ = Rotation.align_vectors(b, rp[best])
    return rot.as_matrix()


def refine(x: np.ndarray, y: np.ndarray, camera: CameraModel, hyp: Hypothesis, catalog: OnboardCatalog,
           radii_px=(30.0, 10.0, 4.0, 2.5), min_stars: int = 4, k1_min_stars: int = 6):
    """Predict-match-fit from a pattern hypothesis: the camera with the hypothesis' focal length,
    then for each radius in ``radii_px`` match every detection to the nearest predicted catalog
    star within it (one detection per star) and fit f, k1 (with enough stars) and the attitude.
    Returns (camera, detection rows, catalog indices, RMS residual of the last fit in px) or None
    with fewer than ``min_stars``."""
    cam, a = replace(camera, f=hyp.f), hyp.a
    near = catalog.stars_within(a[2], camera.fov_half_angle_diagonal * 1.2)
    det = cat = res = None
    for radius in radii_px:
        px, py = cam.vector_to_pixel(catalog.vec[near] @ a.T)
        inside = np.isfinite(px) & cam.in_frame(px, py)
        if inside.sum() < min_stars:
            return None
        cx, cy, ci = px[inside], py[inside], near[inside]
        d = np.hypot(x[:, None] - cx[None, :], y[:, None] - cy[None, :])
        j = np.argmin(d, axis=1)
        ok = d[np.arange(len(x)), j] < radius
        rows = np.flatnonzero(ok)
        rows = rows[np.unique(j[rows], return_index=True)[1]]  # brightest detection per star
        if len(rows) < min_stars:
            return None
        det, cat = rows, ci[j[rows]]
        res = fit_frame(StarObservations(x[det], y[det], catalog.vec[cat]), cam, k1_min_stars)
        if res is None:
            return None
        cam, a = res.camera, res.attitudes[0]
    return cam, det, cat, res.residual_rms_px
