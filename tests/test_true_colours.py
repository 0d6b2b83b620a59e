"""Open-loop colours in the whole-sky run: blackbody true colours, channel gain errors,
scintillation, the closed loop unchanged without them, and the command line's refusals."""

import json
from dataclasses import replace

import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.reference_frames import attitude_from_radec_roll
from ground.sim import whole_sky as skysim
from ground.sim.true_colours import TrueColours, impair, true_colour_table

CAM = CameraModel.reference_design()


@pytest.fixture(scope="module")
def catalog():
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    return build_catalog(CatalogDesign())


def _scenes(catalog, model, n=40, colour=True):
    a = attitude_from_radec_roll(1.2, 0.4, 0.5)
    return [skysim.observe(catalog, a, CAM, model, np.random.default_rng(k), colour=colour) for k in range(n)]


def test_blackbody_true_colours_differ_from_the_catalog_by_the_measured_amount(catalog):
    rg, bg = true_colour_table(catalog, "blackbody")
    d_rg, d_bg = np.abs(rg / catalog.rg - 1), np.abs(bg / catalog.bg - 1)
    # measured on the V <= 5 catalog (bench_colour_openloop.py prints them): medians 3.7 % / 4.2 %,
    # 90th percentiles 11.0 % / 13.2 %; the tolerances leave room for changes of the catalog's model
    assert np.median(d_rg) == pytest.approx(0.037, abs=0.01) and np.median(d_bg) == pytest.approx(0.042, abs=0.01)
    assert np.percentile(d_rg, 90) == pytest.approx(0.11, abs=0.03)
    assert np.percentile(d_bg, 90) == pytest.approx(0.13, abs=0.03)
    bv = np.asarray(catalog.meta["bv"], float)
    hot, solar = bv < 0.0, (bv > 0.6) & (bv < 1.0)
    assert np.median(d_rg[hot]) > 3 * np.median(d_rg[solar])  # a Planck spectrum misses the Balmer jump
    same = true_colour_table(catalog, "catalog")
    assert np.array_equal(same[0], catalog.rg.astype(float)) and np.array_equal(same[1], catalog.bg.astype(float))


def test_observed_colours_follow_the_true_colour_source(catalog):
    model = skysim.ErrorModel(sigma_colour=0.0, colours=TrueColours("blackbody"))
    rg, bg = true_colour_table(catalog, "blackbody")
    for sc in _scenes(catalog, model, 5):
        assert np.array_equal(sc.rg, rg[sc.truth]) and np.array_equal(sc.bg, bg[sc.truth])


def test_gain_errors_scale_rg_and_bg_per_frame_by_one_plus_or_minus_the_error(catalog):
    model = skysim.ErrorModel(sigma_colour=0.0, colours=TrueColours("catalog", gain_error=0.05))
    signs = []
    for sc in _scenes(catalog, model):
        k_rg, k_bg = sc.rg / catalog.rg[sc.truth], sc.bg / catalog.bg[sc.truth]
        assert np.ptp(k_rg) < 1e-6 and np.ptp(k_bg) < 1e-6  # one gain per frame and channel
        assert abs(k_rg[0] - 1) == pytest.approx(0.05, abs=1e-6) and abs(k_bg[0] - 1) == pytest.approx(0.05, abs=1e-6)
        signs.append((np.sign(k_rg[0] - 1), np.sign(k_bg[0] - 1)))
    assert len(set(signs)) == 4  # both signs, both channels, independently


def test_scintillation_is_per_star_and_per_channel(catalog):
    sigma = 0.03
    model = skysim.ErrorModel(sigma_colour=0.0, colours=TrueColours("catalog", scintillation=sigma))
    log_rg = np.concatenate([np.log(sc.rg / catalog.rg[sc.truth]) for sc in _scenes(catalog, model, 100)])
    assert np.std(log_rg) == pytest.approx(np.sqrt(2) * sigma, rel=0.05)  # f_r / f_g: two channels
    assert abs(np.mean(log_rg)) < 0.003


def test_zero_impairments_reproduce_the_closed_loop_exactly(catalog):
    rng = np.random.default_rng(5)
    rg, bg = np.array([0.8, 1.1]), np.array([0.7, 0.9])
    out = impair(rg, bg, TrueColours(), rng)
    assert out[0] is rg and out[1] is bg and rng.random() == np.random.default_rng(5).random()
    cfg = skysim.ColourSimConfig(n_boresights=30, n_roll=2, seed=4, model=skysim.ErrorModel(false_stars=1.0))
    explicit = replace(cfg, model=replace(cfg.model, colours=TrueColours("catalog", 0.0, 0.0)))
    a = skysim.run_poses(catalog, CAM, cfg, np.arange(60))
    b = skysim.run_poses(catalog, CAM, explicit, np.arange(60))
    for name in a.dtype.names:
        if name != "time_s":
            np.testing.assert_array_equal(a[name], b[name])


def test_the_open_loop_changes_only_the_colours(catalog):
    """Same directions, drops and false stars, and the same measurement noise draws: the closed
    and open loops differ in the noise-free colours alone (mono frames not at all)."""
    closed = skysim.ErrorModel(false_stars=2.0, p_drop=0.1)
    bb = replace(closed, colours=TrueColours("blackbody"))
    opened = replace(closed, colours=TrueColours("blackbody", 0.05, 0.03))
    rg, bg = true_colour_table(catalog, "blackbody")
    for c, b, o in zip(_scenes(catalog, closed, 10), _scenes(catalog, bb, 10), _scenes(catalog, opened, 10)):
        assert np.array_equal(c.vectors, o.vectors) and np.array_equal(c.truth, o.truth)
        true = c.truth >= 0
        noise_c = c.rg[true] - catalog.rg[c.truth[true]]
        np.testing.assert_allclose(b.rg[true] - rg[b.truth[true]], noise_c, atol=1e-12)
        assert not np.allclose(o.rg, b.rg)
    for c, o in zip(_scenes(catalog, closed, 5, False), _scenes(catalog, opened, 5, False)):
        assert np.array_equal(c.vectors, o.vectors) and np.array_equal(c.truth, o.truth)


def test_bad_values_are_refused(catalog):
    for kw in ({"source": "pickles"}, {"gain_error": -0.01}, {"gain_error": 0.6}, {"scintillation": 1.5}):
        with pytest.raises(ValueError):
            TrueColours(**kw)


@pytest.mark.parametrize(
    "argv,flag",
    [
        (["--gain-error", "0.7"], "--gain-error"),
        (["--gain-error", "-0.05"], "--gain-error"),
        (["--scintillation", "nan"], "--scintillation"),
        (["--scintillation", "2"], "--scintillation"),
        (["--true-colours", "pickles"], "--true-colours"),
    ],
)
def test_cli_refuses_out_of_range_open_loop_values_before_any_work(argv, flag, capsys, tmp_path):
    from ground.cli.main import main

    with pytest.raises(SystemExit) as exit_:
        main(["sim", "colour", "--out", str(tmp_path / "never"), *argv])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert "Traceback" not in err and f"error: argument {flag}:" in last and argv[1] in last, err
    assert not (tmp_path / "never").exists()


def test_cli_open_loop_options_reach_the_simulator(capsys):
    """The options change what is simulated, not only what is printed: colours off by a 40 %
    gain error and 40 % scintillation leave no high-confidence solve of poses that all solve
    with the catalog's own colours (measured 30 of 30, then 0 of 30, 29 no solution)."""
    from ground.cli.main import main

    argv = ["--json", "sim", "colour", "--boresights", "20", "--rolls", "1", "--workers", "1", "--no-progress"]
    assert main(argv) == 0
    clean = json.loads(capsys.readouterr().out)
    impaired_args = ["--true-colours", "blackbody", "--gain-error", "0.4", "--scintillation", "0.4"]
    assert main([*argv, *impaired_args]) == 0
    impaired = json.loads(capsys.readouterr().out)
    assert (clean["true_colours"], clean["gain_error"], clean["scintillation"]) == ("catalog", 0.0, 0.0)
    assert (impaired["true_colours"], impaired["gain_error"], impaired["scintillation"]) == ("blackbody", 0.4, 0.4)
    assert clean["high_confidence"] == clean["poses"] == 20
    assert impaired["high_confidence"] < 10 and impaired["high_confidence_wrong"] == 0


def test_blackbody_colours_go_through_the_catalog_qe():
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.sim.true_colours import catalog_qe

    ircut = build_catalog(CatalogDesign(qe_path="mt9p031_like_ircut"))
    assert catalog_qe(ircut).name == ircut.meta["qe"] == "mt9p031_like_ircut"
    rg, _ = true_colour_table(ircut, "blackbody")
    assert np.median(np.abs(rg / ircut.rg - 1)) < 0.1  # the same detector on both sides
