"""4-star K-vector matching (seed 001 section 2) against brute force."""

import numpy as np
import pytest
from ident_sky import random_attitude, random_catalog

from firmware_model.catalog.onboard import angle_between
from firmware_model.ident.four_star import (
    GROUP_PAIRS,
    SIGNATURES,
    FourStarParams,
    identify_group,
    match_four_star,
    vote_matrix,
)

EPS = np.radians(0.01)


@pytest.fixture(scope="module")
def cat():
    # Mv <= 5 density (about 1630 stars), seed 001 pair range 0.05-24.5 deg
    return random_catalog(1630, 3, phi_max_deg=24.5, phi_min_deg=0.05, colour=False)


def field(cat, rng, radius_deg=12.25, sigma=EPS / (3 * np.sqrt(2))):
    a = random_attitude(rng)
    idx = cat.stars_within(a[2], np.radians(radius_deg))
    s = cat.vec[idx] @ a.T + rng.normal(scale=sigma, size=(len(idx), 3))
    return idx, s / np.linalg.norm(s, axis=1)[:, None]


def brute_votes(group, cat, eps):
    m = np.zeros((cat.n_stars, 6), int)
    for r, (a, b) in enumerate(GROUP_PAIRS):
        theta = float(angle_between(group[a], group[b]))
        for i, j, phi in zip(cat.pair_i, cat.pair_j, cat.pair_phi):
            if abs(phi - theta) <= eps:
                m[i, r] += 1
                m[j, r] += 1
    return m


def test_vote_matrix_and_signatures_equal_brute_force(cat):
    rng = np.random.default_rng(0)
    for _ in range(3):
        idx, s = field(cat, rng)
        group = s[:4]
        rows, m = vote_matrix(group, cat, EPS, 10**9)
        dense = brute_votes(group, cat, EPS)
        ref_rows = np.nonzero(dense.any(axis=1))[0]
        assert rows.tolist() == ref_rows.tolist()
        np.testing.assert_array_equal(m, dense[ref_rows])
        ids = identify_group(group, cat, EPS, resolve_ambiguous=False)
        for k in range(4):
            hits = np.nonzero(np.all(dense == SIGNATURES[k], axis=1))[0]
            assert ids[k] == (hits[0] if len(hits) == 1 else -1)


def brute_consistent(group, cat, eps, cands):
    out = []
    for c in np.array(np.meshgrid(*cands, indexing="ij")).reshape(4, -1).T:
        if len(set(c.tolist())) == 4 and all(
            abs(float(angle_between(cat.vec[c[a]], cat.vec[c[b]]) - angle_between(group[a], group[b]))) <= eps
            for a, b in GROUP_PAIRS
        ):
            out.append(c.tolist())
    return out


def test_ambiguity_resolution_equals_brute_force(cat):
    rng = np.random.default_rng(6)
    resolved = 0
    for _ in range(40):
        idx, s = field(cat, rng)
        if len(idx) < 4:
            continue
        group = s[-4:]  # outer stars: wide angles, many candidates
        paper = identify_group(group, cat, EPS, resolve_ambiguous=False)
        ours = identify_group(group, cat, EPS)
        if (paper >= 0).all():
            assert ours.tolist() == paper.tolist()
            continue
        dense = brute_votes(group, cat, EPS)
        cands = [np.nonzero(np.all(dense[:, SIGNATURES[k] == 1] >= 1, axis=1))[0] for k in range(4)]
        if np.prod([len(c) for c in cands], dtype=float) > 4096:
            continue
        ref = brute_consistent(group, cat, EPS, cands)
        if len(ref) == 1:
            assert ours.tolist() == ref[0]
            resolved += 1
        else:
            assert ours.tolist() == paper.tolist()
    assert resolved >= 3


def test_identifications_are_correct_and_plenty(cat):
    rng = np.random.default_rng(1)
    identified = wrong = 0
    for _ in range(25):
        idx, s = field(cat, rng)
        if len(idx) < 4:
            continue
        res = match_four_star(s, cat, EPS)
        wrong += int(np.sum(idx[res.det] != res.cat))
        identified += len(res.det)
        assert len(res.det) >= 2
        assert len(res.det) + len(res.unidentified) == len(idx)
    assert wrong == 0 and identified > 200


def test_false_star_in_the_central_group_is_survived(cat):
    rng = np.random.default_rng(2)
    idx, s = field(cat, rng)
    while len(idx) < 8:
        idx, s = field(cat, rng)
    fake = np.array([[0.001, -0.002, 1.0]]) / np.linalg.norm([0.001, -0.002, 1.0])  # near the centre
    res = match_four_star(np.vstack([fake, s]), cat, EPS)
    truth = np.concatenate([[-1], idx])
    assert 0 not in res.det and len(res.det) >= 2
    assert np.all(truth[res.det] == res.cat)


def test_group_count_is_bounded(cat):
    rng = np.random.default_rng(4)
    v = rng.normal(size=(60, 3)) * [0.1, 0.1, 0] + [0, 0, 1]
    v /= np.linalg.norm(v, axis=1)[:, None]
    res = match_four_star(v, cat, EPS, FourStarParams(max_groups=5))
    assert res.groups <= 5 and len(res.det) == 0
