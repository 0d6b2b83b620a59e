"""The optional parts ([plots], [dask]) answer in one line when they are not installed, and a
command that only draws as a side effect keeps its results."""

import sys

import numpy as np
import pytest

from ground.cli.main import main
from ground.optional import MissingExtra, dask_distributed, pyplot


def test_missing_extras_name_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # an import of it now fails
    with pytest.raises(MissingExtra, match=r"pip install 'colour-st16\[plots\]'"):
        pyplot()
    monkeypatch.setitem(sys.modules, "dask", None)
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    with pytest.raises(MissingExtra, match=r"pip install 'colour-st16\[dask\]'"):
        dask_distributed()


def test_a_plot_asked_for_without_matplotlib_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    from firmware_model.pipeline.raw_frame import Frame
    from ground.sim.frame_writer import write_frame

    write_frame(Frame(np.zeros((48, 64), np.uint16), "MONO", white_level=4095), tmp_path / "f.npy")
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    assert main(["frame", "inspect", str(tmp_path / "f.npy"), "--plot", str(tmp_path / "p.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["st16-ground: plots need matplotlib: pip install 'colour-st16[plots]'"]


def test_sim_without_matplotlib_keeps_its_rows_and_summary(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    argv = ["sim", "colour", "--boresights", "20", "--rolls", "1", "--workers", "1", "--out", str(tmp_path)]
    assert main(argv) == 0
    assert (tmp_path / "colour_rows.npy").exists() and (tmp_path / "colour_summary.json").exists()
    assert not (tmp_path / "error_cdf.png").exists()
    assert "plots skipped: plots need matplotlib" in capsys.readouterr().err
