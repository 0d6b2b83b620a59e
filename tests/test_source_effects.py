"""Detector effects in the device's sky sources (issue 33): a schedule's ``# effects:`` line and the
feed's URL options render radiation tracks, dose hot pixels and the detector at its temperature."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from firmware_model.camera import CameraModel
from ground.sim.detector_effects import effects_from_options
from ground.sim.exposure import ExposureRenderer
from ground.sim.sensor_sim import DetectorModel, Stars
from ground.sim.sky_source import SkySource, read_effects

CAM = CameraModel.from_fov(320, 240, 2.0)
NO_STARS = Stars([], np.zeros((0, 3)), [], [], [])
Q = "1,0,0,0"


def _source(tmp_path, header: str) -> SkySource:
    path = tmp_path / "s.csv"
    path.write_text(f"{header}qw,qx,qy,qz,seed\n{Q},1\n{Q},1\n")
    src = SkySource(str(path), CAM)
    src.renderer = ExposureRenderer(CAM, stars=NO_STARS)
    src.renderer.draw_bank(src.renderer.effective_detector(DetectorModel(), src.effects)).join()
    return src


def test_a_schedule_effects_line_renders_tracks_and_hot_pixels_from_the_rows_seed(tmp_path):
    plain = _source(tmp_path, "")
    hit = _source(tmp_path, "# effects: hits_per_frame=20 dose_krad=200 temperature_c=40\n")
    base = plain(SimpleNamespace(started=0.0, sequence=0))
    a, b = (hit(SimpleNamespace(started=0.0, sequence=k)) for k in range(2))
    truth = a.metadata["effects"]
    assert len(truth["cosmic"]["tracks"]) > 5 and truth["dose"]["new_hot_pixels"] > 0
    assert truth["dark_e_per_s"] > DetectorModel().dark_e_per_s  # 40 degC: more dark current than at 20
    assert np.array_equal(a.pixels, b.pixels)  # the same row seed: the same hits
    assert float(a.pixels.astype(float).mean()) > float(base.pixels.astype(float).mean())
    assert "effects" not in base.metadata


@pytest.mark.parametrize(
    "line, says",
    [
        ("# effects: cosmic_rate=-1\n", "line 1: effect option cosmic_rate=-1 is outside 0 to 1e+06"),
        ("# effects: cosmic_rates=4\n", "line 1: unknown effect option(s) ['cosmic_rates']"),
        ("# effects: saa=1\n", "line 1: effect option saa needs an orbit"),
        ("# effects: dose_krad=lots\n", "line 1: effect option dose_krad='lots' is not a number"),
        ("# effects: hits_per_frame\n", "line 1: expected KEY=VALUE items"),
    ],
)
def test_a_bad_effects_line_is_one_error_naming_its_line(tmp_path, line, says):
    path = tmp_path / "s.csv"
    path.write_text(f"{line}qw,qx,qy,qz\n{Q}\n")
    with pytest.raises(ValueError, match=r".*") as exc:
        read_effects(path, None)
    assert says in str(exc.value) and "\n" not in str(exc.value)


def test_the_feed_takes_effect_options_from_its_url():
    from ground.sim.attitude_feed import AttitudeFeedSource

    src = AttitudeFeedSource(
        "udp://127.0.0.1:0?pattern=MONO&hits_per_frame=5&temperature_c=30", CAM, ExposureRenderer(CAM, NO_STARS)
    )
    try:
        assert src.effects is not None and src.effects.cosmic.hits_per_frame == 5.0
        assert src.effects.temperature_c == 30.0
    finally:
        src.close()
    with pytest.raises(ValueError, match="unknown option"):
        AttitudeFeedSource("udp://127.0.0.1:0?hits=5", CAM, ExposureRenderer(CAM, NO_STARS))


def test_no_options_no_effects():
    assert effects_from_options({}) is None
