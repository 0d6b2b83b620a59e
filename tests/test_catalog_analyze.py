"""Ambiguity search and view availability against brute force; the spiral."""

import itertools

import numpy as np
import pytest

from firmware_model.catalog.onboard import OnboardCatalog, angle_between
from ground.catalog.analyze import (
    ambiguous_pairs,
    even_template_floor,
    field_nesting,
    solve_decreasing,
    spiral_points,
    synthetic_colour_ambiguity,
    template_floor,
    two_star_views,
    view_availability,
)


@pytest.fixture(scope="module")
def cat():
    rng = np.random.default_rng(3)
    n = 120
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v[:, 2] > 0.5]  # a cap, so the pair table is dense
    m = len(v)
    rg = rng.choice([0.8, 0.9, 1.0, 1.1], m) + rng.normal(0, 0.01, m)
    bg = rng.choice([0.7, 0.9], m) + rng.normal(0, 0.01, m)
    rg[0] = np.nan  # one star without colour
    return OnboardCatalog.build(np.arange(m), v, np.full(m, 4.0), rg, bg, phi_min=1e-3, phi_max=0.4, n_h=64)


def _brute_ambiguous(cat, sphi, dstar, srg=None, sbg=None):
    n = cat.n_pairs
    amb = np.zeros(n, bool)
    for p, q in itertools.combinations(range(n), 2):
        d2 = ((cat.pair_phi[p] - cat.pair_phi[q]) / sphi) ** 2
        if srg is not None:
            i, j, k, l = cat.pair_i[p], cat.pair_j[p], cat.pair_i[q], cat.pair_j[q]

            def c(a, b, c_, d):
                t = (
                    ((cat.rg[a] - cat.rg[c_]) / srg) ** 2
                    + ((cat.rg[b] - cat.rg[d]) / srg) ** 2
                    + ((cat.bg[a] - cat.bg[c_]) / sbg) ** 2
                    + ((cat.bg[b] - cat.bg[d]) / sbg) ** 2
                )
                return 0.0 if np.isnan(t) else t

            d2 += min(c(i, j, k, l), c(i, j, l, k))
        if d2 < dstar**2:
            amb[p] = amb[q] = True
    return amb


@pytest.mark.parametrize("sphi, colour", [(2e-4, True), (2e-4, False), (1e-3, True), (5e-5, False)])
def test_ambiguity_matches_brute_force(cat, sphi, colour):
    kw = {"sigma_rg": 0.02, "sigma_bg": 0.02} if colour else {}
    fast = ambiguous_pairs(cat, sphi, 4.65, **kw)
    slow = _brute_ambiguous(cat, sphi, 4.65, kw.get("sigma_rg"), kw.get("sigma_bg"))
    assert fast.any() and (~fast).any() or sphi == 5e-5
    np.testing.assert_array_equal(fast, slow)


def test_spiral_is_uniform():
    pts = spiral_points(2000)
    assert np.allclose(np.linalg.norm(pts, axis=1), 1.0)
    assert np.linalg.norm(pts.mean(axis=0)) < 0.01
    from scipy.spatial import cKDTree

    d, _ = cKDTree(pts).query(pts, k=2)
    spacing = np.sqrt(4 * np.pi / 2000)
    assert 0.8 * spacing < np.median(d[:, 1]) < 1.2 * spacing and d[:, 1].min() > 0.5 * spacing


def test_view_availability_matches_brute_force(cat):
    theta = 0.2
    amb = ambiguous_pairs(cat, 3e-4, 4.65, sigma_rg=0.02, sigma_bg=0.02)
    assert amb.any() and (~amb).any()
    views = spiral_points(600)
    lookup = {(int(i), int(j)): bool(a) for i, j, a in zip(cat.pair_i, cat.pair_j, amb)}
    bad, unres = np.zeros(len(views), bool), np.zeros(len(views), bool)
    for k, r in enumerate(views):
        inside = np.flatnonzero(angle_between(cat.vec, r) < theta)
        bad[k] = len(inside) < 2
        pairs = [(int(a), int(b)) for a, b in itertools.combinations(inside, 2)]
        usable = [not lookup[p] for p in pairs if p in lookup]
        unres[k] = not bad[k] and not any(usable)
    assert amb.sum() < (~amb).sum()  # branch: count ambiguous pairs per view
    stats = view_availability(cat, views, theta, amb)
    np.testing.assert_array_equal(stats.bad_mask, bad)
    np.testing.assert_array_equal(stats.unresolvable_mask, unres)
    assert bad.any() and (~bad).any() and unres.any()
    # branch: count unambiguous pairs per view
    mostly_amb = ambiguous_pairs(cat, 3e-3, 4.65)  # monochrome, wide: most pairs ambiguous
    assert mostly_amb.sum() > (~mostly_amb).sum()
    lookup = {(int(i), int(j)): bool(a) for i, j, a in zip(cat.pair_i, cat.pair_j, mostly_amb)}
    stats = view_availability(cat, views, theta, mostly_amb)
    for k in np.flatnonzero(~stats.bad_mask)[:200]:
        inside = np.flatnonzero(angle_between(cat.vec, views[k]) < theta)
        usable = any(not lookup.get((int(a), int(b)), True) for a, b in itertools.combinations(inside, 2))
        assert stats.unresolvable_mask[k] == (not usable)


def test_views_need_phi_max_of_twice_the_field(cat):
    with pytest.raises(ValueError, match="< 2 theta_FOV"):
        view_availability(cat, spiral_points(10), 0.3, np.zeros(cat.n_pairs, bool))


# --- issue 32: the checks of table 1 against its definition ---------------------------------------


def _templated(cat, labels, table):
    """``cat`` with every star the colour of its template under a 'detector' ``table`` (label -> rg, bg)."""
    rg = np.array([table[k][0] for k in labels])
    bg = np.array([table[k][1] for k in labels])
    return OnboardCatalog.build(cat.star_id, cat.vec, cat.mag, rg, bg, phi_min=cat.phi_min, phi_max=cat.phi_max, n_h=64)


def test_template_floor_is_positive_and_independent_of_the_detector(cat):
    labels = np.random.default_rng(5).integers(0, 3, cat.n_stars)  # 3 shared templates
    qe_a = {0: (0.8, 0.7), 1: (1.0, 0.9), 2: (1.2, 0.5)}
    qe_b = {0: (0.95, 0.6), 1: (0.96, 0.61), 2: (1.3, 1.1)}  # another response: other, closer ratios
    a, b = _templated(cat, labels, qe_a), _templated(cat, labels, qe_b)
    sphi = 1e-3
    floor_a, floor_b = template_floor(a, sphi, 4.65), template_floor(b, sphi, 4.65)
    assert floor_a.any()
    np.testing.assert_array_equal(floor_a, floor_b)
    # the floor is what no colour noise gets under: every pair in it is ambiguous at any sigma_colour
    for sc in (0.02, 1e-4):
        assert not (floor_b & ~ambiguous_pairs(b, sphi, 4.65, sc, sc)).any()
    # one spectrum for all: the monochrome ambiguity; a spectrum per star: nothing left
    np.testing.assert_array_equal(even_template_floor(cat, sphi, 4.65, 1), ambiguous_pairs(cat, sphi, 4.65))
    assert not even_template_floor(cat, sphi, 4.65, cat.n_stars).any()


def test_required_colour_spread_is_found_by_bisection(cat):
    sphi = 1e-3
    f = [synthetic_colour_ambiguity(cat, sphi, 4.65, w, 2) for w in (0.1, 1.0, 10.0, 100.0)]
    assert f == sorted(f, reverse=True) and f[0] > f[-1]
    target = 0.5 * (f[0] + f[-1])
    w = solve_decreasing(lambda x: synthetic_colour_ambiguity(cat, sphi, 4.65, x, 2), target, 0.1, 100.0)
    assert synthetic_colour_ambiguity(cat, sphi, 4.65, w * 1.01, 2) <= target
    assert synthetic_colour_ambiguity(cat, sphi, 4.65, w / 1.01, 2) > target
    # a 1-D locus needs a wider spread than two independent colours for the same ambiguity
    w1 = solve_decreasing(lambda x: synthetic_colour_ambiguity(cat, sphi, 4.65, x, 1), target, 0.1, 1e4)
    assert w1 > w


def test_two_star_views_match_a_direct_count(cat):
    theta = 0.15
    amb = ambiguous_pairs(cat, 1e-3, 4.65)  # monochrome
    assert amb.any() and (~amb).any()
    views = spiral_points(3000)
    lookup = {(int(i), int(j)): bool(a) for i, j, a in zip(cat.pair_i, cat.pair_j, amb)}
    two, unres = 0, np.zeros(len(views), bool)
    for k, r in enumerate(views):
        inside = np.flatnonzero(angle_between(cat.vec, r) < theta)
        if len(inside) == 2:
            two += 1
            unres[k] = lookup.get((int(inside[0]), int(inside[1])), True)
    got = two_star_views(cat, views, theta, amb)
    assert got.exactly_two == two > 0
    np.testing.assert_array_equal(got.mask, unres)
    assert got.ambiguous == unres.sum() > 0 and got.ambiguous < two
    # a lower bound on the unresolvable views by the full definition
    full = view_availability(cat, views, theta, amb)
    assert not (got.mask & ~full.unresolvable_mask).any()


def test_a_wider_field_keeps_every_ambiguous_pair(cat):
    small = OnboardCatalog.build(cat.star_id, cat.vec, cat.mag, cat.rg, cat.bg, phi_min=1e-3, phi_max=0.2, n_h=64)
    sphi_small, sphi_big = 1e-3, 1e-3 * 4 / 3  # the wider field: a shorter focal length, a wider window
    amb_s = ambiguous_pairs(small, sphi_small, 4.65, 0.02, 0.02)
    amb_b = ambiguous_pairs(cat, sphi_big, 4.65, 0.02, 0.02)
    n = field_nesting(small, amb_s, cat, amb_b, 4.65 * sphi_small, 4.65 * sphi_big)
    assert n.contained == n.small_pairs == small.n_pairs and n.big_pairs == cat.n_pairs
    assert n.small_ambiguous > 0 and n.still_ambiguous == n.small_ambiguous
    assert n.big_ambiguous >= n.small_ambiguous and n.added_pairs == cat.n_pairs - small.n_pairs
    assert n.window_ratio == pytest.approx(4 / 3)
