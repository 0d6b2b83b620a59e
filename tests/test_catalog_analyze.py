"""Ambiguity search and view availability against brute force; the spiral."""

import itertools

import numpy as np
import pytest

from firmware_model.catalog.onboard import OnboardCatalog, angle_between
from ground.catalog.analyze import ambiguous_pairs, spiral_points, view_availability


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
