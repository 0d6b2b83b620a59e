"""Planet and Moon prediction and labelling (firmware_model/pipeline/planets.py).

Truth for the ephemeris checks comes from published events, each quoted with its source
and converted into a geometric fact that does not depend on our code:

* 2019-11-11 transit of Mercury, geocentric contacts (F. Espenak, eclipsewise.com):
  I 12:35:27, II 12:37:08, III 18:02:33, IV 18:04:14 UT. At I and IV the centres are
  R_sun + r_Mercury apart, at II and III R_sun - r_Mercury.
* 2017-08-21 total solar eclipse, greatest eclipse 18:25:32 UT1 at 36 58.0' N,
  87 40.3' W (F. Espenak, NASA): on the central line the centres of the Sun and the
  Moon coincide, and the Moon's disk is the larger one (eclipse magnitude 1.03).
* 2020-12-21 great conjunction: Jupiter and Saturn 6.1 arcmin (0.1 deg) apart, the
  closest since 1623, on 21 December (UTC).
* 2020-03-20 03:50 UTC March equinox: the Sun's apparent longitude of date is 0, so its
  astrometric (unaberrated) longitude is +20.5 arcsec (annual aberration).
"""

import socket

import numpy as np
import pytest
from astropy import units as u
from astropy.time import Time
from scipy.spatial.transform import Rotation

from firmware_model.camera import CameraModel
from firmware_model.pipeline import planets
from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat, vec_to_radec

ARCSEC = np.radians(1.0 / 3600.0)
ARCMIN = 60.0 * ARCSEC


def _sep(a, b) -> float:
    """Angle (rad) between two vectors."""
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b)))


def _radius(body, pos) -> float:
    return float(np.arcsin(planets.RADIUS_KM[body] / np.linalg.norm(pos)))


# ---------------------------------------------------------------- published events
@pytest.mark.parametrize(
    "utc, sign",
    [
        ("2019-11-11T12:35:27", +1),
        ("2019-11-11T12:37:08", -1),
        ("2019-11-11T18:02:33", -1),
        ("2019-11-11T18:04:14", +1),
    ],
)
def test_mercury_transit_contacts(utc, sign):
    # Mercury crosses the limb at ~6 arcsec/min: 10 arcsec is 2 min of timing
    pos = planets.astrometric_positions(utc, ("sun", "mercury"))
    contact = _radius("sun", pos["sun"]) + sign * _radius("mercury", pos["mercury"])
    assert abs(_sep(pos["sun"], pos["mercury"]) - contact) < 10 * ARCSEC


def test_eclipse_2017_centres_coincide_on_the_central_line():
    site = (36 + 58.0 / 60, -(87 + 40.3 / 60), 150.0)
    utc = "2017-08-21T18:25:32"
    topo = planets.astrometric_positions(utc, ("sun", "moon"), site=site)
    # moon98 is good to 3 arcsec RMS; the site is on the central line to ~0.2 km
    assert _sep(topo["sun"], topo["moon"]) < 20 * ARCSEC
    assert _radius("moon", topo["moon"]) > _radius("sun", topo["sun"])  # total, not annular
    # geocentric, the Moon is displaced by the site's parallax (~0.45 deg here)
    geo = planets.astrometric_positions(utc, ("sun", "moon"))
    assert _sep(geo["sun"], geo["moon"]) > 20 * ARCMIN
    moon_geo = planets.planet_directions(utc)["moon"]
    moon_topo = planets.planet_directions(utc, site=site)["moon"]
    assert _sep(moon_geo, geo["moon"]) < 0.1 * ARCSEC
    assert _sep(moon_topo, topo["moon"]) < 0.1 * ARCSEC


def test_great_conjunction_2020():
    t0 = Time("2020-12-20T00:00:00", scale="utc")
    epochs = t0 + np.arange(0, 3 * 24 * 60, 20) * u.min  # 3 days in 20 min steps
    seps = []
    for t in epochs:
        d = planets.planet_directions(t)
        seps.append(_sep(d["jupiter"], d["saturn"]))
    i = int(np.argmin(seps))
    # published 6.1 arcmin; plan94 leaves ~30 arcsec RMS on each planet
    assert abs(seps[i] - 6.1 * ARCMIN) < 0.5 * ARCMIN
    assert epochs[i].utc.iso.startswith("2020-12-21")


def test_equinox_2020_fixes_the_absolute_axes():
    import erfa

    t = Time("2020-03-20T03:50:00", scale="utc")
    sun = planets.astrometric_positions(t, ("sun",))["sun"]
    # GCRS -> true equator and equinox of date (bias, precession, nutation)
    npb = erfa.pnm06a(t.tt.jd1, t.tt.jd2)
    ra, dec = vec_to_radec(npb @ sun)
    ra = (ra + np.pi) % (2 * np.pi) - np.pi
    eps = np.radians(23.44)
    # astrometric longitude +20.5 arcsec, latitude 0 -> RA, Dec of date
    # tolerance: the equinox time is given to the minute (2.5 arcsec/min) plus epv00
    assert abs(ra - 20.5 * ARCSEC * np.cos(eps)) < 5 * ARCSEC
    assert abs(dec - 20.5 * ARCSEC * np.sin(eps)) < 5 * ARCSEC


def test_directions_are_unit_vectors_for_all_bodies_and_cached():
    d = planets.planet_directions("2024-06-01T00:00:00")
    assert set(d) == set(planets.PLANETS) | {"moon"}
    assert np.allclose([np.linalg.norm(v) for v in d.values()], 1.0)
    b = planets.body_positions("2024-06-01T00:00:00")
    assert b["moon"].extended and not b["jupiter"].extended
    assert np.radians(0.24) < b["moon"].angular_radius < np.radians(0.28)
    assert planets.body_positions(Time("2024-06-01T00:00:00", scale="utc")) is b


def test_no_network_access_even_with_expired_tables(monkeypatch):
    """With every local leap-second table treated as expired and downloads enabled
    globally, predicting positions must not open a connection."""
    import astropy.time.core as time_core
    from astropy.utils import iers

    attempts = []

    def refuse(*args, **kwargs):
        attempts.append(args)
        raise OSError("network disabled in test")

    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(time_core, "_LEAP_SECONDS_CHECK", time_core._LeapSecondsCheck.NOT_STARTED)
    with iers.conf.set_temp("auto_max_age", -1e6), iers.conf.set_temp("auto_download", True):
        with pytest.warns(Warning):  # astropy reports the "expired" tables
            planets.planet_directions("2031-02-03T04:05:06", site=(10.0, 20.0, 0.0))
    assert attempts == []


# ---------------------------------------------------------------- synthetic frames
CAMERA = CameraModel.reference_design()


def _attitude_placing(direction, x, y, roll=0.3):
    """Quaternion that puts ICRS ``direction`` at pixel (x, y) of CAMERA."""
    ra, dec = vec_to_radec(direction)
    a0 = attitude_from_radec_roll(ra, dec, roll)  # direction -> +z
    target = CAMERA.pixel_to_vector(x, y)[0]
    rot, _ = Rotation.align_vectors([target], [[0.0, 0.0, 1.0]])
    return matrix_to_quat(rot.as_matrix() @ a0)


EPOCH = "2024-12-01T06:00:00"  # new Moon; Jupiter in Taurus, far from the other bodies


def test_jupiter_detection_is_the_only_label():
    jupiter = planets.planet_directions(EPOCH)["jupiter"]
    q = _attitude_placing(jupiter, 1800.3, 600.7)
    view = planets.planets_in_view(q, CAMERA, EPOCH)
    assert [b.name for b in view] == ["jupiter"]
    assert abs(view[0].x - 1800.3) < 1e-6 and abs(view[0].y - 600.7) < 1e-6
    tol = planets.default_tol_px(CAMERA)
    assert 4.0 < tol < 6.0  # 2.5 arcmin at 27.9 arcsec/px
    rng = np.random.default_rng(9)
    stars_x = rng.uniform(0, CAMERA.width - 1, 40)
    stars_y = rng.uniform(0, CAMERA.height - 1, 40)
    keep = np.hypot(stars_x - 1800.3, stars_y - 600.7) > 50
    # detection 0: a star just outside the tolerance; detection 3: Jupiter (0.5 px off)
    x = np.concatenate([[1800.3 + tol + 1.0], stars_x[keep][:2], [1800.6], stars_x[keep][2:]])
    y = np.concatenate([[600.7], stars_y[keep][:2], [601.1], stars_y[keep][2:]])
    labels = planets.label_planets(x, y, q, CAMERA, EPOCH)
    assert [(lab.index, lab.body) for lab in labels] == [(3, "jupiter")]
    assert labels[0].distance_px == pytest.approx(0.5, abs=1e-6)
    # a wider tolerance takes the near star too
    wide = planets.label_planets(x, y, q, CAMERA, EPOCH, tol_px=tol + 2.0)
    assert [lab.index for lab in wide] == [0, 3]


def test_empty_sky_gives_no_labels():
    # the north ecliptic pole is ~90 deg from every planet and >= 84 deg from the Moon
    pole = np.array([0.0, -np.sin(np.radians(23.44)), np.cos(np.radians(23.44))])
    q = _attitude_placing(pole, CAMERA.cx, CAMERA.cy)
    assert planets.planets_in_view(q, CAMERA, EPOCH) == []
    xs, ys = np.meshgrid(np.linspace(0, CAMERA.width - 1, 20), np.linspace(0, CAMERA.height - 1, 15))
    assert planets.label_planets(xs.ravel(), ys.ravel(), q, CAMERA, EPOCH) == []
    assert planets.label_planets([], [], q, CAMERA, EPOCH) == []


MOON_EPOCH = "2024-06-15T00:00:00"


def test_moon_disk_and_glare_are_labelled():
    bodies = planets.body_positions(MOON_EPOCH)
    q = _attitude_placing(bodies["moon"].direction, CAMERA.cx, CAMERA.cy, roll=1.0)
    view = planets.planets_in_view(q, CAMERA, MOON_EPOCH)
    moon = [b for b in view if b.name == "moon"]
    assert len(moon) == 1
    r = moon[0].radius_px
    assert r == pytest.approx(bodies["moon"].angular_radius * CAMERA.f, rel=1e-3)
    assert 30 < r < 37  # 0.24-0.28 deg at 27.9 arcsec/px
    tol = planets.default_tol_px(CAMERA)
    margin = planets.DEFAULT_MOON_MARGIN * CAMERA.f
    cx, cy = CAMERA.cx, CAMERA.cy
    offsets = [0.0, 0.9 * r, r + 0.5 * margin, r + margin + tol - 1.0, r + margin + tol + 2.0, 400.0]
    x = cx + np.array(offsets) * np.cos(0.7)
    y = cy + np.array(offsets) * np.sin(0.7)
    labels = planets.label_planets(x, y, q, CAMERA, MOON_EPOCH)
    assert [(lab.index, lab.body) for lab in labels] == [(0, "moon"), (1, "moon"), (2, "moon"), (3, "moon")]
    # without a glare margin only the disk (plus the tolerance) counts
    disk_only = planets.label_planets(x, y, q, CAMERA, MOON_EPOCH, moon_margin=0.0)
    assert [lab.index for lab in disk_only] == [0, 1]


def test_moon_off_the_array_with_its_disk_on_it():
    moon = planets.body_positions(MOON_EPOCH)["moon"]
    # centre 20 px beyond the left edge: half of the disk lies on the array
    q = _attitude_placing(moon.direction, -20.5, CAMERA.cy)
    view = planets.planets_in_view(q, CAMERA, MOON_EPOCH)
    assert [b.name for b in view] == ["moon"]
    labels = planets.label_planets([0.0, 200.0], [CAMERA.cy, CAMERA.cy], q, CAMERA, MOON_EPOCH)
    assert [(lab.index, lab.body) for lab in labels] == [(0, "moon")]
    # far enough off that even the glare margin misses the array: not in view
    far = _attitude_placing(moon.direction, -1000.0, CAMERA.cy)
    assert planets.planets_in_view(far, CAMERA, MOON_EPOCH) == []
