"""The frame's own centroid noise (strategy.adapt_noise, extra_noise,
noise_rejected), high confidence of search-chosen patterns (searched_confident), the fit's
Rodrigues rotation (camera_fit.rotvec_matrix) and the optics search going first when the best
pattern's refined optics say the nominal focal length is off (optics_search.nominal_off)."""

from dataclasses import replace

import numpy as np
import pytest
from ident_sky import random_attitude
from open_loop_sky import NOMINAL, PIXEL_RAD, POINTINGS, open_loop_catalog, render
from scipy.spatial.transform import Rotation

from firmware_model.camera import CameraModel
from firmware_model.ident.consensus import ConsensusParams, Outcome
from firmware_model.ident.solver import Method, Mode, SolveParams
from firmware_model.ident.strategy import (
    IdentificationInput,
    StrategyParams,
    extra_noise,
    identify,
    noise_rejected,
    searched_confident,
)
from firmware_model.ident.verify import FieldOfView, VerifyParams, verify
from firmware_model.pipeline import scale_free
from firmware_model.pipeline.camera_fit import rotvec_matrix
from firmware_model.pipeline.extract import extract_stars
from firmware_model.pipeline.run import run_pipeline
from firmware_model.pipeline.solve_types import OpticsSearch, SolveInput, StageTimings
from firmware_model.reference_frames import quat_to_matrix, rotation_angle
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from protocol.result import Status

CAM = CameraModel.reference_design()


def _residual_angles(rng, n, s):
    """Angles |N(0, s^2 I_2)| of ``n`` stars."""
    return np.hypot(*rng.normal(scale=s, size=(2, n)))


def test_extra_noise_recovers_the_per_axis_noise_the_residuals_show():
    rng = np.random.default_rng(12)
    r = _residual_angles(rng, 40, 1.0)
    e = extra_noise(r, np.full(40, 0.1))
    assert e > 0.0 and abs(np.hypot(0.1, e) - 1.0) < 0.25
    # residuals consistent with the announced noise: nothing added
    calm = _residual_angles(np.random.default_rng(3), 40, 0.05)
    assert extra_noise(calm, np.full(40, 0.1)) == 0.0


def test_noise_rejected_only_when_the_residuals_exceed_the_announced_noise():
    sigma = np.full(40, 0.1)
    for seed in range(5):
        rng = np.random.default_rng(seed)
        assert not noise_rejected(_residual_angles(rng, 40, 0.1), sigma)
        assert noise_rejected(_residual_angles(rng, 40, 1.0), sigma)
    assert not noise_rejected(np.array([5.0, 5.0]), np.full(2, 0.1))  # fewer than three stars: no test


def test_searched_confident_needs_a_large_set_or_a_negligible_chance():
    cp = ConsensusParams()
    assert searched_confident(4, 0.5, 1e-9, cp)
    assert not searched_confident(4, 1.0, 1e-5, cp)
    assert not searched_confident(5, 1.0, 1e-7, cp)  # below six stars the chance must reach 1e-8
    assert searched_confident(6, 0.9, 1e-3, cp)
    assert not searched_confident(6, 0.5, 1e-3, cp)  # large but covering too little
    assert not searched_confident(6, float("nan"), 1e-3, cp)  # unknown coverage counts as none


@pytest.mark.parametrize(
    "r",
    [[0.3, -0.2, 0.1], [2.0, 1.0, -0.5], [0.0, 0.0, np.pi - 1e-6], [1e-10, 0.0, 0.0], [3e-9, -4e-9, 1e-9]],
)
def test_rotvec_matrix_is_scipys_rotation(r):
    r = np.asarray(r, float)
    m = rotvec_matrix(r)
    assert np.allclose(m, Rotation.from_rotvec(r).as_matrix(), rtol=0.0, atol=1e-12)
    assert np.allclose(m @ m.T, np.eye(3), atol=1e-12) and np.linalg.det(m) == pytest.approx(1.0, abs=1e-12)


@pytest.fixture(scope="module")
def catalog():
    return build_catalog(CatalogDesign(sigma_rg=0.05, sigma_bg=0.05))


def _noisy_geometric_frame(catalog, seed=1, noise_px=1.0):
    """Catalog stars on the reference array under a random attitude, their centroids moved by
    ``noise_px`` per axis, brightest first: (attitude, vectors, truth catalog indices)."""
    rng = np.random.default_rng(seed)
    a = random_attitude(rng)
    s = catalog.vec @ a.T
    x, y = CAM.vector_to_pixel(s)
    on = np.flatnonzero((s[:, 2] > 0) & CAM.in_frame(x, y))
    on = on[np.argsort(catalog.mag[on])]
    v = CAM.pixel_to_vector(
        x[on] + rng.normal(scale=noise_px, size=len(on)), y[on] + rng.normal(scale=noise_px, size=len(on))
    )
    return a, v, on


def _identify_announcing(catalog, vectors, sigma_px):
    nan = np.full(len(vectors), np.nan)
    params = SolveParams(mode=Mode.GEOMETRIC, sigma_vec=sigma_px / CAM.f, fov=FieldOfView.from_camera(CAM, 0.0))
    det = IdentificationInput(vectors, nan, nan, sigma_px=np.full(len(vectors), sigma_px), focal_px=CAM.f)
    return identify(det, catalog, StrategyParams(solve=params))


def _error_sigmas(sol, a_true):
    """The answer's attitude error about each sensor axis over its reported 1-sigma."""
    m = quat_to_matrix(sol.q_icrs_to_sensor) @ a_true.T  # small rotation, sensor frame
    delta = 0.5 * np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    return delta / np.sqrt(np.diag(sol.covariance))


def test_adapt_noise_holds_an_answer_to_the_noise_its_stars_show(catalog):
    a, v, truth = _noisy_geometric_frame(catalog)
    under = _identify_announcing(catalog, v, 0.1)  # 1 px centroids announced as 0.1 px
    sol = under.solution
    assert sol.status is not Outcome.NO_MATCH and len(sol.matched_det) >= 5
    assert np.array_equal(truth[under.rows[sol.matched_det]], sol.matched_cat)
    assert sol.noise_extra > 0.0
    assert 0.3 < sol.noise_extra * CAM.f < 2.0  # per axis, px: the order of the 1 px the frame has
    assert any("announced centroid noise" in note for note in sol.notes)
    assert np.all(np.abs(_error_sigmas(sol, a)) < 3.0)
    # the same stars with their noise announced: nothing to adapt
    honest = _identify_announcing(catalog, v, 1.0).solution
    assert honest.status is Outcome.HIGH_CONFIDENCE and honest.noise_extra == 0.0
    assert not any("announced centroid noise" in note for note in honest.notes)
    assert np.all(np.abs(_error_sigmas(honest, a)) < 3.0)


@pytest.fixture(scope="module")
def deep_catalog():
    return build_catalog(CatalogDesign(sigma_rg=0.05, sigma_bg=0.05, m_verify=6.0))


def test_a_decided_answer_takes_the_verification_only_stars_in_view(catalog, deep_catalog):
    a, v, truth = _noisy_geometric_frame(deep_catalog, noise_px=0.2)
    shallow = _identify_announcing(catalog, v, 0.2)
    deep = _identify_announcing(deep_catalog, v, 0.2)
    ss, ds = shallow.solution, deep.solution
    assert ss.status is Outcome.HIGH_CONFIDENCE and ds.status is Outcome.HIGH_CONFIDENCE
    assert np.array_equal(truth[deep.rows[ds.matched_det]], ds.matched_cat)
    assert np.count_nonzero(ds.matched_cat >= deep_catalog.n_pattern_stars) >= 5
    assert len(ds.matched_det) > len(ss.matched_det)
    assert ds.chance == ss.chance  # the decision is the pattern stars'
    assert ds.roll_sigma < ss.roll_sigma
    assert np.all(np.abs(_error_sigmas(ds, a)) < 3.0)


def test_a_deep_verification_counts_pattern_stars_and_every_star_for_the_chance(deep_catalog):
    """With ``deep`` the verification-only stars are matched too: the star-count rules see the
    pattern stars (``n_decisive``), the chance alignment every star looked for and found."""
    a, v, truth = _noisy_geometric_frame(deep_catalog, noise_px=0.2)
    seed = np.flatnonzero(truth < deep_catalog.n_pattern_stars)[:3]
    nan = np.full(len(v), np.nan)
    fov, sigma = FieldOfView.from_camera(CAM, 0.0), np.full(len(v), 0.2 / CAM.f)

    def run(deep):
        m, why = verify(seed, truth[seed], v, nan, nan, sigma, deep_catalog, fov, 0.0, 0.0, VerifyParams(deep=deep))
        assert m is not None, why
        assert np.array_equal(truth[m.det], m.cat)
        return m

    pattern_only, every = run(False), run(True)
    assert pattern_only.n == pattern_only.n_decisive and np.all(pattern_only.cat < deep_catalog.n_pattern_stars)
    assert every.n > every.n_decisive >= pattern_only.n - 1
    assert every.chance < pattern_only.chance


@pytest.fixture(scope="module")
def wide_catalog():
    return open_loop_catalog()


@pytest.fixture(scope="module")
def tetra_frame():
    a, r = render(NOMINAL, POINTINGS[2])
    return a, r.frame


def _first_pattern_says_off(frame, camera, catalog):
    from firmware_model.pipeline.optics_search import first_seed, first_tier, nominal_off

    seen = SolveInput(extract_stars(frame, camera), camera, catalog)
    timings = StageTimings()
    peek = first_tier(seen, OpticsSearch(), timings)
    seed = first_seed(seen, OpticsSearch(), timings, peek)
    return nominal_off(peek, seed, seen, OpticsSearch())


def test_search_goes_first_when_the_nominal_focal_length_is_one_percent_off(wide_catalog, tetra_frame):
    a, frame = tetra_frame
    long = replace(NOMINAL, f=NOMINAL.f * 1.01)  # 1 % moves the corners ~6 px: beyond refit_px
    # the catalog's pattern cache for this field is built before the frame (as a device does once):
    # a first build inside the frame's search budget is not what this test is about
    scale_free.catalog_patterns(wide_catalog, long)
    assert _first_pattern_says_off(frame, long, wide_catalog)
    out = run_pipeline(frame, long, wide_catalog)
    assert out.status is Status.OK, out.reason
    assert out.solution.method is Method.PATTERN
    assert rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), a) < 2 * PIXEL_RAD
    assert out.optics is not None and abs(out.optics.camera.f / NOMINAL.f - 1.0) < 0.002
    assert abs(out.optics.focal_scale - 1.0 / 1.01) < 0.002  # the pattern's focal length: the true one


def test_exact_camera_is_kept(wide_catalog, tetra_frame):
    """With the exact camera the search does not go first: the first pattern match is verified with
    the nominal camera (kept) before the geometric matchers run."""
    a, frame = tetra_frame
    assert not _first_pattern_says_off(frame, NOMINAL, wide_catalog)
    out = run_pipeline(frame, NOMINAL, wide_catalog)
    assert out.status is Status.OK, out.reason
    assert out.solution.method is Method.PATTERN and out.camera == NOMINAL
    assert rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), a) < 2 * PIXEL_RAD


def test_estimated_noise_factor_is_the_student_t_widening():
    """The covariance factor for a noise estimated with nu degrees of freedom: (t_q(nu) / 3)^2 with
    q the Gaussian 3-sigma quantile, against scipy's t quantile; the median's degrees of freedom."""
    from scipy.stats import norm, t

    from firmware_model.ident.strategy import MEDIAN_DOF, estimated_noise_factor

    for nu in (2.5, 9, 17, 37, 77):
        exact = (t.ppf(norm.cdf(3.0), nu) / 3.0) ** 2
        assert estimated_noise_factor(nu) == pytest.approx(exact, rel=1e-9)
    assert estimated_noise_factor(200) < estimated_noise_factor(9) < estimated_noise_factor(3)
    assert MEDIAN_DOF == pytest.approx(0.4805, abs=1e-4)  # ln(2)^2
