"""Catalog design: derived quantities, validation messages, TOML."""

import math

import pytest

from ground.catalog.design import CatalogDesign, DesignError


def test_defaults_and_derived_quantities():
    d = CatalogDesign()
    assert d.delta_star == pytest.approx(4.65, abs=0.005)  # seed 000 eq. 7 at P_correct 0.99
    assert math.degrees(d.phi_min) == pytest.approx(7.5 / 500) and math.degrees(d.phi_max) == pytest.approx(15.0)
    assert d.focal_px == pytest.approx(972 / math.tan(math.radians(7.5)))
    assert d.sigma_phi == pytest.approx(2 * 0.2 / d.focal_px)  # eq. 18
    assert d.dphi_star == pytest.approx(d.sigma_phi * d.delta_star / 2)  # eq. 9


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"theta_fov_deg": -1.0}, "theta_fov_deg = -1.0: must be in"),
        ({"phi_min_deg": 15.0}, "phi_min = 15 deg must be below phi_max = 15 deg"),
        ({"phi_min_deg": 1.0, "phi_max_deg": 0.5}, "phi_min = 1 deg must be below phi_max = 0.5 deg"),
        ({"sigma_pix": 0.0}, "sigma_pix = 0.0: must be > 0"),
        ({"p_correct": 1.0}, "p_correct = 1.0"),
        ({"n_h": 0}, "n_h = 0"),
        ({"source": "sky2000"}, "source = 'sky2000'"),
        ({"sensor_width_px": 10.5}, "sensor_width_px = 10.5"),
    ],
)
def test_impossible_parameters_are_named(kwargs, match):
    with pytest.raises(DesignError, match=match):
        CatalogDesign(**kwargs)


def test_toml(tmp_path):
    p = tmp_path / "d.toml"
    p.write_text("[design]\ntheta_fov_deg = 10.0\nm_thresh = 4.5\nsigma_rg = 0.1\nsigma_bg = 0.1\n")
    d = CatalogDesign.from_toml(p)
    assert (d.theta_fov_deg, d.m_thresh, d.sigma_rg) == (10.0, 4.5, 0.1)
    p.write_text("theta_fov_deg = 7.5\nfov = 3\n")
    with pytest.raises(DesignError, match=r"d.toml: unknown design parameter\(s\) \['fov'\]"):
        CatalogDesign.from_toml(p)
    p.write_text("theta_fov_deg = -2\n")
    with pytest.raises(DesignError, match="d.toml: theta_fov_deg = -2"):
        CatalogDesign.from_toml(p)
    p.write_text("theta_fov_deg = \n")
    with pytest.raises(DesignError, match="d.toml"):
        CatalogDesign.from_toml(p)
