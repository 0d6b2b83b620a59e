"""build_catalog on the real catalogs, the pair indices on them, and the CLI."""

import json
import math

import numpy as np
import pytest

from firmware_model.catalog.image_io import catalog_from_image, catalog_to_image
from ground.catalog.build import build_catalog
from ground.catalog.colour import ColourSource
from ground.catalog.design import CatalogDesign, DesignError
from ground.cli.main import main as cli_main


@pytest.fixture(scope="module")
def hip_cat():
    return build_catalog(CatalogDesign(m_thresh=4.0, theta_fov_deg=10.0))


def test_hipparcos_build_invariants(hip_cat):
    c = hip_cat
    assert 500 < c.n_stars < 600 and np.all(c.mag <= 4.0)
    assert np.all(np.diff(np.arctan2(c.vec[:, 1], c.vec[:, 0]) % (2 * np.pi)) >= 0)  # ordered by RA
    assert np.all(np.diff(c.pair_phi) >= 0) and c.pair_phi[0] > c.phi_min and c.pair_phi[-1] <= c.phi_max
    assert np.all(np.isfinite(c.rg)) and np.all(np.isfinite(c.bg))
    counts = c.meta["colour_source_counts"]
    assert counts["BV_LOOKUP"] + counts["VI_LOOKUP"] > 0.99 * c.n_stars and counts["NONE"] == 0
    assert counts["VI_LOOKUP"] > 0.2 * c.n_stars  # the red stars (B-V >= 1.0)
    assert c.meta["design"]["theta_fov_deg"] == 10.0


def test_pair_indices_match_brute_force_on_real_catalog(hip_cat):
    c = hip_cat
    rng = np.random.default_rng(0)
    for phi in rng.uniform(c.phi_min, c.phi_max, 40):
        tol = float(rng.choice([1e-5, 1e-4, 1e-3]))
        want = np.flatnonzero(np.abs(c.pair_phi - phi) <= tol)
        for a, b in (c.hash_range(phi, tol), c.kvector_range(phi, tol)):
            np.testing.assert_array_equal(np.arange(a, b), want)
        a, b = c.kvector_candidates(phi, tol)
        assert a <= (want[0] if len(want) else a) and b >= (want[-1] + 1 if len(want) else b)


def test_merging_uses_the_resolvability_angle():
    wide = build_catalog(CatalogDesign(m_thresh=4.0, resolve_deg=0.5))
    narrow = build_catalog(CatalogDesign(m_thresh=4.0, resolve_deg=0.0))
    assert wide.meta["selection"]["merged_doubles"] > 0 == narrow.meta["selection"]["merged_doubles"]
    assert wide.n_stars == narrow.n_stars - wide.meta["selection"]["merged_doubles"]


def test_bsc5_build_uses_pickles_types(shared_data):
    c = build_catalog(CatalogDesign(source="bsc5", m_thresh=4.5, pickles_dir=str(shared_data / "pickles")))
    src = c.meta["colour_source"]
    assert (src == ColourSource.PICKLES_MK).mean() > 0.9
    assert 7000 < c.n_pairs < 9000  # seed 000 table 1: 7.8e3 pairs


def test_cli_build_writes_a_valid_image(tmp_path, capsys):
    out = tmp_path / "cat.img"
    design = tmp_path / "d.toml"
    design.write_text("m_thresh = 3.5\ntheta_fov_deg = 10.0\n")
    assert cli_main(["--json", "catalog", "build", "--design", str(design), "--n-h", "256", "-o", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    cat = catalog_from_image(out.read_bytes())
    assert summary["n_pairs"] == cat.n_pairs and cat.n_h == 256
    assert cat.meta["m_thresh"] == 3.5 and math.degrees(cat.meta["theta_fov"]) == pytest.approx(10.0)


def test_cli_refuses_impossible_design(tmp_path, capsys):
    assert cli_main(["catalog", "build", "--theta-fov", "5", "--phi-min", "10", "-o", str(tmp_path / "x")]) == 2
    assert "phi_min = 10 deg must be below phi_max = 10 deg" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_cli_analyze_outputs(tmp_path, capsys):
    args = [
        "catalog",
        "analyze",
        "--m-thresh",
        "3.5",
        "--theta-fov",
        "10",
        "--views",
        "3000",
        "--json-out",
        str(tmp_path / "r.json"),
        "--plot",
        str(tmp_path / "v.png"),
    ]
    assert cli_main(["--json", *args]) == 0
    res = json.loads((tmp_path / "r.json").read_text())
    assert res["n_views"] == 3000 and 0 <= res["ambiguous_pairs_pct"] <= 100
    assert (tmp_path / "v.png").stat().st_size > 10_000


def test_hipparcos_borrows_bsc5_types(shared_data):
    c = build_catalog(CatalogDesign(m_thresh=4.0, mk_types_path=str(shared_data / "bsc5" / "catalog.dat")))
    assert c.meta["selection"]["mk_types_borrowed"] > 0.95 * c.n_stars
    assert c.meta["colour_source_counts"]["PICKLES_MK"] > 0.9 * c.n_stars


def test_bsc5_reproduces_seed000_catalog_and_bad_views(shared_data):
    """Seed 000 table 1, row 1 (M 4.5, theta_FOV 7.5 deg): 7.8e3 pairs, 15.92 % bad views, 99.77 % mono ambiguous."""
    from ground.catalog.analyze import analyze

    design = CatalogDesign(source="bsc5", m_thresh=4.5, epoch=2000.0, pickles_dir=str(shared_data / "pickles"))
    res = analyze(build_catalog(design), design, n_views=20_000)
    assert abs(res.n_pairs / 7800 - 1) < 0.05
    assert abs(res.bad_views_pct - 15.92) < 1.0
    assert abs(res.mono_ambiguous_pairs_pct - 99.77) < 0.2


def test_verification_only_stars_follow_the_pattern_stars_without_pairs(hip_cat):
    deep = build_catalog(CatalogDesign(m_thresh=4.0, m_verify=4.5, theta_fov_deg=10.0))
    n = deep.n_pattern_stars
    assert n == hip_cat.n_stars and deep.n_stars > n  # the pattern stars are those of m_thresh alone
    np.testing.assert_array_equal(deep.star_id[:n], hip_cat.star_id)
    np.testing.assert_array_equal(deep.pair_phi, hip_cat.pair_phi)
    assert np.all(deep.mag[n:] > 4.0) and np.all(deep.mag[n:] <= 4.5)
    assert deep.meta["selection"]["verification_only"] == deep.n_stars - n
    assert catalog_from_image(catalog_to_image(deep)).n_pattern_stars == n


def test_for_field_puts_six_times_the_stars_in_view_with_the_verification_only_ones():
    d = CatalogDesign.for_field(1024, 768, 11.4)
    assert d.m_verify - d.m_thresh == pytest.approx(math.log10(6.0) / 0.515, abs=0.11)
    with pytest.raises(DesignError, match="m_verify"):
        CatalogDesign(m_thresh=5.0, m_verify=4.0)


def test_sparse_regions_promote_their_brightest_fainter_stars_to_pattern_stars():
    from firmware_model.reference_frames import radec_to_vec
    from ground.catalog.build import promote_sparse

    rng = np.random.default_rng(5)
    # a dense patch (20 pattern stars) and a sparse one (2 pattern stars), 10 fainter stars in each
    ra = np.concatenate([rng.uniform(0.0, 0.05, 30), rng.uniform(1.0, 1.05, 12)])
    dec = np.concatenate([rng.uniform(0.0, 0.05, 30), rng.uniform(0.0, 0.05, 12)])
    pattern = np.zeros(42, bool)
    pattern[:20] = pattern[30:32] = True
    vmag = np.where(pattern, 5.0, rng.uniform(6.0, 7.0, 42))
    promoted = promote_sparse(radec_to_vec(ra, dec), vmag, pattern, radius=0.2, per_cap=8)
    assert not promoted[:30].any()  # the dense patch has its 8 already
    assert promoted[30:].sum() == 6  # the sparse one: its 6 brightest fainter stars
    sparse_faint = np.arange(32, 42)
    assert np.all(vmag[sparse_faint][promoted[sparse_faint]] <= np.sort(vmag[sparse_faint])[5])
    assert not promote_sparse(radec_to_vec(ra, dec), vmag, pattern, radius=0.2, per_cap=0).any()


def test_cli_fov_build_has_verification_only_and_sparse_sky_stars_and_flags_override(tmp_path, capsys):
    out = tmp_path / "cat.img"
    base = ["--json", "catalog", "build", "--width", "1024", "--height", "768", "--fov-deg", "11.4", "-o", str(out)]
    assert cli_main(base) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["selection"]["promoted_sparse"] > 0 and summary["selection"]["verification_only"] > 0
    cat = catalog_from_image(out.read_bytes())
    assert cat.n_pattern_stars == summary["n_pattern_stars"] < cat.n_stars
    assert cli_main([*base, "--min-pattern-stars", "0"]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert plain["selection"]["promoted_sparse"] == 0
    assert plain["n_pattern_stars"] == summary["n_pattern_stars"] - summary["selection"]["promoted_sparse"]
