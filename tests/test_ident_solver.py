"""Solver front: method choice, result structure, and degenerate input never raising."""

import numpy as np
import pytest
from ident_sky import random_attitude, random_catalog, scene

from firmware_model.camera import CameraModel
from firmware_model.ident.consensus import Outcome
from firmware_model.ident.solver import SolveParams
from firmware_model.ident.strategy import solve
from firmware_model.ident.verify import FieldOfView
from firmware_model.reference_frames import quat_to_matrix, rotation_angle

CAM = CameraModel.reference_design()
PARAMS = SolveParams(sigma_vec=0.2 / CAM.f, fov=FieldOfView.from_camera(CAM))


@pytest.fixture(scope="module")
def cat():
    return random_catalog(1600, 0)


def rich_scene(cat, seed, n_min=6):
    rng = np.random.default_rng(seed)
    while True:
        a = random_attitude(rng)
        v, rg, bg, truth = scene(cat, a, rng)
        if len(v) >= n_min:
            return a, v, rg, bg, truth


def test_result_structure_and_accuracy(cat):
    a, v, rg, bg, truth = rich_scene(cat, 1)
    res = solve(v, rg, bg, cat, PARAMS)
    assert res.status is Outcome.HIGH_CONFIDENCE and res.method == "colour" and res.reason == ""
    assert res.q_icrs_to_sensor[0] >= 0 and abs(np.linalg.norm(res.q_icrs_to_sensor) - 1) < 1e-12
    assert rotation_angle(quat_to_matrix(res.q_icrs_to_sensor), a) < 10 * PARAMS.sigma_vec
    assert np.all(truth[res.matched_det] == res.matched_cat)
    assert np.all(res.matched_star_id == cat.star_id[res.matched_cat])
    np.testing.assert_allclose(res.matched_rg, cat.rg[res.matched_cat])
    assert res.covariance.shape == (3, 3) and np.all(np.linalg.eigvalsh(res.covariance) > 0)
    assert len(res.residuals) == len(res.matched_det) and res.consensus_rms < 5 * PARAMS.sigma_vec
    assert 0 < res.confidence <= 1 and res.consensus_size >= 2
    assert {"validate", "match", "verify", "total"} <= set(vars(res.timings))
    assert res.matched == list(zip(res.matched_det.tolist(), res.matched_cat.tolist(), res.matched_star_id.tolist()))


def test_auto_picks_geometric_without_colour_and_forced_modes(cat):
    a, v, rg, bg, truth = rich_scene(cat, 2, n_min=8)
    mono = solve(v, None, None, cat, PARAMS)
    assert mono.method == "geometric" and mono.ok
    assert np.all(truth[mono.matched_det] == mono.matched_cat)
    forced = solve(v, rg, bg, cat, SolveParams(mode="geometric", sigma_vec=PARAMS.sigma_vec, fov=PARAMS.fov))
    assert forced.method == "geometric" and forced.ok
    mono_cat = random_catalog(1600, 0, colour=False)
    r = solve(v, rg, bg, mono_cat, SolveParams(mode="colour", fov=PARAMS.fov))
    assert r.status is Outcome.NO_MATCH and "no colours" in r.reason


@pytest.mark.parametrize(
    "vectors, reason",
    [
        (np.empty((0, 3)), "need at least two"),
        (np.array([[0, 0, 1.0]]), "need at least two"),
        (np.full((5, 3), np.nan), "need at least two"),
        (np.zeros((4, 3)), "need at least two"),
        (np.ones((4, 2)), "shape (N, 3)"),
        ("junk", "numeric"),
        (np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, 1.0]]), "need at least two"),
    ],
)
def test_degenerate_input_is_a_clean_no_match(cat, vectors, reason):
    res = solve(vectors, None, None, cat, PARAMS)
    assert res.status is Outcome.NO_MATCH and reason in res.reason and res.q_icrs_to_sensor is None


def test_colour_length_mismatch_and_bad_sigma(cat):
    v = np.array([[0, 0, 1.0], [0.01, 0, 1.0]])
    assert "rg has 3 values" in solve(v, [1, 2, 3], [1, 2], cat, PARAMS).reason
    assert "sigma_vec" in solve(v, None, None, cat, SolveParams(sigma_vec=np.ones(5))).reason


def test_nan_and_duplicate_rows_are_dropped_and_indices_kept(cat):
    """A NaN row goes; a pair closer than phi_min goes whole; indices refer to the input rows."""
    a, v, rg, bg, truth = rich_scene(cat, 3)
    v2 = np.vstack([[np.nan, 0, 1], v[:1], v])  # a NaN row and a duplicate of the brightest
    rg2 = np.concatenate([[0.5], rg[:1], rg])
    bg2 = np.concatenate([[0.5], bg[:1], bg])
    res = solve(v2, rg2, bg2, cat, PARAMS)
    assert res.status is Outcome.HIGH_CONFIDENCE
    assert any("non-finite" in n for n in res.notes) and any("closer than phi_min" in n for n in res.notes)
    truth2 = np.concatenate([[-1, truth[0]], truth])
    assert np.all(truth2[res.matched_det] == res.matched_cat)
    # both copies go: which of two unresolvable detections is the star cannot be told
    assert not {0, 1, 2} & set(res.matched_det.tolist())


def test_hundreds_of_detections_are_bounded(cat):
    a, v, rg, bg, truth = rich_scene(cat, 4)
    rng = np.random.default_rng(4)
    n = 400
    junk = CAM.pixel_to_vector(rng.uniform(0, CAM.width, n), rng.uniform(0, CAM.height, n))
    v2 = np.vstack([v, junk])  # true stars brightest, then noise detections
    res = solve(
        v2, np.concatenate([rg, rng.uniform(0.3, 1.3, n)]), np.concatenate([bg, rng.uniform(0.3, 1.4, n)]), cat, PARAMS
    )
    assert res.ok and np.all(np.concatenate([truth, np.full(n, -1)])[res.matched_det] == res.matched_cat)
    assert any("brightest" in s for s in res.notes)
    assert res.timings.total < 1.0
    junk_first = solve(np.vstack([junk, v]), None, None, cat, PARAMS)  # all-false brightest: geometric
    assert junk_first.status is not Outcome.HIGH_CONFIDENCE or np.all(
        np.concatenate([np.full(n, -1), truth])[junk_first.matched_det] == junk_first.matched_cat
    )


def test_catalog_for_another_fov_is_a_clean_no_match(cat):
    a, v, rg, bg, truth = rich_scene(cat, 5)
    tiny = random_catalog(5000, 1, phi_max_deg=0.25, phi_min_deg=0.001)
    assert tiny.n_pairs > 50
    res = solve(v, rg, bg, tiny, PARAMS)
    assert res.status is Outcome.NO_MATCH and "another field of view" in res.reason


def test_unknown_mode(cat):
    a, v, rg, bg, truth = rich_scene(cat, 6)
    assert "unknown mode" in solve(v, rg, bg, cat, SolveParams(mode="psychic")).reason
