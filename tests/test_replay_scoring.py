"""Scoring of solve records against truth (ground.replay.score)."""

import numpy as np

from firmware_model.frames import attitude_from_radec_roll, matrix_to_quat
from ground.replay import Truth, score

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
