"""Identification with false and missing stars: miss-tolerant coverage test, adaptive
seed and triad orders, the two-star last resort, the triangle side beyond the pair range."""

from dataclasses import replace
from itertools import combinations

import numpy as np
import pytest
from ident_sky import random_attitude, random_catalog, scene

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import angle_between
from firmware_model.ident.consensus import ConsensusParams, Outcome, SeedOrder, confident, match_scene, seed_pairs
from firmware_model.ident.pair_match import PairNoise
from firmware_model.ident.solver import SolveParams
from firmware_model.ident.strategy import check_hypothesis, solve
from firmware_model.ident.triangle import TriadOrder, triangles
from firmware_model.ident.verify import FieldOfView, VerifyParams, chance_alignment, coverage_ok, miss_tail, verify

CAM = CameraModel.reference_design()
SIG = 0.2 / CAM.f
NOISE = PairNoise(2 * SIG, 0.05, 0.05)
FOV = FieldOfView.from_camera(CAM)


@pytest.fixture(scope="module")
def cat():
    return random_catalog(1600, 0)


def test_miss_tail_is_the_binomial_tail():
    from scipy.stats import binom

    for n in (1, 3, 6, 9, 13, 25):
        for m in range(0, n + 2):
            assert miss_tail(n, m, 0.1) == pytest.approx(binom.sf(m - 1, n, 0.1), rel=1e-9, abs=1e-15)
    assert miss_tail(5, 2, 0.0) == 0.0 and miss_tail(5, 0, 0.0) == 1.0


def test_chance_alignment_is_the_binomial_tail_beyond_the_first_two_stars():
    from scipy.stats import binom

    omega, gate = FOV.solid_angle, 5 * SIG
    p = 30 * np.pi * gate**2 / omega
    assert chance_alignment(30, 8, 5, gate, omega) == pytest.approx(binom.sf(2, 6, p), rel=1e-9)
    assert chance_alignment(30, 8, 2, gate, omega) == 1.0  # two stars only fix the attitude
    assert chance_alignment(30, 3, 5, gate, omega) == pytest.approx(p**3, rel=1e-9)  # more matched than predicted
    # more clutter or a wider gate makes a coincidence likelier
    assert chance_alignment(60, 8, 5, gate, omega) > chance_alignment(30, 8, 5, gate, omega)
    assert chance_alignment(30, 8, 5, 3 * gate, omega) > chance_alignment(30, 8, 5, gate, omega)
    assert chance_alignment(10**9, 8, 5, gate, omega) == 1.0  # the per-star chance saturates at 1


def test_few_stars_are_confident_only_when_chance_cannot_explain_them():
    cp = ConsensusParams()

    class Set:
        def __init__(self, n, chance, coverage=0.5):
            self.n, self.chance, self.coverage = n, chance, coverage

    assert confident(Set(4, 1e-12), cp) and confident(Set(5, cp.chance_alpha), cp)
    assert not confident(Set(4, 1e-6), cp)  # a coincidence is not negligible
    assert not confident(Set(3, 1e-20), cp)  # below chance_stars
    assert confident(Set(6, 1.0, coverage=0.8), cp) and not confident(Set(6, 1.0, coverage=0.7), cp)


def test_coverage_tolerates_plausible_misses_only():
    p = VerifyParams()
    assert coverage_ok(6, 4, p) and coverage_ok(9, 6, p) and coverage_ok(13, 9, p) and coverage_ok(3, 2, p)
    assert not coverage_ok(12, 4, p) and not coverage_ok(9, 4, p) and not coverage_ok(20, 2, p)
    strict = replace(p, miss_rate=0.0)  # the fixed 0.7 floor of the previous verification
    assert not coverage_ok(6, 4, strict) and not coverage_ok(3, 2, strict) and coverage_ok(10, 7, strict)
    assert not coverage_ok(9, 6, replace(p, coverage_min_matched=7))


def _impaired_frame(catalog, rng, drop, n_false, min_true=4):
    """A scene with ``drop`` true stars removed and ``n_false`` false detections put first."""
    while True:
        a = random_attitude(rng)
        v, rg, bg, truth = scene(catalog, a, rng)
        if len(v) - drop >= min_true and len(v) >= 6:
            break
    keep = np.sort(rng.choice(len(v), len(v) - drop, replace=False))
    fv = CAM.pixel_to_vector(rng.uniform(0, CAM.width, n_false), rng.uniform(0, CAM.height, n_false))
    v = np.vstack([fv, v[keep]])
    rg = np.concatenate([rng.uniform(0.3, 1.3, n_false), rg[keep]])
    bg = np.concatenate([rng.uniform(0.3, 1.4, n_false), bg[keep]])
    truth = np.concatenate([np.full(n_false, -1), truth[keep]])
    return v, rg, bg, truth


def test_true_identification_with_a_third_missing_is_verified_only_with_the_miss_model(cat):
    rng = np.random.default_rng(4)
    passed = {"new": 0, "strict": 0}
    for _ in range(15):
        while True:
            a = random_attitude(rng)
            v, rg, bg, truth = scene(cat, a, rng)
            if 6 <= len(v) <= 12:
                break
        # drop the faintest: 4 of 6, 5 of 8, 6 of 10, 8 of 12 remain (coverage < 0.7)
        keep = np.arange(len(v) - max(2, int(np.ceil(0.31 * len(v)))))
        for name, vp in (("new", VerifyParams()), ("strict", VerifyParams(miss_rate=0.0, coverage_chance=0.0))):
            m, _ = verify(
                keep, truth[keep], v[keep], rg[keep], bg[keep], np.full(len(keep), SIG), cat, FOV, 0.05, 0.05, vp
            )
            passed[name] += m is not None
    assert passed["strict"] <= 3 and passed["new"] >= 12


def test_seed_order_moves_away_from_failed_detections():
    assert list(SeedOrder(6, adaptive=False)) == list(seed_pairs(6))
    order = SeedOrder(12)
    got = []
    for k, l in order:
        got.append((k, l))
        if min(k, l) < 8:  # detections 0-7 are false: every seed holding one fails
            order.failed(k, l)
        else:
            break
    assert got[-1] == (8, 9) and len(got) == 5  # (0,1), (2,3), (4,5), (6,7), (8,9)
    fixed = list(seed_pairs(12))
    assert fixed.index((8, 9)) + 1 == 45


def test_scene_whose_brightest_detections_are_false_is_solved(cat):
    rng = np.random.default_rng(11)
    solved = {"adaptive": 0, "paper order": 0}
    for _ in range(6):
        v, rg, bg, truth = _impaired_frame(cat, rng, drop=0, n_false=10, min_true=6)

        def chk(d, c, v=v, rg=rg, bg=bg):
            return verify(d, c, v, rg, bg, np.full(len(v), SIG), cat, FOV, 0.05, 0.05, VerifyParams())

        for name, cp in (
            ("adaptive", ConsensusParams()),
            ("paper order", ConsensusParams(adaptive_seeds=False, attempts_per_star=3.0)),
        ):
            res = match_scene(v, rg, bg, cat, NOISE, cp, chk)
            if res.outcome is Outcome.HIGH_CONFIDENCE:
                assert np.all(truth[res.best.det] == res.best.cat)
                solved[name] += 1
    assert solved["adaptive"] == 6 and solved["paper order"] <= 3


def test_two_true_stars_among_false_ones_give_a_low_confidence_answer():
    rng = np.random.default_rng(3)
    sparse = random_catalog(300, 5)  # about two stars per field
    found = 0
    for _ in range(400):
        a = random_attitude(rng)
        v, rg, bg, truth = scene(sparse, a, rng)
        if len(v) != 2 or angle_between(v[0], v[1]) > sparse.phi_max:
            continue
        fv = CAM.pixel_to_vector(rng.uniform(0, CAM.width, 4), rng.uniform(0, CAM.height, 4))
        v2 = np.vstack([fv, v])
        rg2 = np.concatenate([rng.uniform(0.3, 1.3, 4), rg])
        bg2 = np.concatenate([rng.uniform(0.3, 1.4, 4), bg])
        params = SolveParams(sigma_vec=SIG, fov=FOV)
        res = solve(v2, rg2, bg2, sparse, params)
        none = solve(v2, rg2, bg2, sparse, replace(params, consensus=ConsensusParams(last_resort=0)))
        assert none.status is Outcome.NO_MATCH
        assert res.status is Outcome.LOW_CONFIDENCE
        assert sorted(res.matched_det.tolist()) == [4, 5] and np.all(truth[res.matched_det - 4] == res.matched_cat)
        found += 1
        if found == 3:
            break
    assert found == 3


def test_triangles_with_a_side_beyond_the_pair_range_equal_brute_force():
    cat = random_catalog(120, 2, phi_max_deg=12.0, colour=False)
    rng = np.random.default_rng(1)
    eps = np.radians(0.3)
    full = angle_between(cat.vec[:, None, :], cat.vec[None, :, :])
    in_table = (full > cat.phi_min) & (full <= cat.phi_max)
    checked = 0
    for _ in range(400):
        a = random_attitude(rng)
        idx = cat.stars_within(a[2], np.radians(12))
        for t in combinations(idx.tolist(), 3):
            v3 = cat.vec[list(t)] @ a.T
            m = [float(angle_between(v3[p], v3[q])) for p, q in ((0, 1), (0, 2), (1, 2))]
            if not (m[0] <= cat.phi_max < m[2] and m[1] <= cat.phi_max):
                continue  # wanted: sides 0-1 and 0-2 in the table, side 1-2 beyond it
            got = {tuple(x) for x in triangles(v3, cat, eps).tolist()}
            ok01 = in_table & (np.abs(full - m[0]) <= eps)
            ok02 = in_table & (np.abs(full - m[1]) <= eps)
            ok12 = np.abs(full - m[2]) <= eps  # checked on the vectors, no table needed
            x, y, z = np.nonzero(ok01[:, :, None] & ok02[:, None, :] & ok12[None, :, :])
            keep = (x != y) & (x != z) & (y != z)
            x, y, z = x[keep], y[keep], z[keep]
            hand = np.sign(np.linalg.det(np.stack([cat.vec[x], cat.vec[y], cat.vec[z]], axis=1)))
            sel = hand == np.sign(np.linalg.det(v3))
            assert got == set(zip(x[sel].tolist(), y[sel].tolist(), z[sel].tolist()))
            assert t in got
            checked += 1
            break
        if checked >= 5:
            break
    assert checked >= 5


def base_order_index(n, t):
    return list(TriadOrder(n, adaptive=False)).index(t)


def test_triad_order_covers_small_sets_first_and_adapts():
    base = list(TriadOrder(6, adaptive=False))
    assert base[:4] == [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)] and len(base) == 20
    order = TriadOrder(8)
    seen = []
    for t in order:
        seen.append(t)
        if min(t) < 4:  # detections 0-3 false
            order.failed(t)
        else:
            break
    assert seen == [(0, 1, 2), (3, 4, 5), (0, 6, 7), (1, 2, 3), (4, 5, 6)]
    assert base_order_index(8, (4, 5, 6)) == 34  # the base order would need 35 triads


def test_mono_frames_with_false_bright_stars_are_solved(cat):
    rng = np.random.default_rng(21)
    params = SolveParams(mode="geometric", sigma_vec=SIG, fov=FOV)
    ok = 0
    for _ in range(6):
        v, _, _, truth = _impaired_frame(cat, rng, drop=1, n_false=6, min_true=5)
        res = solve(v, None, None, cat, params)
        if res.ok:
            assert np.all(truth[res.matched_det] == res.matched_cat)
            ok += 1
    assert ok == 6


def test_check_hypothesis_maps_input_rows(cat):
    rng = np.random.default_rng(8)
    v, rg, bg, truth = _impaired_frame(cat, rng, drop=0, n_false=2)
    v = np.vstack([[np.nan, 0, 1], v])  # a row the cleaning drops
    rg, bg, truth = np.r_[0.5, rg], np.r_[0.5, bg], np.r_[-1, truth]
    det = np.nonzero(truth >= 0)[0]
    params = SolveParams(sigma_vec=SIG, fov=FOV)
    m, why = check_hypothesis(v, rg, bg, det, truth[det], cat, params)
    assert m is not None and why == "" and m.n == len(det)
    wrong = np.roll(truth[det], 1)
    assert check_hypothesis(v, rg, bg, det, wrong, cat, params)[0] is None


def test_a_false_detection_next_to_a_star_gives_way_to_the_star(cat):
    rng = np.random.default_rng(2)
    while True:
        a = random_attitude(rng)
        v, rg, bg, truth = scene(cat, a, rng)
        if len(v) >= 6:
            break
    # a false detection 0.7 px (3.5 sigma) from star 2, brighter (listed first), same colour
    off = np.cross(v[2], [0.0, 0.0, 1.0])
    fake = v[2] + 0.7 / CAM.f * off / np.linalg.norm(off)
    v2 = np.vstack([fake / np.linalg.norm(fake), v])
    rg2, bg2, truth2 = np.r_[rg[2], rg], np.r_[bg[2], bg], np.r_[-1, truth]
    det = np.r_[0, 1, 2, 4]  # the hypothesis took the false detection for star 2
    m, _ = verify(det, truth2[[3, 1, 2, 4]], v2, rg2, bg2, np.full(len(v2), SIG), cat, FOV, 0.05, 0.05, VerifyParams())
    assert m is not None and 0 not in m.det and 3 in m.det
    assert np.all(truth2[m.det] == m.cat)
