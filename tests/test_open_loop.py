"""Open loop, with known truth: frames rendered with optics the solver is not told about.

The solver gets only what a user has: a distortion-free pinhole camera from the datasheet or
the field of view, and default settings. Covered: the PSF width measured per frame (and the
override), lost in space with the focal length off by 2.5 %, unmodelled distortion and a
principal-point offset (the focal search and the optics fit), planets labelled at the frame's
epoch, and bad frames that must give a clear status and never a confident wrong attitude.
"""

from dataclasses import replace

import numpy as np
import pytest
from open_loop_sky import NOMINAL, PIXEL_RAD, POINTINGS, open_loop_catalog, render

from firmware_model.camera import CameraModel
from firmware_model.pipeline.extract import (
    PSF_FAIL_FRACTION,
    ExtractParams,
    _Pass,
    extract_stars,
    failed_fit_fraction,
)
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.run import run_pipeline
from firmware_model.pipeline.solve_types import PipelineParams
from firmware_model.reference_frames import attitude_from_radec_roll, quat_to_matrix, rotation_angle, vec_to_radec
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.link.solve_report import record_from_output
from ground.sim.sensor_sim import DetectorModel, FalseObject, render_frame
from ground.sim.sky_model import sky_stars
from protocol.result import Status


@pytest.fixture(scope="module")
def catalog():
    return open_loop_catalog()


@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.5])
def test_psf_sigma_is_measured_on_the_frame(sigma):
    _, r = render(NOMINAL, POINTINGS[0], psf_sigma=sigma)
    stars = extract_stars(r.frame, NOMINAL)
    assert stars.psf_source == "measured" and 1 <= stars.psf_passes <= ExtractParams().psf_max_passes
    assert abs(stars.psf_measured_px / sigma - 1) < 0.15, (sigma, stars.psf_measured_px)
    assert abs(stars.psf_sigma_px / sigma - 1) < 0.25
    fixed = extract_stars(r.frame, NOMINAL, ExtractParams(psf_sigma_px=1.7))  # the override is obeyed
    assert fixed.psf_source == "setting" and fixed.psf_sigma_px == 1.7 and fixed.psf_passes == 1


def test_sharp_psf_with_a_wide_start_solves(catalog):
    """The tetra3 failure: a 0.5 px PSF against the 1 px start cleans star cores as hot pixels."""
    a, r = render(NOMINAL, POINTINGS[1], psf_sigma=0.5)
    out = run_pipeline(r.frame, NOMINAL, catalog)
    assert out.status is Status.OK, out.reason
    assert out.stars.psf_passes == 2
    assert rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), a) < 2 * PIXEL_RAD


def test_defocus_ring_among_hot_pixel_clusters_measures_a_wide_psf(catalog):
    """A 1 px guess on a defocus ring fails most star fits while 2x2/3x3 hot-pixel clusters converge
    near 0.8 px: the wide pass (PSF_WIDEN_FACTOR) must win, and the frame solve."""
    from ground.sim import openloop as ol

    rng = np.random.default_rng(5)
    hot, _ = ol.hot_clusters_e((NOMINAL.height, NOMINAL.width), 20, rng, e_range=(1000.0, 3000.0))
    a, r = render(NOMINAL, POINTINGS[0], seed=3, psf=ol.DonutPSF(4.0, 2.0, 0.5), extra_e=hot)
    fit, snr, _ = _Pass(r.frame, ExtractParams(), 1.0, None).result()
    assert failed_fit_fraction(fit, snr) > PSF_FAIL_FRACTION  # the failure this mechanism is for
    stars = extract_stars(r.frame, NOMINAL)
    assert stars.psf_sigma_px > 1.8, stars.psf_sigma_px
    out = run_pipeline(r.frame, NOMINAL, catalog)
    assert out.status is Status.OK, out.reason
    assert rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), a) < 2 * PIXEL_RAD


def centre_pointing_error_px(out, a_true, true_camera):
    """Angle (px) between the solved and the true direction of the nominal image centre."""
    v_true = a_true.T @ true_camera.pixel_to_vector(NOMINAL.cx, NOMINAL.cy)[0]
    v_est = quat_to_matrix(out.solution.q_icrs_to_sensor).T @ np.array([0.0, 0.0, 1.0])
    return float(np.arccos(np.clip(v_true @ v_est, -1, 1)) / PIXEL_RAD)


@pytest.mark.parametrize("pattern", ["MONO", "RGGB"])
def test_lost_in_space_with_datasheet_optics(catalog, pattern):
    """Focal length +2.5 %, k1 putting ~4 px at the corners, principal point (+15, -10) px."""
    true = replace(NOMINAL, f=NOMINAL.f * 1.025, cx=NOMINAL.cx + 15, cy=NOMINAL.cy - 10, k1=0.25)
    corner_px = np.hypot(*(np.array(true.vector_to_pixel(replace(true, k1=0.0).pixel_to_vector(0, 0)))[:, 0]))
    assert 2 < corner_px < 6  # the distortion this test claims
    for k, pointing in enumerate(POINTINGS):
        a, r = render(true, pointing, seed=10 + k, pattern=pattern)
        calibrated_only = run_pipeline(r.frame, NOMINAL, catalog, replace(PipelineParams(), optics=None))
        assert calibrated_only.status is not Status.OK  # what the search is for
        out = run_pipeline(r.frame, NOMINAL, catalog)
        assert out.status is Status.OK, (pointing, out.reason)
        assert centre_pointing_error_px(out, a, true) < 1.0
        fit = out.optics
        assert fit is not None and np.isfinite(fit.focal_scale) and fit.n_stars >= 8
        assert abs(fit.camera.f / true.f - 1) < 0.003 and fit.sigmas["f"] < 0.002 * true.f
        rec = record_from_output(out)
        assert rec["optics"]["fitted"] and rec["optics"]["searched"]
        assert rec["optics"]["focal_sigma_px"] > 0 and abs(rec["optics"]["focal_px"] - fit.camera.f) < 0.01


def test_four_stars_in_opposite_corners_of_a_wide_field_solve():
    """The open-loop bench's sparse coma frame: only 4 catalog stars (V <= 5) in a 20 x 15 deg field,
    at opposite corners (2 360 px apart), their centroids moved 0.6-1 px by coma the solver does
    not model. No catalog pattern within 1.5 half-fields of a star spans them (that radius alone
    returned a 2-star low-confidence wrong answer); the 2 half-field radius does."""
    from ground.sim import openloop as ol

    camera = CameraModel.reference_design()
    a = attitude_from_radec_roll(*np.radians([72.963, -49.661, 3.976]))
    psf = ol.ComaPSF(1.0, 1.3, camera.cx, camera.cy, ol.corner_radius_px(camera))
    r = render_frame(sky_stars(), a, camera, DetectorModel(pattern="MONO"), seed=2, psf=psf)
    out = run_pipeline(r.frame, camera, build_catalog(CatalogDesign()))
    assert out.status is Status.OK, out.reason
    assert len(out.solution.matched_det) == 4
    assert np.degrees(rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), a)) * 3600 < 20.0


def test_planet_on_the_frame_is_labelled_and_not_matched(catalog):
    from firmware_model.pipeline.planets import body_positions

    epoch = "2023-11-03T04:00:00"  # Jupiter at opposition
    jupiter = body_positions(epoch)["jupiter"].direction
    ra, dec = np.degrees(vec_to_radec(jupiter))
    a = attitude_from_radec_roll(np.radians(ra + 2.0), np.radians(dec - 1.0), 0.3)
    x, y = NOMINAL.vector_to_pixel(a @ jupiter)
    assert NOMINAL.in_frame(x, y, margin=20)
    det = DetectorModel(pattern="MONO", aperture_mm=18.0)
    planet = FalseObject("planet", float(x[0]), float(y[0]), float(det.green_electrons(-2.9)))
    r = render_frame(sky_stars(7.0), a, NOMINAL, det, seed=3, false_objects=[planet], timestamp=epoch + "Z")
    out = run_pipeline(r.frame, NOMINAL, catalog)
    assert out.status is Status.OK, out.reason
    assert rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), a) < 2 * PIXEL_RAD
    labelled = [lab for lab in out.planets if lab.body == "jupiter"]
    assert len(labelled) == 1 and labelled[0].distance_px < 2
    row = labelled[0].index
    assert np.hypot(out.stars.x[row] - x[0], out.stars.y[row] - y[0]) < 1
    assert row not in out.used[out.solution.matched_det]
    rec = record_from_output(out)
    assert rec["n_planets"] == 1 and [s["body"] for s in rec["stars"] if s["body"]] == ["jupiter"]
    no_time = run_pipeline(replace(r.frame, timestamp=None), NOMINAL, catalog)  # no epoch: nothing predicted
    assert no_time.planets == [] and record_from_output(no_time)["n_planets"] == 0


def bad_frames():
    rng = np.random.default_rng(4)
    noise = np.clip(np.round(100 + 5 * rng.standard_normal((768, 1024))), 0, 4095).astype(np.uint16)
    yield "blank", Frame(np.full((768, 1024), 100, np.uint16), black_level=64)
    yield "saturated", Frame(np.full((768, 1024), 4095, np.uint16), black_level=64)
    yield "pure noise", Frame(noise, black_level=64)
    # a real star field from a camera with twice the field of view of the configured one
    _, r = render(CameraModel.from_horizontal_fov(1024, 768, 22.8), POINTINGS[0])
    yield "other camera", r.frame


@pytest.mark.parametrize("name,frame", list(bad_frames()))
def test_bad_frames_get_a_status_never_a_confident_answer(catalog, name, frame):
    out = run_pipeline(frame, NOMINAL, catalog)
    assert out.status is not Status.OK, name
    assert out.reason, name
    assert out.timings.total < 10.0  # bounded by the search budget, not a hang


def test_search_goes_before_the_mono_consensus_with_the_nominal_camera(catalog, monkeypatch):
    """When the nominal camera finds nothing, the optics search's pattern hypotheses run
    before the mono consensus fallback with that camera, which is not run when the search answers."""
    from firmware_model.pipeline import frame_identification, run

    calls = []

    def fallback(*args, **kw):
        calls.append(args)
        return original(*args, **kw)

    original = frame_identification.geometric_fallback
    monkeypatch.setattr(frame_identification, "geometric_fallback", fallback)
    true = replace(NOMINAL, f=NOMINAL.f * 1.025, k1=0.25)
    a, r = render(true, POINTINGS[0], seed=10)
    out = run_pipeline(r.frame, NOMINAL, catalog)
    assert out.status is Status.OK and np.isfinite(out.optics.focal_scale) and not calls
    assert centre_pointing_error_px(out, a, true) < 1.0
    monkeypatch.setattr(run, "search_optics", lambda *args: None)  # a search that finds nothing
    run_pipeline(r.frame, NOMINAL, catalog)
    assert len(calls) == 1  # then the deferred fallback runs


def test_flight_timing_stops_the_search_and_the_result_says_so(catalog):
    """Datasheet optics (focal length +2.5 %): the optics search runs. With counted budgets alone the
    frame solves; with a flight-timing deadline already past when the search starts, the search
    stops before its first seed and the answer says the deadline was missed (reason, search flag)."""
    from firmware_model.ident.budget import Stop
    from firmware_model.pipeline.result_fields import result_fields
    from protocol import result

    true = replace(NOMINAL, f=NOMINAL.f * 1.025)
    _, r = render(true, POINTINGS[0], seed=10)
    counted = run_pipeline(r.frame, NOMINAL, catalog)
    assert counted.status is Status.OK and counted.stopped is Stop.NONE
    assert result_fields(counted)["ext.search_flags"] == 0 and counted.timings.seeds >= 1
    late = run_pipeline(r.frame, NOMINAL, catalog, replace(PipelineParams(), flight_deadline_s=0.0))
    assert late.stopped is Stop.DEADLINE
    assert late.reason.startswith("flight-timing deadline missed")
    assert result_fields(late)["ext.search_flags"] == result.DEADLINE_MISSED
    assert record_from_output(late)["search"]["deadline_missed"]
