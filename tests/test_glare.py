"""Bright bodies in the rendered sky (ground.sim.glare; issue 33): the Moon's disc is not taken
for stars, stray light is a gradient that follows the baffle's PST, the Sun in the field saturates
the frame, the Earth's limb needs a position, the device's sources stamp the exposure's time and
position, and frames with no body near are unchanged."""

from __future__ import annotations

import hashlib
import math
from types import SimpleNamespace

import numpy as np
import pytest
from astropy.time import Time

from firmware_model.camera import CameraModel
from firmware_model.pipeline.detect import detect_stars
from firmware_model.pipeline.extract import extract_stars
from firmware_model.reference_frames import attitude_from_radec_roll, rotation_angle, vec_to_radec
from ground.sim import glare as glare_mod
from ground.sim.exposure import ExposureRenderer
from ground.sim.feed_wire import Sample, decode_json, encode_json
from ground.sim.glare import PST, Glare, exposure_start
from ground.sim.noise_bank import NoiseBank
from ground.sim.orbit import CircularOrbit
from ground.sim.sensor_sim import DetectorModel, random_star_field, render_frame
from ground.sim.sky_source import SkySource, read_schedule
from protocol.star_flags import UNTRUSTED

CAMERA = CameraModel.reference_design()
DET = DetectorModel()
#: Epochs of the Moon at lit fractions 0.25, 0.5 and full (2026-03-03 is a total lunar eclipse: not used)
MOON_PHASES = {0.25: "2026-03-23T12:00:00", 0.5: "2026-03-25T18:00:00", 1.0: "2026-04-02T02:00:00"}
MOON_MARGIN_PX = 10.0  #: no detection within the disc's radius plus this


def _pointing(target: np.ndarray, dx_px: float, dy_px: float, roll: float = 0.4) -> np.ndarray:
    """Attitude putting the unit vector ``target`` at about (cx + dx, cy + dy)."""
    a = attitude_from_radec_roll(*vec_to_radec(target), roll)
    b = CAMERA.pixel_to_vector(CAMERA.cx - dx_px, CAMERA.cy - dy_px)[0] @ a  # boresight moved the other way
    return attitude_from_radec_roll(*vec_to_radec(b), roll)


def _off_axis(target: np.ndarray, angle_deg: float) -> np.ndarray:
    """Attitude whose boresight lies ``angle_deg`` from ``target``, ``target`` toward +x (image right)."""
    perp = np.cross(target, [0.0, 0.0, 1.0])
    perp /= np.linalg.norm(perp)
    t = math.radians(angle_deg)
    b = math.cos(t) * target + math.sin(t) * perp
    a = attitude_from_radec_roll(*vec_to_radec(b), 0.0)
    s = a @ target
    roll = math.atan2(s[1], s[0])  # turn the sensor so the target lies along +x
    return attitude_from_radec_roll(*vec_to_radec(b), roll)


@pytest.mark.parametrize("lit", sorted(MOON_PHASES))
def test_the_moons_disc_is_not_taken_for_stars(lit):
    g = Glare(MOON_PHASES[lit])
    moon = g.bodies["moon"]
    a = _pointing(moon.direction, 310.0, -170.0)
    truth = g.truth(a, CAMERA, DET)["moon"]
    assert truth["lit_fraction"] == pytest.approx(lit, abs=0.01)
    assert truth["in_field"] and truth["disc_peak_e"] > 10 * DET.full_well_e  # a saturated disc
    stars = random_star_field(CAMERA, a, 80, vmag_range=(2.0, 6.0), seed=11, min_separation_px=30)
    frame = render_frame(stars, a, CAMERA, DET, seed=3, background_e=g.background_e(a, CAMERA, DET)).frame
    found = extract_stars(frame, CAMERA)
    (x0,), (y0,) = CAMERA.vector_to_pixel(a @ moon.direction)
    radius_px = moon.angular_radius * CAMERA.f
    assert np.hypot(found.x - x0, found.y - y0).min() > radius_px + MOON_MARGIN_PX
    # the stars away from the Moon are found as without it
    sx, sy = CAMERA.vector_to_pixel(stars.vectors @ a.T)
    away = np.hypot(sx - x0, sy - y0) > radius_px + 60.0
    plain = extract_stars(render_frame(stars, a, CAMERA, DET, seed=3).frame, CAMERA)

    def hits(sl):
        return sum(np.hypot(sl.x - x, sl.y - y).min() < 1.0 for x, y in zip(sx[away], sy[away]))

    assert hits(found) >= hits(plain) - 2 and hits(plain) > 40
    assert detect_stars(frame).n_rejected_extended >= 1


@pytest.fixture(scope="module")
def catalog():
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    return build_catalog(CatalogDesign())


def test_a_frame_with_the_moon_beside_the_stars_still_solves(catalog):
    from firmware_model.pipeline.run import run_pipeline
    from ground.sim.sky_model import sky_stars

    epoch = MOON_PHASES[0.5]
    g = Glare(epoch)
    a = _pointing(g.bodies["moon"].direction, -600.0, 250.0)
    # no timestamp: neither the device's exclusion check nor the planet labels (a lookup of the
    # Moon's place) run; detection alone keeps the disc out
    frame = render_frame(sky_stars(), a, CAMERA, DET, seed=5, background_e=g.background_e(a, CAMERA, DET)).frame
    assert g.truth(a, CAMERA, DET)["moon"]["in_field"]
    out = run_pipeline(frame, CAMERA, catalog)
    assert out.solution is not None and out.solution.q_icrs_to_sensor is not None
    from firmware_model.reference_frames import quat_to_matrix

    assert math.degrees(rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), a)) * 3600 < 30.0


def test_stray_light_rises_toward_the_body_and_follows_the_pst():
    g = Glare(MOON_PHASES[0.5])
    sun = g.bodies["sun"].direction
    ratio = (DET.pixel_pitch_um * 1e-3) ** 2 / (math.pi * (DET.aperture_mm / 2) ** 2)
    sun_e = g._irradiance_e(DET)["sun"]
    means = []
    for angle in (20.0, 30.0, 40.0):
        a = _off_axis(sun, angle)
        bg = g.background_e(a, CAMERA, DET)
        assert not g.truth(a, CAMERA, DET)["sun"]["in_field"]
        # along the row through the centre, green sites (RGGB: even row, odd column) brighten toward the Sun (+x)
        row = bg[972, 1::2]
        assert np.all(np.diff(row) > 0)
        # each pixel holds the Sun's irradiance times the PST at its own angle (Moon's light aside)
        for col in (1, 1295, 2591):
            v = CAMERA.pixel_to_vector(col, 972)[0] @ a
            expect = sun_e * ratio * float(g.pst(math.acos(float(v @ sun))))
            assert bg[972, col] == pytest.approx(expect, rel=0.05)
        means.append(float(bg[1::2, 0::2].mean()))  # red-free: the green sites of odd rows (GB rows)
    assert means[0] > means[1] > means[2] > 0
    pst = PST()
    assert means[0] / means[1] == pytest.approx(float(pst(math.radians(20)) / pst(math.radians(30))), rel=0.5)


def test_stray_light_near_the_sun_is_a_gradient_detection_does_not_take_for_stars():
    g = Glare(MOON_PHASES[0.5])
    a = _off_axis(g.bodies["sun"].direction, 28.0)
    bg = g.background_e(a, CAMERA, DET)
    assert bg.max() > 1000 * bg.min() > 0  # a strong gradient across the field
    stars = random_star_field(CAMERA, a, 40, vmag_range=(2.0, 5.0), seed=2, min_separation_px=30)
    sx, sy = CAMERA.vector_to_pixel(stars.vectors @ a.T)

    def counts(background):
        found = extract_stars(render_frame(stars, a, CAMERA, DET, seed=4, background_e=background).frame, CAMERA)
        clean = (found.flags & int(UNTRUSTED)) == 0
        near = np.array([np.nanmin(np.hypot(sx - x, sy - y)) < 1.0 for x, y in zip(found.x, found.y)])
        return int(np.count_nonzero(near)), int(np.count_nonzero(clean & ~near))

    (real, fake), (real0, fake0) = counts(bg), counts(None)
    assert real0 == 40 and real >= real0 - 2  # the stars survive the gradient
    assert fake <= fake0 + 3  # and it gives few trusted detections of its own (noise near threshold)


def test_the_sun_in_the_field_saturates_the_frame():
    g = Glare(MOON_PHASES[0.5])
    a = _pointing(g.bodies["sun"].direction, 200.0, 100.0)
    truth = g.truth(a, CAMERA, DET)["sun"]
    assert truth["in_field"] and truth["disc_peak_e"] > 1e6 * DET.full_well_e
    frame = render_frame(
        random_star_field(CAMERA, a, 20, seed=1), a, CAMERA, DET, seed=2, background_e=g.background_e(a, CAMERA, DET)
    ).frame
    assert np.mean(frame.pixels >= frame.white_level) > 0.9
    assert len(detect_stars(frame)) == 0  # saturated (or uniformly white): no candidate


def test_the_earths_limb_appears_with_a_position_and_not_without():
    epoch = MOON_PHASES[0.5]
    sun = Glare(epoch).bodies["sun"].direction
    r = (6378.137 + 550.0) * sun  # above the sub-solar point: the whole visible Earth is daylit
    lit = Glare(epoch, r)
    earth = lit.bodies["earth"]
    # the boresight 2 deg above the limb, the limb toward +x: the field's edge dips below it
    a = _off_axis(earth.direction, math.degrees(earth.angular_radius) + 2.0 + 7.5)
    a = _off_axis(earth.direction, math.degrees(earth.angular_radius) + 8.0)
    with_pos = lit.background_e(a, CAMERA, DET)
    truth = lit.truth(a, CAMERA, DET)
    assert truth["earth"]["in_field"] and truth["earth"]["disc_peak_e"] > DET.full_well_e
    assert with_pos[:, -20:].min() > DET.full_well_e  # the limb side is saturated
    assert with_pos[:, :20].max() < DET.full_well_e  # the sky side is not
    dark = Glare(epoch)
    assert "earth" not in dark.bodies and "earth" not in dark.truth(a, CAMERA, DET)
    assert dark.background_e(a, CAMERA, DET).max() < 1.0


def test_nothing_near_leaves_frames_byte_identical():
    # frames without background_e are those of the code before it (sha256 of the pixels)
    cam = CameraModel.pinhole(256, 192, 400.0)
    stars = random_star_field(cam, np.eye(3), 20, seed=3)
    plain = render_frame(stars, np.eye(3), cam, DetectorModel(), seed=5)
    assert hashlib.sha256(plain.frame.pixels.tobytes()).hexdigest().startswith("030f1735d4e7db14")
    bank = NoiseBank(DetectorModel(), (192, 256), seed=2)
    banked = render_frame(stars, np.eye(3), cam, DetectorModel(), seed=5, noise=bank)
    assert hashlib.sha256(banked.frame.pixels.tobytes()).hexdigest().startswith("9e2cbeb98bb6d3a1")
    # the Sun and the Moon far from the boresight: no glare above the floor, the same frame
    g = Glare(MOON_PHASES[0.5])
    a = _off_axis(g.bodies["sun"].direction, 120.0)
    assert math.degrees(math.acos(float(a[2] @ g.bodies["moon"].direction))) > 60.0
    assert not g.background_e(a, CAMERA, DET).any()
    renderer = ExposureRenderer(CAMERA)
    with_glare = renderer.render(a, DET, 7, epoch_utc=MOON_PHASES[0.5])
    without = renderer.render(a, DET, 7)
    assert np.array_equal(with_glare.pixels, without.pixels)
    # the timestamp is the exposure's start, the epoch its mid-time (docs/CONVENTIONS.md)
    assert with_glare.timestamp == exposure_start(MOON_PHASES[0.5], DET.exposure_s) and without.timestamp is None


def test_sky_schedule_stamps_time_and_position(tmp_path):
    q = "0.5,0.5,0.5,0.5"
    path = tmp_path / "s.csv"
    path.write_text(
        "# orbit: 550,97.6,10,0,2026-03-25T18:00:00\n"
        "qw,qx,qy,qz,time,x_km,y_km,z_km\n"
        f"{q},2026-03-25T18:00:00,7000,0,0\n"
        f"{q},2026-03-25T18:10:00,,,\n"
        f"{q},,,,\n"
    )
    rows = read_schedule(path)
    assert rows[0].time_utc == "2026-03-25T18:00:00.000" and list(rows[0].position_km) == [7000.0, 0.0, 0.0]
    assert rows[1].position_km is None and rows[2].time_utc is None
    src = SkySource(str(path), CAMERA)
    src.ready()
    go = float(Time("2026-03-25T19:00:00", scale="utc").unix)
    frames = [src(SimpleNamespace(started=go, sequence=k)) for k in range(3)]
    assert [f.timestamp for f in frames] == [
        "2026-03-25T18:00:00.000",
        "2026-03-25T18:10:00.000",
        "2026-03-25T19:00:00.000",
    ]
    assert frames[0].metadata["sc_position_km"] == [7000.0, 0.0, 0.0]
    orbit = CircularOrbit.parse("550,97.6,10,0,2026-03-25T18:00:00")
    for f, t in ((frames[1], "2026-03-25T18:10:00.05"), (frames[2], "2026-03-25T19:00:00.05")):
        expect = orbit.position_gcrs_km(float(Time(t, scale="utc").unix))
        assert f.metadata["sc_position_km"] == pytest.approx(list(expect), abs=1e-6)
        assert set(f.metadata["glare"]) >= {"sun", "moon", "earth"}


@pytest.mark.parametrize(
    "text, msg",
    [
        ("qw,qx,qy,qz,time\n1,0,0,0,yesterday\n", "row 1: time 'yesterday' is not ISO-8601 UTC"),
        ("qw,qx,qy,qz,x_km,y_km,z_km\n1,0,0,0,7000,0,\n", "row 1: position needs all of x_km, y_km, z_km"),
        ("qw,qx,qy,qz,x_km,y_km,z_km\n1,0,0,0,6000,0,0\n", "row 1: position 6000 km from the geocentre is inside"),
        ("# orbit: 50\nqw,qx,qy,qz\n1,0,0,0\n", "line 1: orbit altitude 50 km is outside"),
    ],
)
def test_bad_schedule_times_positions_and_orbits_are_one_line_errors(tmp_path, text, msg):
    path = tmp_path / "s.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=msg.replace("(", r"\(")) as info:
        SkySource(str(path), CAMERA)
    assert "\n" not in str(info.value)


def test_feed_sample_position_round_trips_in_json():
    s = Sample(1.79e9, np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([7000.0, 1.5, -2.0]))
    back = decode_json(encode_json(s))
    assert list(back.r) == [7000.0, 1.5, -2.0]
    plain = decode_json(encode_json(Sample(1.79e9, np.array([1.0, 0, 0, 0]), np.zeros(3))))
    assert plain.r is None and b'"r"' not in encode_json(plain)


def test_the_floor_and_grid_are_what_the_docs_say():
    assert glare_mod.FLOOR_E == 0.01 and glare_mod.GRID_PX == 64
    assert PST()(math.radians(35.0)) == pytest.approx(1e-8)


def test_glare_is_an_effect_of_the_availability_run():
    from ground.sim.availability import render_with_effects

    orbit = CircularOrbit.parse("550,97.6,10,0,2026-03-25T18:00:00")
    g = Glare(MOON_PHASES[0.5], orbit=orbit).at_time(float(Time("2026-03-25T18:05:00", scale="utc").unix))
    assert g.epoch_utc == "2026-03-25T18:05:00.000"
    t = float(Time(g.epoch_utc, scale="utc").unix)
    assert list(g.sc_position_km) == pytest.approx(list(orbit.position_gcrs_km(t)))
    a = _off_axis(g.bodies["sun"].direction, 28.0)
    inp = g.render_inputs(a, CAMERA, DET, np.random.default_rng(0))
    start = exposure_start(g.epoch_utc, DET.exposure_s)  # the glare's epoch is the mid-time
    assert inp.timestamp == start and inp.metadata["sc_position_km"] == pytest.approx(list(g.sc_position_km))
    assert inp.extra_e is not None and inp.extra_e.max() > 100.0
    r = render_with_effects(random_star_field(CAMERA, a, 5, seed=1), a, CAMERA, DET, [g], np.random.default_rng(0), 3)
    assert r.frame.timestamp == start and "glare" in r.truth["effects"][0]
