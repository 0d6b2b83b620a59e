"""Issue 40, sections 3, 4, 5 and 9: every effect rate, seed, pattern, time and position of the
device's sky sources is bounded and checked at start-up in one line naming the file and the row
or line (or the feed's option); positions inside the Moon or the Sun, and interpolated feed
positions, are refused; a schedule is read once (a pipe works); a feed whose every sample was bad
says why."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
from types import SimpleNamespace

import numpy as np
import pytest
from manual_clock import ManualClock

from firmware_model.camera import CameraModel
from firmware_model.device.device import FrameUnavailable
from firmware_model.pipeline.planets import astrometric_positions
from ground.sim.attitude_feed import AttitudeFeedSource
from ground.sim.exposure import ExposureRenderer
from ground.sim.feed_wire import Sample
from ground.sim.sensor_sim import Stars
from ground.sim.sky_source import Schedule, SkySource, check_position

CAM = CameraModel.from_fov(320, 240, 2.0)
NO_STARS = Stars([], np.zeros((0, 3)), [], [], [])
Q = "1,0,0,0"
WHEN = "2026-12-05T12:00:00"


def _write(tmp_path, text: str):
    path = tmp_path / "sched.csv"
    path.write_text(text)
    return path


ROW_CASES = [
    ("pattern", f"qw,qx,qy,qz,pattern\n{Q},XYZW\n", "row 1: pattern 'XYZW' is not one of"),
    ("seed -5", f"qw,qx,qy,qz,seed\n{Q},-5\n", "row 1: seed '-5' is not a whole number from 0"),
    ("seed abc", f"qw,qx,qy,qz,seed\n{Q},1\n{Q},abc\n", "row 2: seed 'abc' is not a whole number"),
    ("year 1", f"qw,qx,qy,qz,time\n{Q},0001-01-01T00:00:00\n", "row 1: time '0001-01-01T00:00:00' is before 1972"),
    ("23:59:60", f"qw,qx,qy,qz,time\n{Q},2026-12-05T23:59:60\n", "second 60 on a day without a leap second"),
    ("2040", f"qw,qx,qy,qz,time\n{Q},2040-01-01T00:00:00\n", "row 1: time '2040-01-01T00:00:00' is not a valid"),
    ("saa", f"# orbit: 550\n# effects: saa=maybe\nqw,qx,qy,qz\n{Q}\n", "line 2: effect option saa='maybe' is not"),
    ("duplicate", f"# effects: cosmic_rate=4 cosmic_rate=1e12\nqw,qx,qy,qz\n{Q}\n", "cosmic_rate given twice"),
    ("hits", f"# effects: hits_per_frame=1e6\nqw,qx,qy,qz\n{Q}\n", "hits_per_frame=1e6 is outside 0 to 5000"),
    ("hits 1e20", f"# effects: hits_per_frame=1e20\nqw,qx,qy,qz\n{Q}\n", "hits_per_frame=1e20 is outside"),
    ("flux", f"# effects: cosmic_rate=1e12\nqw,qx,qy,qz\n{Q}\n", "cosmic_rate=1e12 is outside 0 to 1e+06"),
    ("inf", f"# effects: cosmic_rate=inf\nqw,qx,qy,qz\n{Q}\n", "cosmic_rate=inf is outside"),
    ("nan", f"# effects: dose_krad=nan\nqw,qx,qy,qz\n{Q}\n", "dose_krad=nan is outside"),
    ("dose", f"# effects: dose_krad=1e5\nqw,qx,qy,qz\n{Q}\n", "dose_krad=1e5 is outside 0 to 10000"),
    ("temperature", f"# effects: temperature_c=200\nqw,qx,qy,qz\n{Q}\n", "temperature_c=200 is outside -40 to 85"),
    ("epoch", f"# orbit: 550,97.6,0,0,2026-12-05T23:59:60\nqw,qx,qy,qz\n{Q}\n", "line 1: orbit"),
]


@pytest.mark.parametrize("text, says", [c[1:] for c in ROW_CASES], ids=[c[0] for c in ROW_CASES])
def test_a_bad_schedule_value_is_one_line_naming_file_and_row_at_start(tmp_path, text, says):
    path = _write(tmp_path, text)
    with pytest.raises(ValueError) as info:
        SkySource(str(path), CAM)
    msg = str(info.value)
    assert msg.startswith(f"{path}: ") and says in msg and "\n" not in msg


def test_flux_over_the_exposure_is_bounded_in_hits_per_frame(tmp_path):
    """A flux within its own range that would put more hits in a frame than the source renders."""
    path = _write(tmp_path, f"# effects: cosmic_rate=1e6\nqw,qx,qy,qz\n{Q}\n")
    big = CameraModel.reference_design()
    with pytest.raises(ValueError, match="radiation hits per frame .* more than the 5000"):
        SkySource(str(path), big)


def test_a_position_inside_the_moon_or_the_sun_is_refused(tmp_path):
    bodies = astrometric_positions(WHEN, ("moon", "sun"))
    moon = bodies["moon"] + np.array([100.0, 0.0, 0.0])  # 100 km from the Moon's centre
    assert "inside the Moon" in (check_position(moon, WHEN) or "")
    assert check_position(bodies["sun"], WHEN)  # inside the Sun, and beyond the farthest position
    assert check_position(np.array([7000.0, 0.0, 0.0]), WHEN) is None
    path = _write(tmp_path, f"qw,qx,qy,qz,time,x_km,y_km,z_km\n{Q},{WHEN},{moon[0]},{moon[1]},{moon[2]}\n")
    with pytest.raises(ValueError, match=r"row 1: position is inside the Moon \(\d+ km from its centre"):
        Schedule.read(path)


def test_a_row_position_that_is_inside_the_moon_at_the_go_time_is_bad_frame(tmp_path):
    """Without a time the position is judged at the exposure: BAD_FRAME, never a render."""
    clock = ManualClock()
    moon = astrometric_positions(_iso(clock.now + 0.05), ("moon",))["moon"]
    path = _write(tmp_path, f"qw,qx,qy,qz,x_km,y_km,z_km\n{Q},{moon[0]},{moon[1]},{moon[2]}\n")
    src = SkySource(str(path), CAM)
    src.renderer = ExposureRenderer(CAM, stars=NO_STARS)
    with pytest.raises(FrameUnavailable, match="sky schedule row 1: position is inside the Moon") as info:
        src(SimpleNamespace(started=clock.now, sequence=1))
    assert "\n" not in str(info.value)


def _iso(t: float) -> str:
    from ground.sim.orbit import utc_iso

    return utc_iso(t)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


FEED_CASES = [
    ("pattern=XYZW", "unknown CFA pattern 'XYZW'"),
    ("hits_per_frame=1e5", "hits_per_frame=1e5 is outside 0 to 5000"),
    ("cosmic_rate=1e12", "cosmic_rate=1e12 is outside"),
    ("cosmic_rate=inf", "cosmic_rate=inf is outside"),
    ("cosmic_rate=4&cosmic_rate=5", "option(s) ['cosmic_rate'] given twice"),
    ("saa=maybe&orbit=550", "saa='maybe' is not one of"),
    ("exposure=inf", "exposure=inf s is outside (0, 10]"),
    ("timeout=nan", "timeout=nan s is outside [0, 60]"),
    ("max_gap=1e9", "max_gap=1e9 s is outside"),
    ("idle=-1", "idle=-1 s is outside"),
    ("exposure=10&cosmic_rate=1e6", "radiation hits per frame"),
    ("orbit=550,97.6,0,0,2026-12-05T23:59:60", "second 60 on a day without a leap second"),
]


@pytest.mark.parametrize("query, says", FEED_CASES, ids=[c[0] for c in FEED_CASES])
def test_a_bad_feed_option_is_one_line_at_start(query, says):
    with pytest.raises(ValueError) as info:
        AttitudeFeedSource(f"udp://127.0.0.1:{_free_udp_port()}?{query}", CAM, ExposureRenderer(CAM, stars=NO_STARS))
    msg = str(info.value)
    assert msg.startswith("attitude feed 'udp://") and says in msg and "\n" not in msg


def _feed_source(query: str = ""):
    clock = ManualClock()
    renderer = ExposureRenderer(CAM, stars=NO_STARS)
    src = AttitudeFeedSource(f"udp://127.0.0.1:{_free_udp_port()}?pattern=MONO{query}", CAM, renderer, clock)
    src.ready()
    return src, clock


def test_an_interpolated_feed_position_inside_the_earth_is_bad_frame_with_its_reason():
    """Samples alternating +7000 / -7000 km are each fine; between them the position passes
    near the geocentre: BAD_FRAME naming it, never a render (it used to be SOLVER_ERROR)."""
    src, clock = _feed_source()
    try:
        now = clock.now
        for k, t in enumerate(np.arange(now - 1, now + 1, 0.1)):
            r = np.array([7000.0 if k % 2 else -7000.0, 100.0, 0.0])
            src.feed.offer(Sample(float(t), np.array([1.0, 0, 0, 0]), np.zeros(3), r))
        assert not src.feed.faults()  # every sample alone is sound
        with pytest.raises(FrameUnavailable, match="interpolated sample position .* inside the atmosphere") as info:
            src(SimpleNamespace(started=now, sequence=1))
        assert "\n" not in str(info.value)
    finally:
        src.close()


def test_a_feed_orbit_through_the_moon_is_bad_frame():
    clock = ManualClock()
    moon = astrometric_positions(_iso(clock.now + 0.05), ("moon",))["moon"]
    src, clock = _feed_source("&orbit=550")
    try:
        src.orbit = _orbit_at(moon)
        now = clock.now
        for t in np.arange(now - 1, now + 1, 0.02):
            src.feed.offer(Sample(float(t), np.array([1.0, 0, 0, 0]), np.zeros(3)))
        with pytest.raises(FrameUnavailable, match="attitude feed: orbit position is inside the Moon"):
            src(SimpleNamespace(started=now, sequence=1))
    finally:
        src.close()


def _orbit_at(point):
    """A stand-in orbit that is at ``point`` whenever asked."""
    return SimpleNamespace(position_gcrs_km=lambda t: np.asarray(point, float))


def test_a_feed_whose_every_sample_was_bad_names_the_fault():
    src, clock = _feed_source("&timeout=0")
    try:
        now = clock.now
        for t in np.arange(now - 1, now + 1, 0.1):
            src.feed.offer(Sample(float(t), np.array([1.0, 0, 0, 0]) * 1.1, np.zeros(3)))
        clock.advance(1.0)  # past the capture's wait
        with pytest.raises(FrameUnavailable) as info:
            src(SimpleNamespace(started=now, sequence=1))
        assert "quaternion norm 1.100000000 is not 1" in str(info.value)
        assert "no sample received" not in str(info.value)
    finally:
        src.close()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs a FIFO")
def test_a_schedule_from_a_pipe_keeps_its_orbit_and_effects(tmp_path):
    """``--sky <(cat sched.csv)``: the schedule is read once (it used to be read three times, and
    the orbit and effects lines, read from the emptied pipe, were lost)."""
    text = f"# orbit: 550,97.6\n# effects: cosmic_rate=4 dose_krad=10\nqw,qx,qy,qz\n{Q}\n"
    fifo = tmp_path / "sched.fifo"
    os.mkfifo(fifo)

    def feed() -> None:
        with open(fifo, "w") as f:
            f.write(text)

    writer = threading.Thread(target=feed, daemon=True)
    writer.start()
    sched = Schedule.read(fifo)
    writer.join(60)
    assert sched.orbit is not None and sched.orbit.altitude_km == 550.0
    assert sched.effects is not None and sched.effects.dose_krad == 10.0 and len(sched.rows) == 1


def test_the_device_refuses_a_bad_schedule_in_one_line_exit_2(tmp_path):
    path = _write(tmp_path, f"qw,qx,qy,qz,seed\n{Q},abc\n")
    proc = subprocess.run(
        [sys.executable, "-m", "firmware_model.device.cli", "--pty", "--sky", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"st16-device: {path}: row 1: seed 'abc' is not a whole number from 0 to 4294967295"
    ]


def test_sim_availability_refuses_a_flux_that_fills_a_long_exposure(capsys):
    from ground.cli.main import main

    code = main(["sim", "availability", "--cosmic-rate", "1e6", "--exposure-ms", "60000", "--attitudes", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "more than the 100000 a frame may hold" in err[0]


def test_the_source_limits_match_the_command_lines():
    from ground import arg_types
    from ground.sim import detector_effects as de

    for parse, limit in [
        (arg_types.FLUX_PER_CM2_S, de.MAX_COSMIC_RATE),
        (arg_types.HITS_PER_FRAME, de.MAX_HITS_PER_FRAME),
        (arg_types.DOSE_KRAD, de.MAX_DOSE_KRAD),
    ]:
        assert parse(repr(limit)) == limit
        with pytest.raises(Exception, match="must be from"):
            parse(repr(limit * 1.0001))
