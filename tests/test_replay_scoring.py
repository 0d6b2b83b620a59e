"""Scoring of solve records against truth (ground.analysis.replay.score)."""

import numpy as np

from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat
from ground.analysis.replay import Truth, score

A = attitude_from_radec_roll(1.0, 0.3, 2.0)
Q = matrix_to_quat(A).tolist()


def record(q, stars):
    return {"q_icrs_to_sensor": q, "stars": [{"x": x, "y": y, "catalog_id": cid} for x, y, cid in stars]}


def test_scores_correct_wrong_and_no_match():
    truth = Truth(np.array(Q), np.array([10, 11, 12]), np.array([100.0, 200.0, 201.0]), np.array([50.0, 80.0, 80.5]))
    assert score(record(Q, [(100.2, 50.1, 10)]), truth)["outcome"] == "correct"
    # a blend: the detection between stars 11 and 12 may carry either id
    assert score(record(Q, [(200.5, 80.2, 12)]), truth)["outcome"] == "correct"
    bad = score(record(Q, [(100.2, 50.1, 11)]), truth)
    assert bad["outcome"] == "wrong" and bad["wrong_ids"] == 1
    rotated = matrix_to_quat(attitude_from_radec_roll(1.0, 0.3, 2.01)).tolist()  # 0.57 deg off
    far = score(record(rotated, []), truth)
    assert far["outcome"] == "wrong" and 0.5 < far["attitude_error_deg"] < 0.6
    assert score({"q_icrs_to_sensor": None, "stars": []}, truth) == {"outcome": "no_match"}
    assert score(record(Q, []), None) == {"outcome": "unscored"}


def test_a_malformed_or_foreign_truth_file_is_not_scored_and_says_why(tmp_path):
    import json

    from firmware_model.pipeline.raw_frame import Frame

    frame = Frame(pixels=np.zeros((40, 60), np.uint16), pattern="MONO", metadata={"seed": 5})
    good = {
        "seed": 5,
        "camera": {"width": 60, "height": 40},
        "attitude_quaternion": [1, 0, 0, 0],
        "stars": [{"id": 7, "x": 3.0, "y": 4.0}],
    }
    cases = {
        "garbage": "{not json",
        "no_quaternion": json.dumps({"stars": []}),
        "bad_star": json.dumps({**good, "stars": [{"x": 1}]}),
        "other_size": json.dumps({**good, "camera": {"width": 2592, "height": 1944}}),
        "other_seed": json.dumps({**good, "seed": 6}),
    }
    for name, text in cases.items():
        (tmp_path / f"{name}.truth.json").write_text(text)
        said = []
        assert Truth.for_frame(tmp_path / f"{name}.dng", frame, said.append) is None, name
        assert len(said) == 1 and "not scored" in said[0], (name, said)
    (tmp_path / "ok.truth.json").write_text(json.dumps(good))
    said = []
    truth = Truth.for_frame(tmp_path / "ok.dng", frame, said.append)
    assert truth is not None and not said and truth.stars_near(3.2, 4.1) == {7}
    assert Truth.for_frame(tmp_path / "absent.dng", frame, said.append) is None and not said
