"""Colour pair matching (seed 000 eqs 1-7, 14-16) against brute force on small catalogs."""

import numpy as np
import pytest
from ident_sky import random_catalog

from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.ident.pair_match import (
    PairNoise,
    best_match,
    consistency_tolerance,
    critical_distance,
    match_pair,
    pair_tuple,
    sigma_phi_from_centroid,
)


def test_critical_distance_is_papers_value():
    assert critical_distance(0.99) == pytest.approx(4.65, abs=0.005)
    assert consistency_tolerance(2e-5, 4.65) == pytest.approx(4.65e-5)
    assert sigma_phi_from_centroid(0.2, 7383.1) == pytest.approx(54.2e-6, rel=1e-3)
    with pytest.raises(ValueError, match="P_correct"):
        critical_distance(1.0)
    with pytest.raises(ValueError, match="sigma_phi"):
        PairNoise(0.0)


def brute_force(t, cat, noise, delta_star):
    out = {}
    for row in range(cat.n_pairs):
        i, j, phi = cat.pair_i[row], cat.pair_j[row], cat.pair_phi[row]
        for swapped, (a, b) in enumerate(((i, j), (j, i))):
            d = np.sqrt(
                ((t[0] - cat.rg[a]) / noise.sigma_rg) ** 2
                + ((t[1] - cat.bg[a]) / noise.sigma_bg) ** 2
                + ((t[2] - phi) / noise.sigma_phi) ** 2
                + ((t[3] - cat.rg[b]) / noise.sigma_rg) ** 2
                + ((t[4] - cat.bg[b]) / noise.sigma_bg) ** 2
            )
            if d < delta_star:
                out[(row, bool(swapped))] = d
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_match_pair_equals_brute_force_both_orderings(seed):
    cat = random_catalog(150, seed, phi_max_deg=40.0)
    rng = np.random.default_rng(seed)
    noise = PairNoise(sigma_phi=2e-3, sigma_rg=0.1, sigma_bg=0.1)
    ds = critical_distance(0.99)
    for _ in range(40):
        row = rng.integers(cat.n_pairs)
        i, j = cat.pair_i[row], cat.pair_j[row]
        k, l = (i, j) if rng.random() < 0.5 else (j, i)
        t = pair_tuple(cat.vec[k], cat.vec[l], cat.rg[k], cat.bg[k], cat.rg[l], cat.bg[l])
        t = t + rng.normal(scale=[0.1, 0.1, 2e-3, 0.1, 0.1])
        got = match_pair(t, cat, noise, ds)
        ref = brute_force(t, cat, noise, ds)
        assert {(int(r), bool(s)) for r, s in zip(got.row, got.swapped)} == set(ref)
        assert np.all(np.diff(got.delta) >= 0)
        for r, s, d in zip(got.row, got.swapped, got.delta):
            assert d == pytest.approx(ref[(int(r), bool(s))], rel=1e-6)
        if ref:
            (r0, s0) = min(ref, key=ref.get)
            ck, cl, _ = best_match(t, cat, noise, ds)
            pi, pj = cat.pair_i[r0], cat.pair_j[r0]
            assert (ck, cl) == ((pj, pi) if s0 else (pi, pj))


def symmetric_catalog():
    """Three stars; stars 0 and 1 share a colour (a symmetric pair), star 2 differs."""
    v = np.array([[1.0, 0, 0], [np.cos(0.05), np.sin(0.05), 0], [np.cos(0.03), 0, np.sin(0.03)]])
    return OnboardCatalog.build([1, 2, 3], v, [1, 2, 3], [0.6, 0.6, 1.1], [0.9, 0.9, 0.4], phi_min=1e-4, phi_max=0.2)


def test_symmetric_pair_gives_both_assignments_with_equal_distance():
    cat = symmetric_catalog()
    t = pair_tuple(cat.vec[0], cat.vec[1], 0.6, 0.9, 0.6, 0.9)
    got = match_pair(t, cat, PairNoise(1e-4), critical_distance(0.99))
    assert len(got) == 2
    assert {(int(a), int(b)) for a, b in zip(got.cat_k, got.cat_l)} == {(0, 1), (1, 0)}
    assert got.delta[0] == pytest.approx(got.delta[1])


def test_colour_breaks_the_tie_of_an_asymmetric_pair():
    cat = symmetric_catalog()
    t = pair_tuple(cat.vec[2], cat.vec[0], 1.1, 0.4, 0.6, 0.9)  # observed (k, l) = catalog (2, 0)
    got = match_pair(t, cat, PairNoise(1e-4), critical_distance(0.99))
    assert (int(got.cat_k[0]), int(got.cat_l[0])) == (2, 0) and len(got) == 1


def test_monochrome_reduces_to_angle_only():
    cat = random_catalog(200, 4, phi_max_deg=30.0, colour=False)
    phi = float(cat.pair_phi[50])
    t = np.array([np.nan, np.nan, phi, np.nan, np.nan])
    noise = PairNoise(1e-3)
    got = match_pair(t, cat, noise, 4.65)
    expect = np.nonzero(np.abs(cat.pair_phi - phi) / 1e-3 < 4.65)[0]
    assert sorted(set(got.row.tolist())) == expect.tolist()
    assert np.allclose(got.delta, np.abs(cat.pair_phi[got.row] - phi) / 1e-3)


def test_window_cap_flags_truncation():
    cat = random_catalog(300, 5, phi_max_deg=40.0, colour=False)
    t = np.array([np.nan, np.nan, float(cat.pair_phi[cat.n_pairs // 2]), np.nan, np.nan])
    got = match_pair(t, cat, PairNoise(5e-2), 4.65, max_window=10)
    assert got.truncated and len(set(got.row.tolist())) <= 10
