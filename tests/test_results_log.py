import csv

import numpy as np

from ground.analysis.results_log import ResultsLog, plot_summary, summarize


def test_log_appends_jsonl_and_csv_and_summarizes(tmp_path):
    log = ResultsLog(tmp_path)
    log.append(
        {
            "frame": "a",
            "outcome": "correct",
            "attitude_error_deg": 0.002,
            "solve_s": 0.1,
            "q_icrs_to_sensor": np.array([1.0, 0, 0, 0]),
            "residuals_arcsec": [1.0, 2.0],
        }
    )
    log.append({"frame": "b", "outcome": "wrong", "attitude_error_deg": 12.0, "solve_s": 0.3})
    log.append({"frame": "c", "outcome": "no_match", "reason": "too few stars"})
    log.append({"frame": "d", "outcome": "unreadable", "reason": "not an image"})
    recs = ResultsLog(tmp_path).records()
    assert [r["frame"] for r in recs] == ["a", "b", "c", "d"]
    rows = list(csv.DictReader(open(tmp_path / "results.csv")))
    assert len(rows) == 4 and rows[0]["qw"] == "1.0" and rows[2]["reason"] == "too few stars"
    s = summarize(recs)
    assert s["counts"] == {"correct": 1, "no_match": 1, "unreadable": 1, "wrong": 1}
    assert s["success_rate"] == 1 / 3 and s["wrong_rate"] == 1 / 3
    assert s["attitude_error_deg"]["max"] == 12.0
    assert s["solve_s"]["median"] == 0.2
    paths = plot_summary(recs, tmp_path / "plots")
    assert {p.name for p in paths} == {"error_cdf.png", "residuals.png"}
    assert all(p.stat().st_size > 1000 for p in paths)


def test_a_log_cut_mid_line_keeps_its_records_and_goes_on(tmp_path, caplog):
    from ground.analysis.results_log import ResultsLog

    log = ResultsLog(tmp_path)
    log.append({"frame": "a.dng", "outcome": "correct"})
    with open(log.jsonl_path, "a") as fh:
        fh.write('{"frame": "b.dng", "outc')  # a crash or a full disk mid-write
    assert [r["frame"] for r in log.records()] == ["a.dng"]
    assert "cut short" in caplog.text  # a warning: on stderr under st16-ground (its --log-level)
    log.append({"frame": "c.dng", "outcome": "correct"})
    assert [r["frame"] for r in log.records()] == ["a.dng", "c.dng"]
