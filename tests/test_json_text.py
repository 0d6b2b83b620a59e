"""Strict JSON out of the ground tool: NaN and infinities are null, numpy values plain."""

import json

import numpy as np
import pytest

from ground import json_text


def _strict(text):
    def refuse(name):
        raise ValueError(f"non-JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_values_become_null_and_numpy_values_plain():
    obj = {
        "a": float("nan"),
        "b": np.float32(1.5),
        "c": np.array([1.0, np.inf]),
        "d": [np.int64(3), -np.inf],
        "e": (1, "x", None),
    }
    assert _strict(json_text.dumps(obj)) == {"a": None, "b": 1.5, "c": [1.0, None], "d": [3, None], "e": [1, "x", None]}


def test_what_it_cannot_represent_is_refused():
    with pytest.raises(TypeError):
        json_text.dumps({"x": object()})


def test_the_results_log_is_strict_json(tmp_path):
    from ground.analysis.results_log import ResultsLog

    log = ResultsLog(tmp_path)
    log.append(
        {
            "frame": "f.dng",
            "outcome": "no_match",
            "status": "NO_MATCH",
            "sigma_arcsec": [np.nan, 1.0, np.inf],
            "q_icrs_to_sensor": None,
        }
    )
    rows = [_strict(line) for line in (tmp_path / "results.jsonl").read_text().splitlines()]
    assert rows[0]["sigma_arcsec"] == [None, 1.0, None]
