"""Detector effects over a mission: the models' numbers (hit rate, track charge, hot pixels with
dose, dark current with temperature, the SAA) and a short rendered run with hits on."""

import math

import numpy as np
import pytest
from scipy.optimize import brentq, minimize_scalar
from scipy.stats import landau

from firmware_model.camera import CameraModel
from firmware_model.device.housekeeping import DETECTOR
from ground.sim import detector_effects as de
from ground.sim.availability import AvailabilityConfig, frame_attitude, render_with_effects, run_availability, summarise
from ground.sim.sensor_sim import DetectorModel, FalseObject, Stars, fixed_pattern, render_frame

REF = CameraModel.reference_design()
SMALL = CameraModel.from_fov(320, 240, 2.0)
QUIET = dict(prnu=0.0, dsnu_e=0.0, hot_pixel_fraction=0.0, read_noise_e=0.0, sky_e_per_s=0.0, dark_e_per_s=0.0)


def _no_stars():
    return Stars(np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0))


def test_hits_per_frame_are_poisson_with_mean_flux_times_area_times_exposure():
    det = DetectorModel()
    area = de.sensitive_area_cm2(det, REF)
    assert area == pytest.approx(2592 * 1944 * (2.2e-4) ** 2)  # the MT9P031's 5.70 x 4.28 mm array
    rays = de.CosmicRays(flux_cm2_s=100.0)
    expected = 100.0 * area * det.exposure_s  # 2.44 hits
    assert rays.mean_hits(det, REF) == pytest.approx(expected)
    n = np.array([len(rays.tracks(det, REF, np.random.default_rng(s))[0]) for s in range(3000)])
    # the sample mean of 3000 Poisson draws has a standard error sqrt(mean / 3000) = 0.029; 5 of them
    assert abs(n.mean() - expected) < 5 * math.sqrt(expected / len(n))
    assert abs(n.var() - expected) < 0.15 * expected  # Poisson: variance equals the mean
    fixed = de.CosmicRays(flux_cm2_s=100.0, hits_per_frame=7.0)
    assert fixed.mean_hits(det, REF) == 7.0  # a fixed mean wins over the flux


@pytest.mark.parametrize("bad", [dict(flux_cm2_s=-1.0), dict(hits_per_frame=-0.5), dict(flux_cm2_s=float("nan"))])
def test_negative_rates_are_refused(bad):
    with pytest.raises(ValueError, match="at least 0|from 0 to"):
        de.CosmicRays(**bad)


def test_landau_constants_are_scipys():
    mode = minimize_scalar(lambda x: -landau.pdf(x), bracket=(-1, 0, 1)).x
    half = landau.pdf(mode) / 2
    fwhm = brentq(lambda x: landau.pdf(x) - half, mode, mode + 20) - brentq(
        lambda x: landau.pdf(x) - half, mode - 10, mode
    )
    assert de.LANDAU_MODE == pytest.approx(mode, abs=1e-3)
    assert de.LANDAU_FWHM == pytest.approx(fwhm, abs=1e-3)


def test_track_geometry_and_charge():
    det = DetectorModel()
    # without spread, the charge is exactly e_per_um x the path through the sensitive depth
    flat = de.CosmicRays(hits_per_frame=400.0, charge_fwhm_fraction=0.0)
    _, rows = flat.tracks(det, REF, np.random.default_rng(5))
    path = np.array([r["path_um"] for r in rows])
    length = np.array([math.hypot(r["x2"] - r["x"], r["y2"] - r["y"]) for r in rows])
    theta = np.radians([r["incidence_deg"] for r in rows])
    assert np.allclose(path, de.SENSITIVE_DEPTH_UM / np.cos(theta))
    assert np.allclose(length, de.SENSITIVE_DEPTH_UM * np.tan(theta) / det.pixel_pitch_um)
    short = length < math.hypot(REF.width, REF.height)
    assert np.allclose(np.array([r["electrons"] for r in rows])[short], de.MIP_E_PER_UM * path[short])
    # plane crossings of an isotropic flux: cos(theta)^2 is uniform on (0, 1], its mean 1/2
    assert np.mean(np.cos(theta) ** 2) == pytest.approx(0.5, abs=5 * math.sqrt(1 / 12 / len(theta)))
    # with the Landau spread, the most probable charge per um stays at e_per_um
    spread = de.CosmicRays(hits_per_frame=4000.0)
    _, rows = spread.tracks(det, REF, np.random.default_rng(6))
    ratio = np.array([r["electrons"] / r["path_um"] for r in rows if r["path_um"] < 50]) / de.MIP_E_PER_UM
    hist, edges = np.histogram(ratio, bins=np.arange(0.0, 3.0, 0.05))
    peak = 0.5 * (edges[np.argmax(hist)] + edges[np.argmax(hist) + 1])
    assert peak == pytest.approx(1.0, abs=0.1)
    assert ratio.max() == pytest.approx(de.CHARGE_CAP)  # the Landau tail reaches the cap (1.5 % of tracks)


@pytest.mark.parametrize("diffusion", [0.0, 0.5, 1.5])
def test_a_rendered_track_holds_its_charge_and_spreads_by_the_diffusion(diffusion):
    det = DetectorModel(**QUIET)
    obj = FalseObject("cosmic", 100.3, 120.6, 2000.0, x2=130.8, y2=101.2, diffusion_px=diffusion)
    e = render_frame(_no_stars(), np.eye(3), SMALL, det, seed=1, false_objects=[obj]).electrons
    assert e.sum() == pytest.approx(2000.0, rel=1e-6)  # the stamp reaches 4 sigma + 1 px
    width = np.count_nonzero(e > 1e-3 * e.max())
    assert width > 31 if diffusion == 0 else width > 31 * (1 + 2 * diffusion)  # 31 px long, wider when diffused
    off = FalseObject("cosmic", 310.0, 120.0, 1000.0, x2=330.0, y2=120.0, diffusion_px=diffusion)
    e = render_frame(_no_stars(), np.eye(3), SMALL, det, seed=1, false_objects=[off]).electrons
    assert 0.4 * 1000 < e.sum() < 0.6 * 1000  # half of it ran off the array


def test_tracks_are_deterministic_per_seed():
    fx = de.MissionEffects(cosmic=de.CosmicRays(hits_per_frame=20.0), dose_krad=1.0)
    a = fx.render_inputs(np.eye(3), REF, DetectorModel(), np.random.default_rng(11))
    b = fx.render_inputs(np.eye(3), REF, DetectorModel(), np.random.default_rng(11))
    c = fx.render_inputs(np.eye(3), REF, DetectorModel(), np.random.default_rng(12))
    assert a.truth == b.truth and np.array_equal(a.extra_e, b.extra_e)
    assert a.truth["cosmic"]["tracks"] != c.truth["cosmic"]["tracks"]
    assert np.array_equal(a.extra_e, c.extra_e)  # the dose's hot pixels belong to the sensor, not the frame


def test_hot_pixels_grow_with_dose_and_stay_hot():
    det = DetectorModel()
    shape = (REF.height, REF.width)
    sets = [set(de.dose_hot_pixels(det, shape, d).tolist()) for d in (0.0, 1.0, 2.0, 5.0)]
    assert sets[0] == set()
    assert sets[1] <= sets[2] <= sets[3]  # a pixel hot at 1 krad stays hot at 2 and 5 krad
    n = shape[0] * shape[1]
    for dose, got in zip((1.0, 2.0, 5.0), sets[1:]):
        p = de.hot_pixel_fraction(dose)
        assert p == pytest.approx(de.HOT_FRACTION_PER_KRAD * dose)
        assert abs(len(got) - n * p) < 5 * math.sqrt(n * p)  # binomial count, 5 sigma
    assert not sets[3] & set(fixed_pattern(det, shape)[2].tolist())  # beyond the fixed hot pixels
    other = set(de.dose_hot_pixels(DetectorModel(sensor_seed=2), shape, 5.0).tolist())
    assert other != sets[3]  # another sensor, other pixels
    with pytest.raises(ValueError, match="at least 0"):
        de.hot_pixel_fraction(-1.0)
    # rendered: the new hot pixels carry the detector's hot-pixel rate over the exposure
    inp = de.MissionEffects(dose_krad=2.0).render_inputs(np.eye(3), REF, det, np.random.default_rng(0))
    hot = np.flatnonzero(inp.extra_e)
    assert set(hot.tolist()) == sets[2]
    assert np.all(inp.extra_e.ravel()[hot] == det.hot_pixel_e_per_s * det.exposure_s)


def test_dark_current_doubles_every_doubling_step():
    ref = DetectorModel().dark_e_per_s
    assert de.REFERENCE_C == 20.0  # the housekeeping model's idle detector
    assert de.dark_e_per_s(de.REFERENCE_C) == pytest.approx(ref)
    assert de.dark_e_per_s(de.REFERENCE_C + de.DARK_DOUBLING_C) == pytest.approx(2 * ref)
    assert de.dark_e_per_s(de.REFERENCE_C - 2 * de.DARK_DOUBLING_C) == pytest.approx(ref / 4)
    det = de.MissionEffects(temperature_c=de.REFERENCE_C + de.DARK_DOUBLING_C).detector_for(DetectorModel())
    assert det.dark_e_per_s == pytest.approx(2 * ref)
    assert det.hot_pixel_e_per_s == pytest.approx(2 * DetectorModel().hot_pixel_e_per_s)
    with pytest.raises(ValueError, match="from -40 to 85 degC"):
        de.MissionEffects(temperature_c=120.0)


def test_detector_temperature_from_the_housekeeping_node():
    idle, busy = 20.0 + DETECTOR.idle_rise_c, 20.0 + DETECTOR.busy_rise_c
    assert de.detector_temperature_c(0.0) == pytest.approx(idle)
    assert de.detector_temperature_c(1.0) == pytest.approx(busy)
    assert de.detector_temperature_c(0.5) == pytest.approx(0.5 * (idle + busy))
    assert de.detector_temperature_c(1.0, elapsed_s=0.0) == pytest.approx(idle)
    after_tau = idle + (busy - idle) * (1 - math.exp(-1))
    assert de.detector_temperature_c(1.0, elapsed_s=DETECTOR.tau_s) == pytest.approx(after_tau)
    fx = de.MissionEffects(duty=1.0)
    assert fx.detector_for(DetectorModel()).dark_e_per_s == pytest.approx(de.dark_e_per_s(busy))
    with pytest.raises(ValueError, match="duty"):
        de.MissionEffects(duty=1.5)


def test_saa_raises_the_flux_inside_and_not_outside():
    saa = de.SouthAtlanticAnomaly()
    assert saa.contains(-25.0, -45.0) and saa.contains(-30.0, -70.0)
    assert not saa.contains(50.0, -30.0) and not saa.contains(-25.0, 100.0) and not saa.contains(-25.0, 315.0 + 50)
    assert saa.contains(-25.0, 315.0)  # longitude wraps: 315 E is 45 W
    rays = de.CosmicRays(flux_cm2_s=4.0, saa=saa)
    det = DetectorModel()
    outside = rays.mean_hits(det, REF, (50.0, 0.0))
    inside = rays.mean_hits(det, REF, (-25.0, -45.0))
    assert outside == pytest.approx(rays.mean_hits(det, REF))  # no position: the base flux
    assert inside == pytest.approx(outside * saa.flux_cm2_s / 4.0)
    assert saa.flux_at(-25.0, -45.0, 4.0) == saa.flux_cm2_s and saa.flux_at(50.0, 0.0, 4.0) == 4.0


def test_subsatellite_point_round_trips_through_astropy():
    import astropy.units as u
    from astropy.coordinates import GCRS, ITRS, EarthLocation
    from astropy.time import Time

    t = Time("2026-06-01T03:00:00", scale="utc")
    loc = EarthLocation.from_geodetic(-45.0 * u.deg, -25.0 * u.deg, 550.0 * u.km)
    gcrs = ITRS(loc.get_itrs(obstime=t).cartesian, obstime=t).transform_to(GCRS(obstime=t))
    lat, lon, height = de.subsatellite_point(gcrs.cartesian.xyz.to_value(u.km), float(t.unix))
    assert (lat, lon, height) == pytest.approx((-25.0, -45.0, 550.0), abs=1e-6)


def test_mission_effects_on_an_orbit_see_the_saa_under_the_spacecraft():
    from ground.sim.orbit import CircularOrbit

    orbit = CircularOrbit(550.0)
    fx = de.MissionEffects(cosmic=de.CosmicRays(flux_cm2_s=4.0, saa=de.SouthAtlanticAnomaly()), orbit=orbit)
    for t in orbit.epoch_posix + np.array([0.0, 1500.0, 3000.0]):
        inp = fx.at_time(t).render_inputs(np.eye(3), REF, DetectorModel(), np.random.default_rng(0))
        where = inp.truth["subsatellite_deg"]
        assert inp.truth["cosmic"]["in_saa"] == de.SouthAtlanticAnomaly().contains(*where)
        assert inp.timestamp is not None and inp.timestamp.endswith("Z")
        assert "sc_position_km" not in inp.metadata and len(inp.truth["sc_position_km"]) == 3


def test_short_run_with_hits_has_no_confident_wrong_answer_and_the_tracks_are_in_the_frame():
    from ground.sim.sky_model import sky_stars

    fx = de.MissionEffects(cosmic=de.CosmicRays(hits_per_frame=50.0))
    rows = run_availability(AvailabilityConfig(3, seed=4), [fx])
    s = summarise(rows)
    assert s["high_confidence_wrong"] == 0
    assert s["mean_hits_per_frame"] > 30  # Poisson(50) three times
    assert s["correct"] >= 1
    # the tracks are in the pixels: the frame with hits minus the same frame without (same noise seed)
    a = frame_attitude(4, 0)
    det = DetectorModel()
    with_hits = render_with_effects(sky_stars(), a, REF, det, [fx], np.random.default_rng(1), 7)
    without = render_with_effects(sky_stars(), a, REF, det, [], np.random.default_rng(1), 7)
    tracks = with_hits.truth["effects"][0]["cosmic"]["tracks"]
    assert with_hits.frame.timestamp is None and len(tracks) > 30  # no orbit: no time
    extra = with_hits.electrons - without.electrons
    inside = [t for t in tracks if 0 <= min(t["x"], t["x2"]) and max(t["x"], t["x2"]) < REF.width - 1]
    inside = [t for t in inside if 0 <= min(t["y"], t["y2"]) and max(t["y"], t["y2"]) < REF.height - 1]
    assert 0.99 * sum(t["electrons"] for t in inside) <= extra.sum() <= sum(t["electrons"] for t in tracks) + 1e-6
    diff = with_hits.frame.pixels.astype(int) - without.frame.pixels.astype(int)
    for t in inside:
        r, c = round(0.5 * (t["y"] + t["y2"])), round(0.5 * (t["x"] + t["x2"]))
        assert diff[r - 1 : r + 2, c - 1 : c + 2].max() > 10  # DN: at least ~16 e- above the same frame
