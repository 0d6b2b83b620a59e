"""``st16-ground --log-level``: warnings and notes go through logging to one stderr handler per
run; the default (warning) shows the lines a user always saw, as they read before; debug adds
notes; a bad level is an argparse error (exit 2)."""

import logging

import numpy as np
import pytest

from firmware_model.pipeline.raw_frame import Frame
from ground.cli.main import OWN_LOGGERS, main
from ground.sim.frame_writer import write_frame


@pytest.fixture
def frame_with_bad_truth(tmp_path):
    path = write_frame(Frame(np.zeros((48, 64), np.uint16), "MONO", white_level=4095), tmp_path / "f.npy")
    (tmp_path / "f.truth.json").write_text("{not json")
    return path


def _inspect(capsys, path, *options):
    assert main(["frame", "inspect", str(path), *options]) == 0
    return capsys.readouterr()


def test_the_default_level_shows_the_warning_as_it_read_and_no_debug_line(frame_with_bad_truth, capsys):
    captured = _inspect(capsys, frame_with_bad_truth)
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("st16-ground: f.truth.json is not a readable truth file (")
    assert err[0].endswith("); ignored")
    assert "64 x 48 MONO frame" not in captured.err
    assert "PSF sigma" in captured.out  # the command's output stays on stdout


@pytest.mark.parametrize("where", ["before", "after"])
def test_log_level_debug_shows_debug_lines(frame_with_bad_truth, capsys, where):
    options = ["--log-level", "debug"]
    argv = [*options, "frame", "inspect", str(frame_with_bad_truth)]
    if where == "after":  # a global option: accepted after the command too
        argv = ["frame", "inspect", str(frame_with_bad_truth), *options]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert f"{frame_with_bad_truth}: 64 x 48 MONO frame" in err.splitlines()
    assert "is not a readable truth file" in err  # warnings too


def test_log_level_error_hides_warnings(frame_with_bad_truth, capsys):
    assert _inspect(capsys, frame_with_bad_truth, "--log-level", "error").err == ""


def test_the_handler_is_gone_after_the_run_and_records_reach_the_root_logger(frame_with_bad_truth, capsys, caplog):
    levels = {name: logging.getLogger(name).level for name in OWN_LOGGERS}
    with caplog.at_level(logging.DEBUG):
        _inspect(capsys, frame_with_bad_truth, "--log-level", "debug")
    assert any(r.name == "ground.cli.frame" and r.levelno == logging.DEBUG for r in caplog.records)
    assert all(not logging.getLogger(name).handlers for name in OWN_LOGGERS)
    assert {name: logging.getLogger(name).level for name in OWN_LOGGERS} == levels
    assert main(["frame", "inspect", str(frame_with_bad_truth)]) == 0  # no second handler left behind
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


@pytest.mark.parametrize("argv", [["--log-level", "loud", "ping"], ["ping", "--log-level", "LOUD"]])
def test_a_bad_log_level_is_a_one_line_usage_error(argv, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--port", "/dev/no-such-port", *argv])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "error: argument --log-level: invalid choice:" in err[-1], err
    assert "'debug', 'info', 'warning', 'error'" in err[-1]
    assert not [line for line in err if "Traceback" in line]
