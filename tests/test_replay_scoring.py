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


def test_table5_with_no_frame_to_score_says_why_and_exits_2(tmp_path, capsys):
    """Issue 30: table5 on frames without truth printed an all-zero '(0 frames)' table, exit 0."""
    import pytest

    from firmware_model.catalog.image_io import catalog_to_image
    from firmware_model.pipeline.frame_readers import frame_files
    from ground.analysis.table5 import NothingToScore, table5
    from ground.arg_types import InputError
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.cli.main import main

    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(2):
        np.save(frames / f"f{k}.npy", np.zeros((48, 64), np.uint16))
    catalog = build_catalog(CatalogDesign(m_thresh=3.0))
    with pytest.raises(NothingToScore, match=r"none of the 2 frames in .*frames has truth: .*<stem>\.truth\.json"):
        table5(frame_files(frames), None, catalog, progress=False)
    with pytest.raises(InputError, match="no frame to score"):
        table5([], None, catalog, progress=False)
    image = tmp_path / "cat.st16cat"
    image.write_bytes(catalog_to_image(catalog))
    capsys.readouterr()
    assert main(["table5", str(frames), "--catalog", str(image)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "has truth: table5 scores frames against truth files" in err


def test_a_star_never_measured_in_colour_has_no_mean_colour_error():
    """Mono frames measure no colour (rg, bg NaN): table5's per-star mean colour error leaves such a
    star out instead of numpy's 'Mean of empty slice' warning."""
    import warnings

    from ground.analysis.table5 import _mean_colour_error

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _mean_colour_error([(np.nan, np.nan), (np.nan, np.nan)]) is None
        mean = _mean_colour_error([(0.1, -0.2), (np.nan, np.nan), (0.3, 0.0)])
    assert mean is not None and np.allclose(mean, [0.2, -0.1])
