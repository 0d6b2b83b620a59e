"""Pair table and both indices against brute force on small generated catalogs."""

import numpy as np
import pytest

from firmware_model.catalog.onboard import OnboardCatalog, build_pair_table


def random_sky(n, seed):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None]


def brute_pairs(vec, phi_min, phi_max):
    n = len(vec)
    out = []
    for i in range(n):
        for j in range(i + 1, n):
            phi = np.arccos(np.clip(vec[i] @ vec[j], -1, 1))
            if phi_min < phi <= phi_max:
                out.append((i, j, phi))
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pair_table_matches_brute_force(seed):
    vec = random_sky(300, seed)
    phi_min, phi_max = np.radians(0.5), np.radians(15.0)
    pi, pj, phi = build_pair_table(vec, phi_min, phi_max)
    ref = brute_pairs(vec, phi_min, phi_max)
    assert len(phi) == len(ref)
    assert set(zip(pi.tolist(), pj.tolist())) == {(i, j) for i, j, _ in ref}
    assert np.all(np.diff(phi) >= 0)
    assert np.all(pi < pj)
    ref_phi = {(i, j): p for i, j, p in ref}
    assert np.allclose([ref_phi[(i, j)] for i, j in zip(pi, pj)], phi, atol=1e-9)


def test_pair_table_rejects_impossible_bounds():
    with pytest.raises(ValueError, match="phi_min"):
        build_pair_table(random_sky(10, 0), 0.3, 0.2)


@pytest.mark.parametrize("n_h,dphi_star", [(1024, 0.0), (64, 0.001), (7, 0.01)])
def test_indices_match_brute_force(n_h, dphi_star):
    vec = random_sky(400, 5)
    cat = OnboardCatalog.build(
        np.arange(400),
        vec,
        np.zeros(400),
        phi_min=np.radians(0.1),
        phi_max=np.radians(20.0),
        n_h=n_h,
        dphi_star=dphi_star,
    )
    rng = np.random.default_rng(9)
    queries = np.concatenate([rng.uniform(-0.01, cat.phi_max + 0.01, 300), cat.pair_phi[::97]])
    for phi in queries:
        for tol in (1e-5, 3e-4, 5e-3):
            inside = np.nonzero(np.abs(cat.pair_phi - phi) <= tol)[0]
            expect = (int(inside[0]), int(inside[-1]) + 1) if len(inside) else None
            for got in (cat.hash_range(phi, tol), cat.kvector_range(phi, tol)):
                if expect is None:
                    assert got[0] == got[1]
                else:
                    assert got == expect
            a, b = cat.kvector_candidates(phi, tol)
            if expect is not None:
                assert a <= expect[0] and b >= expect[1]
            s, e = cat.pair_ranges(np.array([phi]), tol)
            assert (int(s[0]), int(e[0])) == (cat.hash_range(phi, tol))


def test_stars_within():
    vec = random_sky(500, 3)
    cat = OnboardCatalog.build(np.arange(500), vec, np.zeros(500), phi_min=0.001, phi_max=0.2)
    d = vec[17]
    got = cat.stars_within(d, 0.3)
    brute = np.nonzero(np.arccos(np.clip(vec @ d, -1, 1)) <= 0.3)[0]
    assert np.array_equal(got, brute)
