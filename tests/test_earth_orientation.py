"""Earth orientation from the project's own table (issue 40 section 1): any date works offline,
whatever today's date, with a stated error past the tables, and nothing global changes."""

import numpy as np
import pytest
from astropy.time import Time
from astropy.utils import iers

from ground.calibration.corrections import Site, correct_refraction, refraction_angle
from ground.sim import detector_effects as de
from ground.sim import earth_orientation as eo
from ground.sim.orbit import CircularOrbit

SITE = Site(45.0, 7.0, 300.0)


def _year_past_the_tables() -> Time:
    """A date a year past the end of the bundled tables (IERS-A's predictions)."""
    return Time(eo.table().end_mjd + 365.0, format="mjd", scale="utc")


@pytest.fixture
def clock_a_year_on(monkeypatch):
    """astropy's wall clock (``Time.now``, which IERS_Auto compares its predictions with) set a
    year past the bundled tables, as a device installed today and run next year sees it."""
    later = _year_past_the_tables()
    monkeypatch.setattr(Time, "now", classmethod(lambda cls: Time(later.isot, scale="utc")))
    return later


def test_the_subsatellite_point_works_a_year_past_the_tables(clock_a_year_on):
    t = clock_a_year_on.unix + 3600.0
    lat, lon, height = de.subsatellite_point([6928.137, 0.0, 0.0], t)
    assert abs(lat) < 0.5 and height == pytest.approx(550.0, abs=0.01)
    # past the table: UT1 = UTC, no polar motion; the same point as ERFA's with zeros
    assert eo.eop(Time(t, format="unix")).source == eo.OUTSIDE
    fx = de.MissionEffects(
        cosmic=de.CosmicRays(flux_cm2_s=4.0, saa=de.SouthAtlanticAnomaly()), orbit=CircularOrbit(550)
    )
    inp = fx.at_time(t).render_inputs(np.eye(3), _camera(), de.DetectorModel(), np.random.default_rng(0))
    assert len(inp.truth["subsatellite_deg"]) == 2


def _camera():
    from firmware_model.camera import CameraModel

    return CameraModel.reference_design()


def test_refraction_works_a_year_past_the_tables(clock_a_year_on):
    t = Time(clock_a_year_on.isot, scale="utc")
    r = refraction_angle(np.radians(20.0), SITE, t)
    r_then = refraction_angle(np.radians(20.0), SITE, Time("2024-03-01T00:00:00", scale="utc"))
    assert np.degrees(r[0]) * 3600 == pytest.approx(158.2, abs=0.5)  # Bennett-like at 20 deg, 1013 hPa
    assert r[0] == pytest.approx(r_then[0], abs=1e-9)  # the weather's, not the date's
    v = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 0.995]])
    out = correct_refraction(v / np.linalg.norm(v, axis=1)[:, None], np.eye(3), SITE, t)
    assert np.all(np.isfinite(out))


def test_inside_iers_b_the_table_is_astropys():
    import astropy.units as u
    from astropy.coordinates import GCRS, ITRS, CartesianRepresentation

    t = Time("2024-03-01T05:00:00", scale="utc")
    pos = np.array([6928.0, 100.0, 50.0])
    b = iers.IERS_B.open(iers.IERS_B_FILE)
    with iers.earth_orientation_table.set(b):
        ref = GCRS(CartesianRepresentation(*(pos * u.km)), obstime=t).transform_to(ITRS(obstime=t))
    assert eo.eop(t).source == eo.FROM_B
    assert eo.eop(t).dut1_s == pytest.approx(float(b.ut1_utc(t).to_value(u.s)), abs=1e-6)
    assert np.linalg.norm(eo.gcrs_to_itrs(pos, t.unix) - ref.cartesian.xyz.to_value(u.km)) < 1e-6  # km


def test_no_global_setting_is_changed():
    before = iers.earth_orientation_table.get()
    with iers.conf.set_temp("auto_download", True):
        refraction_angle(np.radians(30.0), SITE, Time("2026-11-01T00:00:00", scale="utc"))
        de.subsatellite_point([7000.0, 0.0, 0.0], Time("2026-11-01T00:00:00").unix)
        assert iers.conf.auto_download is True
    assert iers.earth_orientation_table.get() is before


def test_the_stated_error_past_the_tables_holds(monkeypatch):
    """UT1 - UTC off by its largest 0.9 s and polar motion by 0.6 arcsec: the sub-satellite point
    moves at most SUBSATELLITE_ERROR_KM, the refraction correction at most REFRACTION_ERROR_ARCSEC
    above 10 deg (the figures the module states)."""
    t0 = _year_past_the_tables().unix
    worst_km = 0.0
    for t in t0 + np.linspace(0.0, 86400.0, 7):
        for lon in np.radians(np.arange(0, 360, 60)):
            pos = 6928.137 * np.array([np.cos(lon), np.sin(lon), 0.0])
            a = eo.gcrs_to_itrs(pos, t)
            for d, p in [(0.9, 0.6), (-0.9, -0.6), (0.9, -0.6), (-0.9, 0.6)]:
                b = eo.gcrs_to_itrs(pos, t, dut1_offset_s=d, pm_offset_arcsec=p)
                worst_km = max(worst_km, float(np.arccos(min(1.0, a @ b / (a @ a)))) * 6378.137)
    assert 0.3 < worst_km <= eo.SUBSATELLITE_ERROR_KM

    import astropy.units as u
    from astropy.coordinates import ICRS, AltAz, SkyCoord

    iso = Time(t0 + 0.9 * 86400, format="unix").isot
    with eo.tables():
        vac = AltAz(obstime=Time(iso), location=SITE.location(), pressure=0 * u.hPa)
        sky = SkyCoord(az=np.arange(0, 360, 30) * u.deg, alt=np.full(12, 10.0) * u.deg, frame=vac)
        v = sky.transform_to(ICRS()).cartesian.xyz.value.T
    base = correct_refraction(v, np.eye(3), SITE, Time(iso))
    orig = eo.tables
    monkeypatch.setattr(eo, "tables", lambda: orig(0.9))  # the table's UT1 - UTC off by 0.9 s
    off = correct_refraction(v, np.eye(3), SITE, Time(iso))
    worst_arcsec = float(np.degrees(np.arccos(np.clip(np.sum(base * off, axis=1), -1, 1))).max() * 3600)
    assert 0.01 < worst_arcsec <= eo.REFRACTION_ERROR_ARCSEC
