"""Field corrections: bilinear colour fit (eq. 24) and refraction against Bennett's formula."""

import numpy as np
import pytest
from astropy.time import Time

from firmware_model import reference_frames as frames
from ground.calibration.corrections import (
    ColourCorrection,
    Site,
    bennett_refraction_deg,
    correct_refraction,
    refraction_angle,
)


def test_colour_fit_recovers_known_map_and_rejects_outliers():
    rng = np.random.default_rng(4)
    cat = np.column_stack([rng.uniform(0.3, 1.2, 40), rng.uniform(0.2, 1.4, 40)])
    b = np.array([[0.9, 0.05], [-0.03, 0.8]])
    c = np.array([-0.05, -0.1])
    # observed = inverse of the correction applied to the catalog, plus noise
    obs = (cat - c) @ np.linalg.inv(b).T + rng.normal(0, 0.005, cat.shape)
    obs[3] += [0.6, -0.5]  # an obvious outlier
    fit = ColourCorrection.fit(obs, cat)
    assert fit.n_rejected >= 1
    assert np.allclose(fit.matrix, b, atol=0.03)
    assert np.allclose(fit.offset, c, atol=0.03)
    assert fit.rms_after < 0.01 < fit.rms_before
    again = ColourCorrection.from_json(fit.to_json())
    assert np.allclose(again.beta, fit.beta)


def test_colour_fit_refuses_too_few_stars_and_bad_json():
    with pytest.raises(ValueError, match="at least 4"):
        ColourCorrection.fit(np.ones((3, 2)), np.ones((3, 2)))
    with pytest.raises(ValueError, match="colour correction"):
        ColourCorrection.from_json('{"kind": "other"}')
    with pytest.raises(ValueError, match="6 finite"):
        ColourCorrection.from_json('{"kind": "colour_correction", "beta": [1, 2]}')


SITE = Site(lat_deg=43.66, lon_deg=-79.38, height_m=100, pressure_hpa=1010, temperature_c=10)
TIME = Time("2012-02-10T03:00:00", scale="utc")


def test_astropy_refraction_agrees_with_bennett():
    for alt in (20.0, 35.0, 60.0):
        r = np.degrees(refraction_angle(np.radians(alt), SITE, TIME)[0])
        apparent = alt + r
        # astropy (ERFA refco, humidity and wavelength) and Bennett's mean formula agree to ~3 %
        assert r == pytest.approx(bennett_refraction_deg(apparent, 1010, 10), rel=0.04)


def test_correct_refraction_restores_true_geometry():
    """Refract true vectors with astropy, then correct them: the arcs come back."""
    import astropy.units as u
    from astropy.coordinates import ICRS, SkyCoord

    from ground.calibration.corrections import _altaz_frames

    vacuum, air = _altaz_frames(SITE, TIME)
    # a field centred at 25 deg altitude
    centre = SkyCoord(az=120 * u.deg, alt=25 * u.deg, frame=vacuum).transform_to(ICRS())
    ra, dec = centre.ra.rad, centre.dec.rad
    a = frames.attitude_from_radec_roll(ra, dec, 0.3)
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.1, 0.1, (6, 2))
    s_true = np.column_stack([xy, np.ones(6)])
    s_true /= np.linalg.norm(s_true, axis=1)[:, None]
    true_icrs = SkyCoord(*frames.vec_to_radec(s_true @ a), unit="rad", frame=ICRS())
    app = true_icrs.transform_to(air)
    refracted = SkyCoord(az=app.az, alt=app.alt, frame=vacuum).transform_to(ICRS())
    s_obs = frames.radec_to_vec(refracted.ra.rad, refracted.dec.rad) @ a.T

    def arcs(s):
        return np.arccos(np.clip(s @ s.T, -1, 1))

    before = np.abs(arcs(s_obs) - arcs(s_true)).max()
    exact = np.abs(arcs(correct_refraction(s_obs, a, SITE, TIME)) - arcs(s_true)).max()
    # an attitude off by ~0.5 deg, as in the paper's procedure, costs a little accuracy
    a_approx = frames.attitude_from_radec_roll(ra + 0.008, dec - 0.005, 0.31)
    approx = np.abs(arcs(correct_refraction(s_obs, a_approx, SITE, TIME)) - arcs(s_true)).max()
    assert before > np.radians(10 / 3600)  # refraction distorts the arcs noticeably
    assert exact < np.radians(0.05 / 3600)
    assert approx < before / 3
