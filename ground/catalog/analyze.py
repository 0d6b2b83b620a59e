"""Catalog ambiguity and sky availability (Enright & McVittie sections 3.2 and 5.1, table 1).

* Ambiguous pairs: catalog pairs p, q with Mahalanobis distance (eq. 4, the smaller of the two
  star orderings) below Delta* of eq. 7. The search walks the angle-sorted pair table by offset:
  for offset k every pair still in play is compared with the pair k rows later in one numpy
  operation; a pair leaves play once that neighbour is farther than ``Delta* sigma_phi``. The work
  is the number of neighbour couples within the window (not O(P^2)), and the Python loop runs over
  offsets only. Unknown colour ratios (NaN) count as equal
  to anything (conservative).
* Views: N boresights on the Saff & Kuijlaars (1997) generalized spiral; a view sees the stars
  closer than theta_FOV (circular field of the minor half-axis, as in the paper). Bad view: fewer
  than two stars. Unresolvable view: two or more stars but no unambiguous catalog pair among them.
  Pair-in-view counts use a sparse view x star incidence matrix, in chunks of pairs.
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree
from tqdm import tqdm

from firmware_model.catalog.onboard import OnboardCatalog, chord_of_angle
from firmware_model.reference_frames import vec_to_radec
from ground.atomic_write import save_figure

PAIR_CHUNK = 4096


def ambiguous_pairs(
    cat: OnboardCatalog,
    sigma_phi: float,
    delta_star: float,
    sigma_rg: float | None = None,
    sigma_bg: float | None = None,
    progress: bool = False,
) -> np.ndarray:
    """Boolean per pair: some other catalog pair lies closer than ``delta_star`` (eq. 4).

    With ``sigma_rg``/``sigma_bg`` None the comparison is monochrome (angle only).
    """
    phi = np.asarray(cat.pair_phi, dtype=float)
    n = len(phi)
    amb = np.zeros(n, dtype=bool)
    window = delta_star * sigma_phi
    if sigma_rg is None or sigma_bg is None:
        # angle only: d < Delta* iff |d phi| < window, so the nearest neighbours decide
        close = np.diff(phi) < window
        amb[:-1] |= close
        amb[1:] |= close
        return amb
    rg = np.asarray(cat.rg, dtype=float) / sigma_rg
    bg = np.asarray(cat.bg, dtype=float) / sigma_bg
    pi, pj = np.asarray(cat.pair_i, dtype=np.int64), np.asarray(cat.pair_j, dtype=np.int64)
    limit2 = delta_star**2
    alive = np.arange(n - 1)  # pairs that may still have a neighbour k rows later within the window
    k = 0
    with tqdm(desc="ambiguity search", unit=" offsets", disable=not progress) as bar:
        while len(alive):
            k += 1
            alive = alive[alive + k < n]
            alive = alive[phi[alive + k] - phi[alive] < window]  # phi sorted: once out, out for larger k
            bar.update(1)
            p = alive[~(amb[alive] & amb[alive + k])]  # couples already both ambiguous decide nothing
            q = p + k
            d2 = ((phi[q] - phi[p]) / sigma_phi) ** 2
            d2 += np.minimum(
                _colour_d2(rg, bg, pi[p], pj[p], pi[q], pj[q]), _colour_d2(rg, bg, pi[p], pj[p], pj[q], pi[q])
            )
            hit = d2 < limit2
            amb[p[hit]] = True
            amb[q[hit]] = True
    return amb


def _colour_d2(rg, bg, a, b, c, d) -> np.ndarray:
    """Colour part of eq. 4 for star a~c and b~d (ratios pre-divided by sigma); NaN counts as 0."""
    terms = (rg[a] - rg[c]) ** 2 + (rg[b] - rg[d]) ** 2 + (bg[a] - bg[c]) ** 2 + (bg[b] - bg[d]) ** 2
    return np.nan_to_num(terms, nan=0.0) if np.isnan(terms).any() else terms


def spiral_points(n: int) -> np.ndarray:
    """Saff & Kuijlaars generalized spiral: ``n`` nearly uniform unit vectors, shape (n, 3)."""
    if n < 2:
        raise ValueError(f"need at least 2 spiral points, got {n}")
    k = np.arange(n)
    h = -1.0 + 2.0 * k / (n - 1)
    theta = np.arccos(h)
    step = np.zeros(n)
    inner = slice(1, n - 1)
    step[inner] = 3.6 / math.sqrt(n) / np.sqrt(1.0 - h[inner] ** 2)
    lon = np.mod(np.cumsum(step), 2.0 * np.pi)
    lon[-1] = 0.0
    st = np.sin(theta)
    return np.column_stack([st * np.cos(lon), st * np.sin(lon), np.cos(theta)])


def _incidence(vec: np.ndarray, views: np.ndarray, radius: float) -> sparse.csc_matrix:
    """Boolean (views x stars) matrix: star within ``radius`` of the view boresight."""
    lists = cKDTree(views).query_ball_point(vec, chord_of_angle(radius) * (1 - 1e-12))
    cols = np.repeat(np.arange(len(vec)), [len(v) for v in lists])
    rows = np.concatenate([np.asarray(v, dtype=np.int64) for v in lists]) if len(cols) else np.empty(0, np.int64)
    return sparse.csc_matrix((np.ones(len(rows), dtype=np.int32), (rows, cols)), shape=(len(views), len(vec)))


def _pairs_in_view(m: sparse.csc_matrix, i: np.ndarray, j: np.ndarray, progress: bool, label: str) -> np.ndarray:
    """Per view, how many of the pairs (i, j) have both stars in view (chunked sparse products)."""
    counts = np.zeros(m.shape[0], dtype=np.int64)
    for start in tqdm(
        range(0, len(i), PAIR_CHUNK), desc=label, unit=" chunks", disable=not progress or len(i) <= PAIR_CHUNK
    ):
        a, b = i[start : start + PAIR_CHUNK], j[start : start + PAIR_CHUNK]
        counts += np.asarray(m[:, a].multiply(m[:, b]).sum(axis=1)).ravel()
    return counts


@dataclass
class ViewStats:
    n_views: int
    bad_views: int  # fewer than two stars
    unresolvable_views: int  # >= 2 stars, no unambiguous pair
    bad_mask: np.ndarray
    unresolvable_mask: np.ndarray


def view_availability(
    cat: OnboardCatalog, views: np.ndarray, theta_fov: float, ambiguous: np.ndarray, progress: bool = False
) -> ViewStats:
    """Bad and unresolvable views for boresights ``views`` (unit vectors) and a per-pair ambiguity mask."""
    if cat.phi_max < 2.0 * theta_fov * (1 - 1e-9):
        raise ValueError(
            f"phi_max = {math.degrees(cat.phi_max):.4f} deg < 2 theta_FOV: views would hold pairs missing from the catalog"
        )
    vec = np.asarray(cat.vec, dtype=float)
    m = _incidence(vec, views, theta_fov)
    n_in = np.asarray(m.sum(axis=1)).ravel()
    pi, pj = np.asarray(cat.pair_i, dtype=np.int64), np.asarray(cat.pair_j, dtype=np.int64)
    amb = np.asarray(ambiguous, dtype=bool)
    if amb.sum() <= (~amb).sum():
        close = cKDTree(vec).query_pairs(chord_of_angle(cat.phi_min) * (1 + 1e-12), output_type="ndarray")
        close_in = _pairs_in_view(m, close[:, 0], close[:, 1], progress, "close pairs in views") if len(close) else 0
        catalog_in = n_in * (n_in - 1) // 2 - close_in
        good_in = catalog_in - _pairs_in_view(m, pi[amb], pj[amb], progress, "ambiguous pairs in views")
    else:
        good_in = _pairs_in_view(m, pi[~amb], pj[~amb], progress, "unambiguous pairs in views")
    bad = n_in < 2
    unres = ~bad & (good_in == 0)
    return ViewStats(len(views), int(bad.sum()), int(unres.sum()), bad, unres)


@dataclass
class AnalysisResult:
    """One table-1 row (Enright & McVittie): design, pair counts, ambiguity and availability."""

    m_thresh: float
    theta_fov_deg: float
    sigma_pix: float
    sigma_rg: float
    sigma_bg: float
    delta_star: float
    sigma_phi_rad: float
    n_stars: int
    n_pairs: int
    n_views: int
    bad_views_pct: float
    ambiguous_pairs_pct: float
    unresolvable_views: int
    mono_ambiguous_pairs_pct: float
    mono_unresolvable_views: int
    source: str = ""

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2)


def analyze(cat: OnboardCatalog, design, n_views: int = 100_000, progress: bool = False, return_views: bool = False):
    """Enright & McVittie table-1 figures for ``cat`` built with ``design`` (a CatalogDesign)."""
    sp, dstar = design.sigma_phi, design.delta_star
    amb_c = ambiguous_pairs(cat, sp, dstar, design.sigma_rg, design.sigma_bg, progress=progress)
    amb_m = ambiguous_pairs(cat, sp, dstar, progress=progress)
    views = spiral_points(n_views)
    vc = view_availability(cat, views, design.theta_fov, amb_c, progress)
    vm = view_availability(cat, views, design.theta_fov, amb_m, progress)
    n = max(cat.n_pairs, 1)
    res = AnalysisResult(
        m_thresh=design.m_thresh,
        theta_fov_deg=design.theta_fov_deg,
        sigma_pix=design.sigma_pix,
        sigma_rg=design.sigma_rg,
        sigma_bg=design.sigma_bg,
        delta_star=dstar,
        sigma_phi_rad=sp,
        n_stars=cat.n_stars,
        n_pairs=cat.n_pairs,
        n_views=n_views,
        bad_views_pct=100.0 * vc.bad_views / n_views,
        ambiguous_pairs_pct=100.0 * amb_c.sum() / n,
        unresolvable_views=vc.unresolvable_views,
        mono_ambiguous_pairs_pct=100.0 * amb_m.sum() / n,
        mono_unresolvable_views=vm.unresolvable_views,
        source=str(cat.meta.get("source", "")),
    )
    return (res, views, vc, vm) if return_views else res


TABLE_HEADER = (
    f"{'M_thr':>5} {'thFOV':>5} {'s_pix':>5} {'s_col':>5} | {'pairs e3':>8} {'bad %':>6} {'amb %':>6} "
    f"{'unres':>5} | {'mono amb %':>10} {'mono unres':>10}"
)


def table_row(r: AnalysisResult) -> str:
    """One line in the layout of Enright & McVittie table 1 (colour columns, then monochrome)."""
    col = f"{r.sigma_rg:.3f}" if r.sigma_rg == r.sigma_bg else f"{r.sigma_rg:.2f}/{r.sigma_bg:.2f}"
    return (
        f"{r.m_thresh:5.2f} {r.theta_fov_deg:5.1f} {r.sigma_pix:5.3f} {col:>5} | {r.n_pairs / 1e3:8.1f} {r.bad_views_pct:6.2f} "
        f"{r.ambiguous_pairs_pct:6.2f} {r.unresolvable_views:5d} | {r.mono_ambiguous_pairs_pct:10.2f} {r.mono_unresolvable_views:10d}"
    )


def plot_views(path: str | Path, views: np.ndarray, colour: ViewStats, mono: ViewStats, title: str = "") -> None:
    """Mollweide sky map (RA increasing to the left) of bad and unresolvable views, PNG."""
    from ground.optional import pyplot

    plt = pyplot()

    ra, dec = vec_to_radec(views)
    lon = -np.angle(np.exp(1j * ra))  # RA in (-pi, pi], mirrored so east is left as on the sky
    fig = plt.figure(figsize=(10, 5.6))
    ax = fig.add_subplot(111, projection="mollweide")
    for mask, colour_name, label, size in (
        (mono.unresolvable_mask, "tab:orange", f"monochrome unresolvable ({mono.unresolvable_views})", 3),
        (colour.bad_mask, "tab:red", f"bad: < 2 stars ({colour.bad_views})", 2),
        (colour.unresolvable_mask, "black", f"colour unresolvable ({colour.unresolvable_views})", 6),
    ):
        if mask.any():
            ax.scatter(lon[mask], dec[mask], s=size, c=colour_name, label=label, linewidths=0)
    ax.set_xticks(np.radians([-150, -120, -90, -60, -30, 0, 30, 60, 90, 120, 150]))
    ax.set_xticklabels([f"{h}h" for h in (22, 20, 18, 16, 14, 12, 10, 8, 6, 4, 2)])
    ax.grid(True, alpha=0.4)
    ax.legend(loc="lower right", fontsize=8, markerscale=4)
    ax.set_title(title or f"Bad views over {colour.n_views} spiral boresights")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


# --- Checks of the paper's table 1 against its own definition ------------------------------------


def _recoloured(cat: OnboardCatalog, rg: np.ndarray, bg: np.ndarray) -> OnboardCatalog:
    """A shallow copy of ``cat`` with other colour ratios (same stars, same pairs)."""
    out = copy.copy(cat)
    out.rg, out.bg = np.asarray(rg, dtype=float), np.asarray(bg, dtype=float)
    return out


def template_floor(cat: OnboardCatalog, sigma_phi: float, delta_star: float) -> np.ndarray:
    """Per pair: ambiguous with perfectly measured colours (a neighbour within the angle window whose
    stars have exactly the pair's ratios). No detector response can lower it; it depends only on
    which stars share a colour."""
    return ambiguous_pairs(cat, sigma_phi, delta_star, 1e-12, 1e-12)


def even_template_floor(
    cat: OnboardCatalog, sigma_phi: float, delta_star: float, n_templates: int, seed: int = 0
) -> np.ndarray:
    """:func:`template_floor` with the stars spread as evenly as possible over ``n_templates``
    distinct colours (a random balanced assignment), the most favourable case for that many spectra."""
    rng = np.random.default_rng(seed)
    label = rng.permutation(cat.n_stars) % n_templates
    return template_floor(_recoloured(cat, label.astype(float), np.zeros(cat.n_stars)), sigma_phi, delta_star)


def synthetic_colour_ambiguity(
    cat: OnboardCatalog, sigma_phi: float, delta_star: float, spread_over_sigma: float, dims: int, seed: int = 0
) -> float:
    """Ambiguous pairs (%) when every star has its own random colour, colour noise sigma = 1.

    ``dims`` 2: rg and bg independent, each uniform over a range of width ``spread_over_sigma``.
    ``dims`` 1: one locus coordinate t uniform over that width, rg = bg = t. The result depends on the
    spread only through spread / sigma and (fixed uniforms, scaled) is non-increasing in it."""
    if dims not in (1, 2):
        raise ValueError(f"dims must be 1 or 2, got {dims}")
    z = np.random.default_rng(seed).random((2, cat.n_stars))
    rg = spread_over_sigma * z[0]
    bg = rg if dims == 1 else spread_over_sigma * z[1]
    return 100.0 * ambiguous_pairs(_recoloured(cat, rg, bg), sigma_phi, delta_star, 1.0, 1.0).mean()


def jittered_colour_ambiguity(
    cat: OnboardCatalog, sigma_phi: float, delta_star: float, sigma_colour: float, jitter: float, seed: int = 0
) -> float:
    """Ambiguous pairs (%) after adding N(0, jitter) to every star's rg and bg (the catalog's own colours)."""
    z = np.random.default_rng(seed).standard_normal((2, cat.n_stars))
    rg = np.asarray(cat.rg, dtype=float) + jitter * z[0]
    bg = np.asarray(cat.bg, dtype=float) + jitter * z[1]
    return 100.0 * ambiguous_pairs(_recoloured(cat, rg, bg), sigma_phi, delta_star, sigma_colour, sigma_colour).mean()


def solve_decreasing(f, target: float, lo: float, hi: float, iters: int = 30) -> float:
    """``x`` in [lo, hi] where the non-increasing ``f`` crosses ``target`` (bisection in log x); ``hi``
    when even f(hi) > target, ``lo`` when f(lo) <= target."""
    if f(hi) > target:
        return hi
    if f(lo) <= target:
        return lo
    for _ in range(iters):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if f(mid) > target else (lo, mid)
        if hi / lo < 1.001:
            break
    return math.sqrt(lo * hi)


@dataclass
class TwoStarViews:
    exactly_two: int  # views holding exactly two catalog stars
    ambiguous: int  # of them, views whose one pair is ambiguous or not in the catalog: unresolvable
    mask: np.ndarray  # per view: exactly two stars and unresolvable


def two_star_views(cat: OnboardCatalog, views: np.ndarray, theta_fov: float, ambiguous: np.ndarray) -> TwoStarViews:
    """Views with exactly two stars, and those of them that are unresolvable by the paper's definition
    (their only pair is ambiguous, or too close to be in the catalog): a lower bound on unresolvable views."""
    m = _incidence(np.asarray(cat.vec, dtype=float), views, theta_fov).tocsr()
    n_in = np.diff(m.indptr)
    two = np.flatnonzero(n_in == 2)
    stars = m.indices[m.indptr[two][:, None] + np.arange(2)]
    a, b = stars.min(axis=1).astype(np.int64), stars.max(axis=1).astype(np.int64)
    n = cat.n_stars
    key = np.minimum(cat.pair_i, cat.pair_j).astype(np.int64) * n + np.maximum(cat.pair_i, cat.pair_j)
    order = np.argsort(key)
    want = a * n + b
    pos = np.clip(np.searchsorted(key[order], want), 0, max(len(key) - 1, 0))
    found = (key[order][pos] == want) if len(key) else np.zeros(len(want), bool)
    amb = np.asarray(ambiguous, dtype=bool)[order][pos] if len(key) else np.zeros(len(want), bool)
    unres = ~found | amb
    mask = np.zeros(len(views), dtype=bool)
    mask[two[unres]] = True
    return TwoStarViews(int(len(two)), int(unres.sum()), mask)


@dataclass
class FieldNesting:
    small_pairs: int  # pairs of the smaller-field catalog
    contained: int  # of them, also in the wider-field catalog (same two stars)
    window_ratio: float  # wider / smaller angle window (Delta* sigma_phi)
    small_ambiguous: int  # ambiguous pairs of the smaller catalog
    still_ambiguous: int  # of them, contained and ambiguous in the wider catalog too
    big_pairs: int
    big_ambiguous: int
    added_pairs: int  # wider-catalog pairs not in the smaller one
    added_ambiguous: int


def field_nesting(
    small: OnboardCatalog,
    amb_small: np.ndarray,
    big: OnboardCatalog,
    amb_big: np.ndarray,
    window_small: float,
    window_big: float,
) -> FieldNesting:
    """How the pairs and ambiguity of a smaller-field catalog sit inside a wider-field one (stars
    matched by ``star_id``)."""

    def keys(c: OnboardCatalog) -> np.ndarray:
        sid = np.asarray(c.star_id, dtype=np.int64)
        a, b = sid[c.pair_i], sid[c.pair_j]
        return np.minimum(a, b) * (1 << 31) + np.maximum(a, b)

    ks, kb = keys(small), keys(big)
    in_big = np.isin(ks, kb)
    order = np.argsort(kb)
    pos = np.clip(np.searchsorted(kb[order], ks), 0, len(kb) - 1)
    amb_s, amb_b = np.asarray(amb_small, bool), np.asarray(amb_big, bool)
    still = amb_s & in_big & amb_b[order][pos]
    added = ~np.isin(kb, ks)
    return FieldNesting(
        small_pairs=len(ks),
        contained=int(in_big.sum()),
        window_ratio=window_big / window_small,
        small_ambiguous=int(amb_s.sum()),
        still_ambiguous=int(still.sum()),
        big_pairs=len(kb),
        big_ambiguous=int(amb_b.sum()),
        added_pairs=int(added.sum()),
        added_ambiguous=int((amb_b & added).sum()),
    )
