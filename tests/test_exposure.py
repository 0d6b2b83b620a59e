"""The device's sky exposures (ground.sim.exposure, noise_bank): only the stars in view are
rendered, with the same content as rendering the whole sky, and the bank's noise has the
statistics of fresh noise. No timings here (bench/bench_timing.py has them)."""

import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat
from ground.sim import exposure
from ground.sim.exposure import ExposureRenderer, stars_in_view
from ground.sim.noise_bank import NoiseBank
from ground.sim.sensor_sim import DetectorModel, Stars, render_frame
from ground.sim.sky_model import sky_stars
from ground.sim.sky_source import SkySource

CAM = CameraModel.reference_design()


def test_sky_source_renders_only_the_stars_in_view(monkeypatch, tmp_path):
    att = attitude_from_radec_roll(1.2, 0.4, 0.3)
    seen = []

    def spy(stars, attitude, camera, det, **kw):
        seen.append(stars)
        return render_frame(stars, attitude, camera, det, **kw)

    monkeypatch.setattr(exposure, "render_frame", spy)
    schedule = tmp_path / "s.csv"
    schedule.write_text("qw,qx,qy,qz\n" + ",".join(f"{v:.15f}" for v in matrix_to_quat(att)) + "\n")
    source = SkySource(str(schedule), CAM)
    source.ready()  # its start-up render (dropped) done
    seen.clear()
    source(None)
    (cut,) = seen
    sky = sky_stars()
    assert 0 < len(cut.ids) < 0.02 * len(sky.ids)
    full = render_frame(sky, att, CAM, DetectorModel(), seed=1).truth["stars"]
    part = render_frame(cut, att, CAM, DetectorModel(), seed=1).truth["stars"]
    assert part == full and len(full) > 5  # every star in the frame, nothing else


def test_cut_keeps_stars_at_the_corners():
    att = attitude_from_radec_roll(0.0, 0.0, 0.0)
    xs = np.array([-0.4, CAM.width - 0.6, -0.4, CAM.width - 0.6])
    ys = np.array([-0.4, -0.4, CAM.height - 0.6, CAM.height - 0.6])
    v = CAM.pixel_to_vector(xs, ys) @ att
    stars = Stars(np.arange(4), v, np.full(4, 5.0), np.ones(4), np.ones(4))
    assert len(stars_in_view(stars, att, CAM.fov_half_angle_diagonal + 1e-6).ids) == 4


def test_noise_bank_matches_fresh_noise_statistics():
    cam = CameraModel.from_fov(320, 240, 2.0)
    det = DetectorModel(sky_e_per_s=200.0, read_noise_e=4.0, hot_pixel_fraction=0.0)
    none = Stars(np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0))
    att = attitude_from_radec_roll(0.3, -0.4, 0.1)
    bank = NoiseBank(det, (cam.height, cam.width))
    fresh = render_frame(none, att, cam, det, seed=3).frame.pixels.astype(float)
    banked = [render_frame(none, att, cam, det, seed=s, noise=bank).frame.pixels.astype(float) for s in (3, 4)]
    for b in banked:
        assert b.mean() == pytest.approx(fresh.mean(), abs=0.05)
        assert b.var() == pytest.approx(fresh.var(), rel=0.03)
    assert not np.array_equal(banked[0], banked[1])  # another seed, another noise field
    again = render_frame(none, att, cam, det, seed=3, noise=bank).frame.pixels
    assert np.array_equal(again, banked[0])  # deterministic for a seed


def test_noise_bank_star_signal_keeps_its_mean():
    cam = CameraModel.from_fov(320, 240, 2.0)
    det = DetectorModel(pattern="MONO", prnu=0.0, dsnu_e=0.0, hot_pixel_fraction=0.0)
    att = attitude_from_radec_roll(0.3, -0.4, 0.1)
    star = Stars([1], cam.pixel_to_vector([160.2], [120.7]) @ att, [6.0], [1.0], [1.0])
    renderer = ExposureRenderer(cam, stars=star)
    totals = []
    for seed in range(20):
        px = renderer.render(att, det, seed).pixels.astype(float)
        totals.append((px[110:131, 150:171] - det.black_level_dn).sum() * det.gain_e_per_dn)
    background = 21 * 21 * (det.sky_e_per_s + det.dark_e_per_s) * det.exposure_s
    signal = float(det.green_electrons(6.0)) * 3  # mono: S_r + S_g + S_b with rg = bg = 1
    assert np.mean(totals) - background == pytest.approx(signal, rel=0.03)
