"""``st16-ground frame render / inspect`` end to end on small frames."""

import json

import numpy as np

from ground.cli import main


def test_render_then_inspect_json_and_plot(tmp_path, capsys):
    out = tmp_path / "f.dng"
    args = ["frame", "render", "--out", str(out), "--width", "640", "--height", "480", "--fov", "2.5",
            "--random", "8", "--mag-range", "2", "4", "--seed", "5", "--cosmics", "3"]
    assert main(args) == 0
    truth = json.loads((tmp_path / "f.truth.json").read_text())
    assert len(truth["stars"]) == 8 and len(truth["attitude_quaternion"]) == 4
    capsys.readouterr()
    assert main(["--json", "frame", "inspect", str(out), "--plot", str(tmp_path / "o.png")]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["n_stars"] == 8 and set(rep["timings_ms"]) >= {"detect_ms", "fit_ms", "total_ms"}
    for s in rep["stars"]:
        assert s["truth"] is not None and np.hypot(s["truth"]["dx"], s["truth"]["dy"]) < 0.3
        assert {"x", "y", "rg", "bg", "flags", "reduced_chi2"} <= set(s)
    assert (tmp_path / "o.png").stat().st_size > 10_000


def test_inspect_text_and_bad_file(tmp_path, capsys):
    out = tmp_path / "m.fits"
    assert main(["frame", "render", "--out", str(out), "--width", "320", "--height", "240", "--pattern", "MONO",
                 "--random", "4", "--mag-range", "2", "3"]) == 0
    capsys.readouterr()
    assert main(["frame", "inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert "MONO" in text and "NO_COLOUR" in text and "timings ms" in text
    bad = tmp_path / "junk.dng"
    bad.write_bytes(b"not a raw file at all")
    assert main(["frame", "inspect", str(bad)]) == 2
    assert "not a readable raw" in capsys.readouterr().err
