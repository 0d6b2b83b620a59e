"""Bright-body exclusion (firmware_model.pipeline.exclusion; docs/pipeline.md "Bright-body
exclusion", docs/ICD.md sections 7, 9, 10): frames of stars only, rendered with a timestamp, whose
boresight is 5 deg, or half a degree, inside or outside a body's limit; the statuses, the
hardware.status bits, the reason, the check on every path (lost in space, tracked, blind
solve_image), the attitude memory of the device (its direction of propagation, OK answers only),
and the parameters' range."""

import copy
import json
from datetime import datetime, timedelta

import numpy as np
import pytest
from open_loop_sky import NOMINAL, PIXEL_RAD, POINTINGS, open_loop_catalog, render

from firmware_model.device.cli import main as device_main
from firmware_model.device.device import Device
from firmware_model.device.sensor_input import REJECT_PARAMS_VALUE, DeviceParams, PipelineSolver
from firmware_model.pipeline.exclusion import (
    BLIND_BACKGROUND_FRACTION,
    STATUS_OF,
    ExclusionLimits,
    LastAttitude,
    blinded,
    check_exclusion,
)
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.result_fields import result_fields
from firmware_model.pipeline.run import run_pipeline
from firmware_model.pipeline.sky_bodies import ATMOSPHERE_KM, EARTH_RADIUS_KM, sky_bodies
from firmware_model.pipeline.solve_types import PipelineParams
from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat, quat_to_matrix, rotation_angle
from ground.cli.main import main as ground_main
from ground.link.solve_report import format_record, record_from_output
from protocol import nsp, result, slip
from protocol.commands import Code, Slot, SlotRejected
from protocol.result import ExclusionBits, Status

EPOCH = "2026-06-10T00:00:00+00:00"  # the Sun ~29 deg from POINTINGS[0] (Orion), the Moon ~78 deg
OFF = ExclusionLimits(sun_deg=0.0, moon_deg=0.0, earth_deg=0.0)
SC_KM = 7000.0  # a spacecraft 622 km up


def _inside(edge_deg: float) -> float:
    """A whole-degree limit about 5 deg beyond a body's edge angle (the body inside it)."""
    return float(round(edge_deg) + 5)


def _outside(edge_deg: float) -> float:
    return float(round(edge_deg) - 5)


def _later(seconds: float) -> str:
    return (datetime.fromisoformat(EPOCH) + timedelta(seconds=seconds)).isoformat()


@pytest.fixture(scope="module")
def catalog():
    return open_loop_catalog()


@pytest.fixture(scope="module")
def scene():
    """(true attitude, stamped frame, edge angles in deg from its boresight by body)."""
    a, r = render(NOMINAL, POINTINGS[0], timestamp=EPOCH)
    edges = {n: np.degrees(b.edge_angle(a[2])) for n, b in sky_bodies(EPOCH).items()}
    return a, r.frame, edges


@pytest.fixture(scope="module")
def unchecked(scene, catalog):
    """The frame's answer with no check at all (each case checks a copy)."""
    out = run_pipeline(scene[1], NOMINAL, catalog, PipelineParams(exclusion=None))
    assert out.status is Status.OK, out.reason
    assert rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), scene[0]) < 2 * PIXEL_RAD  # the truth
    return out


def _earth_at(a, edge_deg: float) -> list[float]:
    """A GCRS position SC_KM from the geocentre whose Earth limb is ``edge_deg`` from ``a``'s boresight."""
    b = a[2]
    u = np.cross(b, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    theta = np.arcsin((EARTH_RADIUS_KM + ATMOSPHERE_KM) / SC_KM) + np.radians(edge_deg)
    centre = np.cos(theta) * b + np.sin(theta) * u
    return list(-SC_KM * centre)


def test_sun_inside_its_limit_gives_sun_in_fov_and_no_attitude(scene, catalog):
    a, frame, edges = scene
    limits = ExclusionLimits(sun_deg=_inside(edges["sun"]), moon_deg=0.0)
    out = run_pipeline(frame, NOMINAL, catalog, PipelineParams(exclusion=limits))
    assert out.status is Status.SUN_IN_FOV and out.solution is None and out.in_fov == ("sun",)
    assert out.reason.startswith(f"sun {edges['sun']:.1f} deg from the boresight, inside its {limits.sun_deg:g} deg")
    assert out.reason.endswith("by the solved attitude")
    fields = result_fields(out)
    assert fields["hardware.status"] == ExclusionBits.SUN_IN_FOV
    assert "quaternion" not in fields and "ext.quaternion" not in fields  # zero in the result
    rec = record_from_output(out)
    assert rec["status"] == "SUN_IN_FOV" and rec["q_icrs_to_sensor"] is None and rec["bodies_in_fov"] == ["sun"]
    assert "inside their exclusion angles: sun" in format_record(rec)
    parsed = result.parse(result.build({**fields, "ext.reason": out.reason.encode()[:96]}))
    assert not np.asarray(parsed["quaternion"]).any() and not np.asarray(parsed["ext"]["quaternion"]).any()
    assert result.status_of(int(parsed["return_code"])) is Status.SUN_IN_FOV


def test_sun_outside_its_limit_is_ok_as_before(scene, catalog):
    a, frame, edges = scene
    limits = ExclusionLimits(sun_deg=_outside(edges["sun"]), moon_deg=0.0)
    out = run_pipeline(frame, NOMINAL, catalog, PipelineParams(exclusion=limits))
    assert out.status is Status.OK and out.in_fov == () and out.reason == ""
    assert rotation_angle(quat_to_matrix(out.solution.q_icrs_to_sensor), a) < 2 * PIXEL_RAD
    assert "hardware.status" not in result_fields(out)


def test_the_earth_is_checked_only_with_a_position(scene, unchecked):
    a, frame, _ = scene
    limits = ExclusionLimits(sun_deg=0.0, moon_deg=0.0, earth_deg=25.0)
    assert check_exclusion(copy.deepcopy(unchecked), frame, limits).status is Status.OK  # no position
    for edge, status in ((20.0, Status.EARTH_IN_FOV), (30.0, Status.OK)):
        placed = Frame(frame.pixels, timestamp=EPOCH, metadata={"sc_position_km": _earth_at(a, edge)})
        out = check_exclusion(copy.deepcopy(unchecked), placed, limits)
        assert out.status is status, (edge, out.reason)
        if status is Status.EARTH_IN_FOV:
            assert out.reason.startswith("earth 20.0 deg from the boresight, inside its 25 deg exclusion")
            assert result_fields(out)["hardware.status"] == ExclusionBits.EARTH_IN_FOV
    inside_earth = Frame(frame.pixels, timestamp=EPOCH, metadata={"sc_position_km": [1000.0, 0.0, 0.0]})
    out = check_exclusion(copy.deepcopy(unchecked), inside_earth, limits)
    assert out.status is Status.OK and "bright bodies not checked: spacecraft position" in out.reason


def test_the_moon_inside_its_limit(scene, unchecked):
    _, frame, edges = scene
    out = check_exclusion(
        copy.deepcopy(unchecked), frame, ExclusionLimits(sun_deg=0.0, moon_deg=_inside(edges["moon"]))
    )
    assert out.status is Status.MOON_IN_FOV and out.solution is None
    assert out.reason.startswith(f"moon {edges['moon']:.1f} deg from the boresight")


def test_several_inside_the_sun_then_the_earth_then_the_moon_all_flagged(scene, unchecked):
    a, frame, edges = scene
    placed = Frame(frame.pixels, timestamp=EPOCH, metadata={"sc_position_km": _earth_at(a, 20.0)})
    every = ExclusionLimits(sun_deg=_inside(edges["sun"]), moon_deg=_inside(edges["moon"]), earth_deg=25.0)
    out = check_exclusion(copy.deepcopy(unchecked), placed, every)
    assert out.status is Status.SUN_IN_FOV and out.in_fov == ("sun", "earth", "moon")
    assert out.reason.endswith("by the solved attitude; also earth, moon")
    assert result_fields(out)["hardware.status"] == 0x0E00
    assert record_from_output(out)["bodies_in_fov"] == ["sun", "earth", "moon"]
    no_sun = check_exclusion(copy.deepcopy(unchecked), placed, ExclusionLimits(0.0, every.moon_deg, 25.0))
    assert no_sun.status is Status.EARTH_IN_FOV and no_sun.in_fov == ("earth", "moon")


def test_a_low_confidence_attitude_decides_too(scene, unchecked):
    _, frame, edges = scene
    low = copy.deepcopy(unchecked)
    low.status, low.reason = Status.LOW_CONFIDENCE, "consensus below eta"
    out = check_exclusion(low, frame, ExclusionLimits(sun_deg=_inside(edges["sun"]), moon_deg=0.0))
    assert out.status is Status.SUN_IN_FOV and out.solution is None


def test_without_a_timestamp_the_solve_stands_and_the_reason_says_so(scene, unchecked):
    _, frame, edges = scene
    bare = Frame(frame.pixels)
    out = check_exclusion(copy.deepcopy(unchecked), bare, ExclusionLimits(sun_deg=_inside(edges["sun"])))
    assert out.status is Status.OK and out.reason == "bright bodies not checked: the frame has no timestamp"
    assert check_exclusion(copy.deepcopy(unchecked), bare, OFF).reason == ""  # no limit set: nothing to say
    failed = copy.deepcopy(unchecked)
    failed.status, failed.solution, failed.reason = Status.NO_MATCH, None, "no match"
    assert check_exclusion(failed, bare, ExclusionLimits()).reason == "no match"  # no attitude: nothing to say


def _saturated(timestamp=EPOCH) -> Frame:
    return Frame(np.full((NOMINAL.height, NOMINAL.width), 4095, np.uint16), black_level=64, timestamp=timestamp)


def test_a_saturated_frame_with_no_attitude_memory_is_blinded(catalog):
    out = run_pipeline(_saturated(), NOMINAL, catalog)
    assert out.status is Status.BLINDED and out.reason == "blinded: 100 % of the pixels saturated"
    assert run_pipeline(_saturated(None), NOMINAL, catalog).status is Status.BLINDED  # an image test: no time needed
    assert run_pipeline(_saturated(), NOMINAL, catalog, PipelineParams(exclusion=None)).status is not Status.BLINDED


def test_the_blinded_thresholds():
    shape = (48, 64)
    level = 64 + BLIND_BACKGROUND_FRACTION * (4095 - 64)
    assert blinded(Frame(np.full(shape, int(np.ceil(level)), np.uint16), black_level=64)).startswith(
        "blinded: background"
    )
    assert blinded(Frame(np.full(shape, int(level) - 2, np.uint16), black_level=64)) is None
    half = np.full(shape, 100, np.uint16)
    half[: shape[0] // 2] = 4095
    assert blinded(Frame(half, black_level=64)) == "blinded: 50 % of the pixels saturated"
    half[0, 0] = 100
    assert blinded(Frame(half, black_level=64)) is None


def test_a_remembered_attitude_turns_at_the_trackers_rate():
    q = matrix_to_quat(np.eye(3))
    omega = np.radians([0.0, 0.0, 2.0])  # deg/s about the boresight
    last = LastAttitude(q, 100.0, omega)
    turned = last.recall(103.0, 10.0)
    assert turned.age_s == 3.0 and np.degrees(rotation_angle(quat_to_matrix(turned.q), np.eye(3))) == pytest.approx(6.0)
    assert LastAttitude(q, 100.0).recall(103.0, 10.0).q.tolist() == q.tolist()  # no rate: held
    assert last.recall(110.5, 10.0) is None and last.recall(99.0, 10.0) is None  # too old, or a later frame's


def test_a_remembered_attitude_turns_the_way_the_sensor_turns():
    """The direction, not only the angle: a sensor turning at +2 deg/s about its x axis carries
    its boresight (sensor +z, in ICRS) towards -y of the starting frame (``v_sensor = A v``,
    ``A(t + dt) = R(-omega dt) A``, docs/CONVENTIONS.md), as the tracker's own prediction does."""
    from firmware_model.ident.attitude import quat_matrix
    from firmware_model.ident.tracking import TrackState, predict

    a0 = quat_to_matrix(matrix_to_quat(np.eye(3)))
    omega = np.radians([2.0, 0.0, 0.0])
    turned = quat_to_matrix(LastAttitude(matrix_to_quat(a0), 100.0, omega).recall(103.0, 10.0).q)
    six = np.radians(6.0)
    np.testing.assert_allclose(turned[2], [0.0, -np.sin(six), np.cos(six)], atol=1e-12)  # the boresight in ICRS
    state = TrackState.from_fix(matrix_to_quat(a0), np.eye(3) * 1e-12, 100.0, omega=omega)
    assert rotation_angle(turned, quat_matrix(predict(state, 103.0).q)) < 1e-12  # the tracker's kinematics
    a1 = attitude_from_radec_roll(*np.radians([83.8, -5.4, 20.0]))  # any attitude: omega is in sensor axes
    turned1 = quat_to_matrix(LastAttitude(matrix_to_quat(a1), 0.0, omega).recall(3.0, 10.0).q)
    np.testing.assert_allclose(a1 @ turned1[2], [0.0, -np.sin(six), np.cos(six)], atol=1e-9)


@pytest.mark.parametrize("body", ["sun", "moon"])
def test_a_body_half_a_degree_inside_its_limit_is_excluded_and_half_a_degree_outside_is_not(scene, unchecked, body):
    """The limit itself, not 5 deg either side of it: a check off by more than half a degree fails."""
    _, frame, edges = scene
    others = {"sun_deg": 0.0, "moon_deg": 0.0}
    inside = check_exclusion(
        copy.deepcopy(unchecked), frame, ExclusionLimits(**{**others, f"{body}_deg": edges[body] + 0.5})
    )
    assert inside.status is STATUS_OF[body] and inside.solution is None and inside.in_fov == (body,), inside.reason
    outside = check_exclusion(
        copy.deepcopy(unchecked), frame, ExclusionLimits(**{**others, f"{body}_deg": edges[body] - 0.5})
    )
    assert outside.status is Status.OK and outside.in_fov == () and outside.solution is not None, outside.reason


def test_the_earth_half_a_degree_either_side_of_its_limit(scene, unchecked):
    a, frame, _ = scene
    limits = ExclusionLimits(sun_deg=0.0, moon_deg=0.0, earth_deg=25.0)
    for edge, status in ((24.5, Status.EARTH_IN_FOV), (25.5, Status.OK)):
        placed = Frame(frame.pixels, timestamp=EPOCH, metadata={"sc_position_km": _earth_at(a, edge)})
        assert check_exclusion(copy.deepcopy(unchecked), placed, limits).status is status, edge


def test_the_tracked_path_is_checked_for_bright_bodies(scene, catalog):
    """A frame the tracker follows (no lost-in-space solve) with the Sun inside its limit:
    SUN_IN_FOV by the tracked attitude, as a lost-in-space answer would be."""
    from firmware_model.ident.solver import Method
    from firmware_model.ident.tracking import TrackState
    from firmware_model.pipeline.tracking_run import Tracker

    a, frame, edges = scene

    def tracker():
        return Tracker(state=TrackState.from_fix(matrix_to_quat(a), np.eye(3) * (PIXEL_RAD / 10) ** 2, 0.0))

    sun_in = PipelineParams(optics=None, exclusion=ExclusionLimits(sun_deg=_inside(edges["sun"]), moon_deg=0.0))
    tracked = tracker().solve(frame, 0.1, NOMINAL, catalog, PipelineParams(optics=None, exclusion=None))
    assert tracked.status is Status.OK and tracked.solution.method is Method.TRACKING, tracked.reason  # tracked
    assert rotation_angle(quat_to_matrix(tracked.solution.q_icrs_to_sensor), a) < 2 * PIXEL_RAD
    out = tracker().solve(frame, 0.1, NOMINAL, catalog, sun_in)
    assert out.status is Status.SUN_IN_FOV and out.solution is None and out.in_fov == ("sun",), out.reason
    assert out.reason.endswith("by the solved attitude")


def test_a_blind_solve_image_is_checked_for_bright_bodies(scene, tmp_path):
    """solve_image with no camera (the field of view searched against the whole-sky database, built
    in this run's own cache): a FITS frame stamped with its time, the Sun inside its limit ->
    SUN_IN_FOV; outside it -> OK at the true attitude."""
    from ground.api import solve_image
    from ground.sim.frame_writer import write_fits

    a, frame, edges = scene
    path = write_fits(frame, tmp_path / "orion.fits")
    ok = solve_image(path, params=PipelineParams(exclusion=ExclusionLimits(sun_deg=_outside(edges["sun"]))))
    assert ok.status == "OK", ok.reason
    assert rotation_angle(quat_to_matrix(ok.q_icrs_to_sensor), a) < 2 * PIXEL_RAD
    sun_in = solve_image(path, params=PipelineParams(exclusion=ExclusionLimits(sun_deg=_inside(edges["sun"]))))
    assert sun_in.status == "SUN_IN_FOV" and sun_in.q_icrs_to_sensor is None, sun_in.reason


# ------------------------------------------------------------------ the device's attitude memory


def _send(dev, code, data=b""):
    (frame,) = dev.receive(nsp.command(nsp.DEVICE_ADDRESS, 0x11, code, data).frame())
    return nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(frame)[0].data)


class Frames:
    """Capture source: the next frame of a list."""

    def __init__(self, frames):
        self.frames = list(frames)

    def __call__(self, ctx):
        return self.frames.pop(0)


def _go(dev, params: DeviceParams):
    dev.transfers.objects[Slot.PARAMS] = params
    assert _send(dev, Code.GO, bytes([0x0B])).ack
    assert dev.wait_idle(60)
    return result.parse(dev.runner.result)


def _reason(rec) -> str:
    return bytes(rec["ext"]["reason"]).rstrip(b"\0").decode()


@pytest.mark.parametrize("memory_s, status", [(10.0, Status.SUN_IN_FOV), (0.5, Status.BLINDED)])
def test_a_blinded_frame_after_a_fix_is_judged_by_the_last_attitude(scene, catalog, memory_s, status):
    """An OK solve, then a saturated frame 1 s later with the Sun inside the (new) limit by the
    remembered attitude: SUN_IN_FOV, bit 9, the attitude's age in the reason; with a memory
    shorter than 1 s: BLINDED."""
    a, frame, edges = scene
    dev = Device(
        solver=PipelineSolver(NOMINAL, PipelineParams(optics=None)),
        frame_source=Frames([frame, _saturated(_later(1.0))]),
    )
    dev.transfers.objects[Slot.CATALOG] = catalog
    assert _send(dev, Code.INIT, (0x2000).to_bytes(4, "little")).ack
    fix = _go(dev, DeviceParams(sun_exclusion_deg=_outside(edges["sun"]), moon_exclusion_deg=0.0))
    assert result.status_of(int(fix["return_code"])) is Status.OK
    assert rotation_angle(quat_to_matrix(np.asarray(fix["quaternion"], float)), a) < 2 * PIXEL_RAD  # the truth
    rec = _go(
        dev, DeviceParams(sun_exclusion_deg=_inside(edges["sun"]), moon_exclusion_deg=0.0, exclusion_memory_s=memory_s)
    )
    assert result.status_of(int(rec["return_code"])) is status, _reason(rec)
    assert not np.asarray(rec["quaternion"]).any()
    if status is Status.SUN_IN_FOV:
        assert _reason(rec).endswith("by the last attitude, 1.0 s old")
        assert int(rec["hardware"]["status"]) & ExclusionBits.SUN_IN_FOV
        assert int(rec["hardware"]["status"]) & result.HW_STATUS_MIRROR == Status.SUN_IN_FOV  # mirrored as before
    else:
        assert _reason(rec) == "blinded: 100 % of the pixels saturated"
        assert not int(rec["hardware"]["status"]) & 0x0E00


def test_a_low_confidence_answer_is_not_remembered_and_a_blinded_frame_after_it_is_blinded(scene, catalog, monkeypatch):
    """Only OK attitudes are remembered: a LOW_CONFIDENCE answer (its attitude right, here) then a
    saturated frame 1 s later with the Sun inside the limit by that attitude: BLINDED, not
    SUN_IN_FOV (nothing remembered); after an OK answer the same frame is SUN_IN_FOV."""
    from firmware_model.device import sensor_input

    _, frame, edges = scene
    solver = PipelineSolver(NOMINAL, PipelineParams(optics=None))
    real = sensor_input.run_pipeline

    def low_confidence(*args, **kw):
        out = real(*args, **kw)
        if out.status is Status.OK:
            out.status, out.reason = Status.LOW_CONFIDENCE, "consensus below eta (the test's)"
        return out

    monkeypatch.setattr(sensor_input, "run_pipeline", low_confidence)
    dev = Device(solver=solver, frame_source=Frames([frame, _saturated(_later(1.0))]))
    dev.transfers.objects[Slot.CATALOG] = catalog
    assert _send(dev, Code.INIT, (0x2000).to_bytes(4, "little")).ack
    low = _go(dev, DeviceParams(sun_exclusion_deg=_outside(edges["sun"]), moon_exclusion_deg=0.0))
    assert result.status_of(int(low["return_code"])) is Status.LOW_CONFIDENCE, _reason(low)
    assert np.asarray(low["quaternion"]).any()  # an attitude was reported, with low confidence
    rec = _go(dev, DeviceParams(sun_exclusion_deg=_inside(edges["sun"]), moon_exclusion_deg=0.0))
    assert result.status_of(int(rec["return_code"])) is Status.BLINDED, _reason(rec)
    assert _reason(rec) == "blinded: 100 % of the pixels saturated"
    assert not int(rec["hardware"]["status"]) & 0x0E00
    assert solver.last is None  # nothing remembered


# ------------------------------------------------------------------ the parameters


@pytest.mark.parametrize("key", ["sun_exclusion_deg", "moon_exclusion_deg", "earth_exclusion_deg"])
def test_exclusion_angles_outside_0_90_are_refused(key):
    for bad in (-1, 90.5, "30", True, None):
        if bad is None:
            continue
        with pytest.raises(SlotRejected) as err:
            DeviceParams.from_json(json.dumps({key: bad}).encode())
        assert err.value.code == REJECT_PARAMS_VALUE
        assert err.value.message == f"{key} must be a number in [0, 90] deg, got {bad!r}"
    for good in (0, 90, 12.5):
        assert getattr(DeviceParams.from_json(json.dumps({key: good}).encode()), key) == good


def test_the_memory_parameter_and_what_the_parameters_set():
    with pytest.raises(SlotRejected) as err:
        DeviceParams.from_json(b'{"exclusion_memory_s": 3601}')
    assert err.value.message == "exclusion_memory_s must be a number in [0, 3600] s, got 3601"
    params = DeviceParams.from_json(b'{"sun_exclusion_deg": 40, "exclusion_memory_s": 0}').apply(PipelineParams())
    assert params.exclusion == ExclusionLimits(sun_deg=40.0, memory_s=0.0)  # the others at their defaults
    assert DeviceParams().apply(PipelineParams()).exclusion == ExclusionLimits()
    assert DeviceParams(moon_exclusion_deg=5.0).apply(PipelineParams(exclusion=None)).exclusion == ExclusionLimits(
        moon_deg=5.0
    )


def test_an_out_of_range_angle_is_one_line_and_exit_2_on_the_command_line(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"earth_exclusion_deg": 120}')
    assert device_main(["--pty", "--params", str(bad)]) == 2  # before a link is opened
    err = capsys.readouterr()
    assert "listening" not in err.out and err.err.count("\n") == 1 and "earth_exclusion_deg" in err.err
    assert ground_main(["--port", "/nonexistent", "params", "upload", str(bad)]) == 2  # refused locally
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "[0, 90] deg" in err
    frame = tmp_path / "frame.npy"
    np.save(frame, np.zeros((48, 64), np.uint16))
    assert ground_main(["solve-file", str(frame), "--fov-deg", "10", "--params", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "earth_exclusion_deg" in err and "Traceback" not in err


@pytest.mark.parametrize(
    "timestamp, metadata",
    [("not a time", {}), (EPOCH, {"sc_position_km": [7000.0, 0.0]}), (EPOCH, {"sc_position_km": "far"})],
)
def test_an_unreadable_time_or_position_leaves_the_answer_and_says_so(scene, unchecked, timestamp, metadata):
    _, frame, _ = scene
    odd = Frame(frame.pixels, timestamp=timestamp, metadata=metadata)
    out = check_exclusion(copy.deepcopy(unchecked), odd, ExclusionLimits())
    assert out.status is Status.OK and out.solution is not None
    assert out.reason.startswith("bright bodies not checked: ") and "\n" not in out.reason


def test_the_bench_places_the_sun_at_the_asked_edge_angle():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import bench_exclusion

    sun = sky_bodies(bench_exclusion.EPOCH)["sun"]
    rng = np.random.default_rng(1)
    for edge in (15.0, 27.0, 90.0):
        a = bench_exclusion.attitude_near_sun(rng, sun, edge)
        assert np.degrees(sun.edge_angle(a[2])) == pytest.approx(edge, abs=1e-9)


def test_a_negative_centroid_variance_is_not_used(scene):
    """A glare frame's degenerate fit reported -8e17 px^2 with no flag (bench_exclusion, limit 30,
    x0.5, frame 75): the solver's noise became NaN and run_pipeline raised. Such a row is unusable."""
    from dataclasses import replace

    from firmware_model.pipeline.extract import extract_stars
    from firmware_model.pipeline.frame_identification import usable_rows

    stars = extract_stars(scene[1], NOMINAL)
    assert len(usable_rows(stars)) == len(stars)
    cov = stars.cov_xy.copy()
    cov[0, 0, 0] = -8e17
    assert (
        0 not in usable_rows(replace(stars, cov_xy=cov))
        and len(usable_rows(replace(stars, cov_xy=cov))) == len(stars) - 1
    )
