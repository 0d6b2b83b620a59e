"""Issue 29, item 8: a frame with no stars gets no attitude. A frame of 500 000 hot pixels or of
30 000 random blobs is NO_MATCH ("not a star field": its best match is expected more than once by
chance among the catalog pairs its seed pairs matched), and a star field with hot pixels still
solves."""

import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.ident.consensus import CHANCE_ANSWERS, NOT_A_STAR_FIELD, chance_answers, pair_hypotheses
from firmware_model.ident.pair_match import PairCandidates
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.run import run_pipeline
from firmware_model.reference_frames import quat_to_matrix, rotation_angle
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.sim.device_process import pick_attitudes
from ground.sim.sensor_sim import DetectorModel, render_frame
from ground.sim.sky_model import sky_stars
from protocol.result import Status

CAMERA = CameraModel.reference_design()


@pytest.fixture(scope="module")
def catalog():
    return build_catalog(CatalogDesign())


def _mono(pixels: np.ndarray) -> Frame:
    return Frame(pixels=pixels, pattern="MONO", black_level=0.0, white_level=65535.0)


def hot_pixel_frame(n: int = 500_000, seed: int = 29) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.normal(100, 3, (CAMERA.height, CAMERA.width)).clip(0).astype(np.uint16)
    idx = rng.choice(img.size, n, replace=False)
    img.flat[idx] = rng.integers(1000, 65535, n)
    return img


def blob_frame(n: int = 30_000, seed: int = 29) -> np.ndarray:
    rng = np.random.default_rng(seed)
    h, w = CAMERA.height, CAMERA.width
    img = np.pad(rng.normal(100, 3, (h, w)), 6)
    yy, xx = np.mgrid[-5:6, -5:6]
    for x, y, a in zip(rng.uniform(0, w, n), rng.uniform(0, h, n), 10 ** rng.uniform(2, 4.3, n)):
        cx, cy = int(round(x)), int(round(y))
        img[cy : cy + 11, cx : cx + 11] += a * np.exp(-((xx - (x - cx)) ** 2 + (yy - (y - cy)) ** 2) / 4.5)
    return img[5 : 5 + h, 5 : 5 + w].clip(0, 65535).astype(np.uint16)


def test_chance_answers_count_the_search_s_other_catalog_pairs():
    assert chance_answers(1.0, 1) == 0.0  # a two-star answer whose seed pair matched one catalog pair
    assert chance_answers(1.0, 2) == 1.0 <= CHANCE_ANSWERS  # one other pair as good: even odds, it stands
    assert chance_answers(1.0, 3) > CHANCE_ANSWERS  # two: more likely a coincidence
    assert chance_answers(1e-9, 50_000) < CHANCE_ANSWERS  # many stars beyond the pair decide
    e = np.empty(0, np.int64)
    both = PairCandidates(e, np.zeros(2, bool), np.array([3, 7]), np.array([7, 3]), np.zeros(2))
    assert pair_hypotheses([both]) == 1  # both assignments of one catalog pair: one hypothesis
    graded = PairCandidates(e, np.zeros(3, bool), np.array([3, 5, 9]), np.array([7, 6, 2]), np.array([0.5, 1.0, 2.0]))
    assert pair_hypotheses([graded], 1.0) == 2  # a pair that fits its seed worse than the answer's does not count


@pytest.mark.parametrize("make", [hot_pixel_frame, blob_frame], ids=["500k hot pixels", "30k blobs"])
def test_a_frame_without_stars_gets_no_attitude(catalog, make):
    out = run_pipeline(_mono(make()), CAMERA, catalog)
    assert out.status is Status.NO_MATCH
    assert out.solution is None or out.solution.q_icrs_to_sensor is None
    assert NOT_A_STAR_FIELD in out.reason


def test_a_star_field_with_hot_pixels_still_solves(catalog):
    rng = np.random.default_rng(8)
    a = pick_attitudes(catalog, CAMERA, 1, rng)[0]
    r = render_frame(sky_stars(), a, CAMERA, DetectorModel(pattern="MONO"), seed=5)
    pixels = np.array(r.frame.pixels)
    idx = rng.choice(pixels.size, 20_000, replace=False)
    pixels.flat[idx] = np.iinfo(pixels.dtype).max if pixels.dtype.kind == "u" else 65535
    frame = Frame(pixels=pixels, pattern="MONO", black_level=r.frame.black_level, white_level=r.frame.white_level)
    out = run_pipeline(frame, CAMERA, catalog)
    assert out.status is Status.OK
    assert np.degrees(rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), a)) < 0.01  # the true attitude


def saturated_hot_pixels(n: int, seed: int) -> np.ndarray:
    """Issue 40's frame: ``n`` hot pixels at full scale on a dark background."""
    rng = np.random.default_rng(seed)
    img = rng.normal(100, 3, (CAMERA.height, CAMERA.width)).clip(0).astype(np.uint16)
    img.flat[rng.choice(img.size, n, replace=False)] = 65535
    return img


@pytest.mark.parametrize("pattern", ["RGGB", "MONO"])
@pytest.mark.parametrize("n, seed", [(200_000, 1), (500_000, 1), (500_000, 2)])
def test_a_frame_of_saturated_hot_pixels_gets_no_attitude_in_either_pattern(catalog, pattern, n, seed):
    """Issue 40: an RGGB frame of saturated hot pixels got LOW_CONFIDENCE with a quaternion in 4 of
    5 seeds (a 3-star geometric match with a rival at another attitude); a MONO one NO_MATCH."""
    frame = Frame(pixels=saturated_hot_pixels(n, seed), pattern=pattern, black_level=0.0, white_level=65535.0)
    out = run_pipeline(frame, CAMERA, catalog)
    assert out.status is Status.NO_MATCH, (out.status, out.reason)
    assert out.solution is None or out.solution.q_icrs_to_sensor is None


def test_an_rggb_star_field_with_hot_pixels_still_solves(catalog):
    rng = np.random.default_rng(9)
    a = pick_attitudes(catalog, CAMERA, 1, rng)[0]
    r = render_frame(sky_stars(), a, CAMERA, DetectorModel(pattern="RGGB"), seed=6)
    pixels = np.array(r.frame.pixels)
    pixels.flat[rng.choice(pixels.size, 20_000, replace=False)] = 4095
    frame = Frame(pixels=pixels, pattern="RGGB", black_level=r.frame.black_level, white_level=r.frame.white_level)
    out = run_pipeline(frame, CAMERA, catalog)
    assert out.status is Status.OK, out.reason
    assert np.degrees(rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), a)) < 0.01
