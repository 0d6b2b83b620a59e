"""The rendered availability run: the same rows whatever the worker count, scoring as replay's,
effects joined in order, and ``st16-ground sim availability``'s refusals and output."""

import json

import numpy as np
import pytest

from firmware_model.pipeline.run import run_pipeline
from ground.analysis import replay
from ground.cli import sim as cli_sim
from ground.cli.main import main
from ground.link.solve_report import record_from_output
from ground.sim import availability as av
from ground.sim import detector_effects as de
from ground.sim.sensor_sim import DetectorModel

EFFECTS = [de.MissionEffects(cosmic=de.CosmicRays(hits_per_frame=5.0), dose_krad=1.0, temperature_c=30.0)]


def test_constants_are_the_ones_they_stand_for():
    assert av.CORRECT_DEG == replay.CORRECT_DEG
    assert av.MATCH_RADIUS_PX == replay.MATCH_RADIUS_PX
    assert cli_sim.TEMPERATURE_RANGE_C == de.TEMPERATURE_RANGE_C


def test_rows_do_not_depend_on_the_worker_count_or_the_chunking():
    cfg = av.AvailabilityConfig(3, seed=2)
    one = av.run_availability(cfg, EFFECTS, workers=1, chunk=1)
    two = av.run_availability(cfg, EFFECTS, workers=2, chunk=2)
    assert [r["k"] for r in one] == [0, 1, 2]
    assert one == two
    assert av.summarise(one)["high_confidence_wrong"] == 0


def test_score_is_replays_score():
    cat, camera, sky, _ = av.reference_scene()
    from ground.sim.openloop import stars_in_cone

    for k in range(2):
        a = av.frame_attitude(5, k)
        stars = stars_in_cone(sky, a, camera.fov_half_angle_diagonal + np.radians(1.0))
        r = av.render_with_effects(stars, a, camera, DetectorModel(), EFFECTS, np.random.default_rng(k), 3)
        rec = record_from_output(run_pipeline(r.frame, camera, cat))
        ts = r.truth["stars"]
        truth = replay.Truth(
            r.truth["attitude_quaternion"],
            np.array([s["id"] for s in ts]),
            np.array([s["x"] for s in ts]),
            np.array([s["y"] for s in ts]),
        )
        ours, theirs = av.score(rec, a, ts), replay.score(rec, truth)
        assert ours["outcome"] == {"no_match": "no_solution"}.get(theirs["outcome"], theirs["outcome"])
        if rec["q_icrs_to_sensor"] is not None:
            assert ours["attitude_error_deg"] == pytest.approx(
                theirs["attitude_error_deg"], abs=1e-5
            )  # deg: via a quaternion
            assert ours["wrong_ids"] == theirs["wrong_ids"]
        # a wrong attitude (the truth turned by 1 deg about x) is scored wrong
        turned = np.array([[1, 0, 0], [0, np.cos(0.0175), -np.sin(0.0175)], [0, np.sin(0.0175), np.cos(0.0175)]]) @ a
        if rec["q_icrs_to_sensor"] is not None:
            assert av.score(rec, turned, ts)["outcome"] == "wrong"


def test_effects_apply_in_order_and_join():
    warm = de.MissionEffects(temperature_c=20.0 + 6.5)
    hits = de.MissionEffects(cosmic=de.CosmicRays(hits_per_frame=10.0), dose_krad=1.0)
    a = av.frame_attitude(1, 0)
    _, camera, sky, _ = av.reference_scene()
    from ground.sim.openloop import stars_in_cone

    stars = stars_in_cone(sky, a, camera.fov_half_angle_diagonal + 0.02)
    r = av.render_with_effects(stars, a, camera, DetectorModel(), [warm, hits], np.random.default_rng(0), 1)
    assert [e["effect"] for e in r.truth["effects"]] == ["MissionEffects", "MissionEffects"]
    assert r.truth["detector"]["dark_e_per_s"] == pytest.approx(2 * DetectorModel().dark_e_per_s)
    assert len(r.truth["false_objects"]) == len(r.truth["effects"][1]["cosmic"]["tracks"])
    assert r.frame.camera is None and r.frame.metadata["simulated"] is True


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--cosmic-rate", "-1"], "--cosmic-rate: a particle flux per cm^2 per s must be from 0.0"),
        (["--hits-per-frame", "-5"], "--hits-per-frame: a number of hits per frame must be from 0.0"),
        (["--dose-krad", "-0.1"], "--dose-krad: a dose in krad must be from 0.0"),
        (["--temperature-c", "90"], "--temperature-c: a detector temperature in degC must be from -40.0 to 85.0"),
        (["--cosmic-rate", "nan"], "--cosmic-rate: a particle flux per cm^2 per s must be from"),
        (["--saa", "--orbit", "50"], "--orbit: orbit altitude 50 km is outside 100-400000 km"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(argv, words, capsys):
    try:
        code = main(["sim", "availability", *argv])
    except SystemExit as exc:  # argparse's refusals (ground.cli.main.UsageError)
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and "Traceback" not in err[0], err


def test_cli_run_prints_json_and_writes_rows(tmp_path, capsys):
    out = tmp_path / "av"
    code = main(["sim", "availability", "--attitudes", "2", "--hits-per-frame", "5", "--json", "-o", str(out)])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 2 and summary["high_confidence_wrong"] == 0 and summary["frames_in_saa"] == 0
    assert summary["config"]["hits_per_frame"] == 5.0
    rows = json.loads((out / "availability_rows.json").read_text())
    assert [r["k"] for r in rows] == [0, 1] and all(r["n_hits"] >= 0 for r in rows)
    assert json.loads((out / "availability_summary.json").read_text()) == summary


def test_near_tracks_measures_the_distance_to_the_segment():
    track = [{"x": 10.0, "y": 10.0, "x2": 20.0, "y2": 10.0}]
    x = np.array([15.0, 15.0, 23.0, 24.0, 10.0])
    y = np.array([12.9, 13.1, 10.0, 10.0, 10.0])
    assert av.near_tracks(x, y, track).tolist() == [True, False, True, False, True]
    point = [{"x": 5.0, "y": 5.0, "x2": 5.0, "y2": 5.0}]  # a normal-incidence hit
    assert av.near_tracks(np.array([5.0, 9.0]), np.array([7.0, 5.0]), point).tolist() == [True, False]


def test_cli_saa_run_spreads_the_frames_over_one_day_of_the_orbit(tmp_path, capsys):
    from astropy.time import Time

    out = tmp_path / "saa"
    code = main(["sim", "availability", "--attitudes", "2", "--cosmic-rate", "4", "--saa", "--json", "-o", str(out)])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["config"]["saa"] is True and summary["config"]["orbit"] == "550"
    rows = json.loads((out / "availability_rows.json").read_text())
    t0, t1 = (Time(r["timestamp"].rstrip("Z"), scale="utc").unix for r in rows)
    assert t1 - t0 == pytest.approx(43200.0, abs=1e-3)  # 86400 s / 2 frames
    in_saa = [r["effects"][0]["cosmic"]["in_saa"] for r in rows]
    assert summary["frames_in_saa"] == sum(in_saa)
