"""Open-loop rendering models (ground/sim/openloop.py and the render_frame hooks) do what they claim."""

import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.pipeline.raw_frame import pattern_codes
from firmware_model.reference_frames import attitude_from_radec_roll
from ground.sim import openloop as ol
from ground.sim.sensor_sim import DetectorModel, Stars, pixel_integrated_gaussian, render_frame

CAM = CameraModel.from_fov(320, 240, 2.0)
ATT = attitude_from_radec_roll(0.3, -0.4, 0.1)
QUIET = dict(prnu=0.0, dsnu_e=0.0, hot_pixel_fraction=0.0)
GRID = np.arange(-40, 41, dtype=float)


def _star_at(x, y, vmag=4.0, rg=0.8, bg=0.6):
    return Stars([7], CAM.pixel_to_vector([x], [y]) @ ATT, [vmag], [rg], [bg])


def _fraction_outside(stamp, radius):
    r = np.hypot(GRID[None, :], GRID[:, None])
    return stamp[r > radius].sum()


@pytest.mark.parametrize("beta", [2.5, 4.0])
def test_moffat_integrates_to_one_has_the_fwhm_and_heavier_wings_than_a_gaussian(beta):
    psf = ol.MoffatPSF(fwhm_px=2.5, beta=beta)
    stamp = psf.stamp(0.0, 0.0, GRID, GRID)
    assert stamp.sum() == pytest.approx(1.0, abs=2e-3)
    gauss = pixel_integrated_gaussian(0.0, 0.0, 2.5 / 2.3548, GRID, GRID)
    # same FWHM: the wings beyond 2 FWHM hold >10x the Gaussian's flux
    assert _fraction_outside(stamp, 5.0) > 10 * _fraction_outside(gauss, 5.0)
    wide = ol.MoffatPSF(fwhm_px=8.0, beta=beta).stamp(0.0, 0.0, GRID, GRID)
    assert wide[40, 44] / wide[40, 40] == pytest.approx(0.5, abs=0.03)  # half maximum at FWHM / 2


def test_donut_has_a_hole_and_a_ring_at_the_requested_radius():
    psf = ol.DonutPSF(r_out_px=6.0, r_in_px=3.0, blur_sigma_px=0.3)
    stamp = psf.stamp(0.0, 0.0, GRID, GRID)
    assert stamp.sum() == pytest.approx(1.0, abs=1e-9)
    profile = stamp[40, 40:]
    assert profile[0] < 0.05 * profile.max()
    assert 3 <= int(np.argmax(profile)) <= 6
    assert profile[8] < 0.01 * profile.max()


def test_coma_grows_with_field_radius_and_flares_outward():
    cam = CameraModel.reference_design()
    psf = ol.ComaPSF(1.0, 1.5, cam.cx, cam.cy, ol.corner_radius_px(cam))
    cols, rows = np.arange(-15, 16, dtype=float), np.arange(-15, 16, dtype=float)
    on_axis = psf.stamp(cam.cx, cam.cy, cols + cam.cx, rows + cam.cy)
    assert np.allclose(on_axis, on_axis[::-1, ::-1])  # no coma at the centre
    x0, y0 = 2590.0, 1940.0  # near the (+x, +y) corner
    s = psf.stamp(x0, y0, cols + x0, rows + y0)
    assert s.sum() == pytest.approx(1.0, abs=1e-6)
    cx_, cy_ = (s.sum(0) * cols).sum(), (s.sum(1) * rows).sum()
    c = psf.coma_c(x0, y0)
    assert c == pytest.approx(1.5 * np.hypot(x0 - cam.cx, y0 - cam.cy) / ol.corner_radius_px(cam))
    u = np.array([x0 - cam.cx, y0 - cam.cy]) / np.hypot(x0 - cam.cx, y0 - cam.cy)
    assert cx_ * u[0] + cy_ * u[1] == pytest.approx(c, abs=0.01)  # centroid C outward of the chief ray
    assert abs(-cx_ * u[1] + cy_ * u[0]) < 0.01
    assert not np.allclose(s, s[::-1, ::-1], atol=1e-3)  # asymmetric


@pytest.mark.parametrize(
    "model,shift", [("division", 5.0), ("division", -5.0), ("equisolid", -5.0), ("equisolid", 3.0)]
)
def test_radial_models_move_the_corner_star_by_the_requested_pixels(model, shift):
    base = CameraModel.reference_design()
    cam = ol.RadialMappedCamera(base, model, shift)
    corner = np.array([-0.5, -0.5])
    v = base.pixel_to_vector(corner[:1], corner[1:])
    x, y = cam.vector_to_pixel(v)
    r0 = np.hypot(corner[0] - base.cx, corner[1] - base.cy)
    assert np.hypot(x[0] - base.cx, y[0] - base.cy) - r0 == pytest.approx(shift, abs=1e-6)
    # radial about the principal point; a half-field star moves by much less than the corner one
    xc, yc = cam.vector_to_pixel(np.array([0.0, 0.0, 1.0]))
    assert (xc[0], yc[0]) == pytest.approx((base.cx, base.cy))
    vm = base.pixel_to_vector([base.cx + 0.5 * (corner[0] - base.cx)], [base.cy])
    xm, _ = cam.vector_to_pixel(vm)
    assert 0 < abs(xm[0] - base.vector_to_pixel(vm)[0][0]) < 0.3 * abs(shift)


def test_true_camera_scales_focal_length_and_moves_the_principal_point():
    nominal = CameraModel.reference_design()
    cam = ol.true_camera(nominal, 1.03, (12.0, -20.0))
    assert cam.f == pytest.approx(1.03 * nominal.f)
    x, y = cam.vector_to_pixel(np.array([0.0, 0.0, 1.0]))
    assert (x[0], y[0]) == pytest.approx((nominal.cx + 12.0, nominal.cy - 20.0))


def test_drop_stars_honours_the_fraction():
    n = 200
    stars = Stars(np.arange(n), np.tile([0.0, 0.0, 1.0], (n, 1)), np.full(n, 4.0), np.ones(n), np.ones(n))
    kept, dropped = ol.drop_stars(stars, 0.15, np.random.default_rng(1))
    assert len(dropped) == 30 and len(kept.ids) == 170
    assert not set(kept.ids) & set(dropped)


def test_scintillation_jitters_flux_with_the_requested_sigma_and_unit_mean():
    n = 4000
    stars = Stars(np.arange(n), np.tile([0.0, 0.0, 1.0], (n, 1)), np.full(n, 4.0), np.ones(n), np.ones(n))
    out = ol.scintillate(stars, 0.2, np.random.default_rng(2))
    f = 10 ** (-0.4 * (out.vmag - 4.0))
    assert np.std(np.log(f)) == pytest.approx(0.2, rel=0.05)
    assert np.mean(f) == pytest.approx(1.0, abs=0.01)


def test_channel_gain_changes_the_channel_ratios_by_the_factor():
    det = DetectorModel(pattern="RGGB", **QUIET)
    stars = _star_at(160.3, 120.7)
    chan = np.tile(pattern_codes("RGGB"), (120, 160))
    base = render_frame(stars, ATT, CAM, det, seed=1).electrons
    gained = render_frame(stars, ATT, CAM, det, seed=1, channel_gain=(1.05, 0.97, 0.95)).electrons
    tot = [[e[chan == c].sum() for c in (0, 1, 2)] for e in (base, gained)]
    assert tot[1][0] / tot[1][1] == pytest.approx(tot[0][0] / tot[0][1] * 1.05 / 0.97, rel=1e-9)
    assert tot[1][2] / tot[1][1] == pytest.approx(tot[0][2] / tot[0][1] * 0.95 / 0.97, rel=1e-9)


def test_psf_hook_renders_the_flux_and_default_render_is_unchanged():
    det = DetectorModel(pattern="MONO", **QUIET)
    stars = _star_at(160.2, 120.4)
    ref = render_frame(stars, ATT, CAM, det, seed=4)
    moffat = render_frame(stars, ATT, CAM, det, seed=4, psf=ol.MoffatPSF(3.0, 3.0))
    assert moffat.electrons.sum() == pytest.approx(ref.electrons.sum(), rel=2e-3)
    assert moffat.electrons.max() < 0.7 * ref.electrons.max()
    assert moffat.truth["psf"]["model"] == "moffat" and "psf" not in ref.truth
    again = render_frame(stars, ATT, CAM, det, seed=4, psf=None, extra_e=None, channel_gain=None)
    assert np.array_equal(again.frame.pixels, ref.frame.pixels)


def test_sky_gradient_and_hot_clusters_reach_the_frame():
    det = DetectorModel(pattern="MONO", read_noise_e=0.0, **QUIET)
    none = Stars(np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0))
    ramp = ol.sky_gradient_e((240, 320), 0.0, 400.0, 0.0)  # along +x
    assert ramp[:, 0].max() == 0.0 and ramp[:, -1].min() == pytest.approx(400.0)
    f = render_frame(none, ATT, CAM, det, seed=5, extra_e=ramp).frame
    dn = f.pixels.astype(float) - det.black_level_dn
    assert (dn[:, -8:].mean() - dn[:, :8].mean()) * det.gain_e_per_dn == pytest.approx(400.0 * 312 / 319, rel=0.05)
    hot, where = ol.hot_clusters_e((240, 320), 5, np.random.default_rng(3), e_range=(1000.0, 1000.0))
    assert len(where) == 5 and hot.max() >= 1000.0
    assert max(s * s for _, _, s in where) <= np.count_nonzero(hot) <= sum(s * s for _, _, s in where)


def test_bad_columns_stuck_dead_hot():
    det = DetectorModel(pattern="MONO", **QUIET)
    none = Stars(np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0))
    f = render_frame(none, ATT, CAM, det, seed=6).frame
    g = ol.apply_bad_columns(f, [(10, "stuck"), (20, "dead"), (30, "hot")])
    assert np.all(g.pixels[:, 10] == det.white_level_dn)
    assert np.all(g.pixels[:, 20] == det.black_level_dn)
    assert np.array_equal(g.pixels[:, 30].astype(int), f.pixels[:, 30].astype(int) + 300)
    assert np.array_equal(np.delete(g.pixels, [10, 20, 30], axis=1), np.delete(f.pixels, [10, 20, 30], axis=1))


def test_streak_carries_electrons_per_pixel_of_length():
    det = DetectorModel(pattern="MONO", **QUIET)
    none = Stars(np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0))
    obj = ol.streak(50.0, 60.0, 250.0, 160.0, 100.0)
    e = render_frame(none, ATT, CAM, det, seed=7, false_objects=[obj]).electrons
    assert e.sum() / det.mono_response == pytest.approx(100.0 * np.hypot(200, 100) * 3, rel=0.01)  # r + g + b


def test_blackbody_colours_follow_the_temperature_of_b_minus_v_and_keep_the_rest():
    from ground.catalog.colour import ballesteros_temperature, blackbody_ratios, default_qe

    qe = default_qe()
    bv = np.array([-0.2, 0.65, 1.5, np.nan, -0.9])
    rg, bg = ol.blackbody_colours(bv, np.full(5, 0.5), np.full(5, 0.4))
    want_rg, want_bg = blackbody_ratios(qe, ballesteros_temperature(bv[:3]), qe.band)
    assert rg[:3] == pytest.approx(want_rg, rel=1e-4) and bg[:3] == pytest.approx(want_bg, rel=1e-4)
    assert rg[0] < rg[1] < rg[2] and bg[0] > bg[1] > bg[2]  # hot stars blue, cool stars red
    assert list(rg[3:]) == [0.5, 0.5] and list(bg[3:]) == [0.4, 0.4]  # no usable B-V: unchanged
