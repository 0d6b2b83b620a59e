"""Bad files, interrupts and closed pipes through the ``st16-ground`` command line: one line on
stderr, a documented exit code, no traceback (docs/bad_input.md)."""

import json
import subprocess
import sys

import pytest
from interrupt import COUNTING, interruptible, without_bar

from ground.cli.main import main


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


@pytest.fixture
def files(tmp_path):
    (tmp_path / "garbage.bin").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "text.txt").write_text("hello, I am not what you think\n")
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "f.npy").write_bytes(b"")  # a frame file: the catalog is checked, not the empty folder
    return tmp_path


@pytest.mark.parametrize(
    "argv,code,fragment",
    [
        (["params", "upload", "{d}/nope.json"], 2, "nope.json: no such file"),
        (["params", "upload", "{d}/garbage.bin"], 2, "not UTF-8 JSON"),
        (["replay", "{d}/frames", "--offline", "--catalog", "{d}/nope.st16cat"], 2, "--catalog"),
        (["replay", "{d}/frames", "--offline", "--catalog", "{d}/text.txt"], 2, "TRUNCATED"),
        (["demo", "--out", "{d}/a_file"], 2, "Not a directory"),
        (["frame", "inspect", "{d}/nope.dng"], 2, "no such file"),
    ],
)
def test_missing_or_garbage_files_are_one_line(files, capsys, argv, code, fragment):
    rc = main(["--port", "/dev/no-such-port", *[a.format(d=files) for a in argv]])
    assert rc == code
    assert fragment in _one_line_error(capsys)


def test_a_camera_file_that_is_not_a_camera_model_is_one_line(files, capsys):
    import numpy as np

    from firmware_model.pipeline.raw_frame import Frame
    from ground.sim.frame_writer import write_frame

    write_frame(Frame(np.zeros((48, 64), np.uint16), "MONO", white_level=4095), files / "f.npy")
    rc = main(
        [
            "solve",
            "--frame",
            str(files / "f.npy"),
            "--offline",
            "--catalog",
            str(files / "text.txt"),
            "--camera",
            str(files / "text.txt"),
        ]
    )
    assert rc == 2
    assert "camera model" in _one_line_error(capsys)


def test_ctrl_c_in_a_long_command_is_one_line_and_exit_130(tmp_path):
    args = ["sim", "colour", "--boresights", "100000", "--rolls", "10", "--workers", "1", "--out", str(tmp_path)]
    with interruptible(args) as child:
        child.wait_for(COUNTING, "progress bar counting poses")  # past start-up and the catalog, inside the run
        code, err = child.interrupt()
    assert code == 130, err
    assert without_bar(err) == ["st16-ground: interrupted"], err  # the bar's drawings aside: one line


def test_a_reader_that_goes_away_leaves_no_traceback():
    """``st16-ground ... | head -1``: the pipe closes under the writer."""
    cmd = (
        f"{sys.executable} -m ground.cli --json sim fourstar --step 20 | head -c 1 > /dev/null; "
        "echo ${PIPESTATUS[0]} >&2"
    )
    run = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=120)
    assert "Traceback" not in run.stderr and "BrokenPipe" not in run.stderr, run.stderr
    assert run.stderr.strip().splitlines()[-1] in ("0", "1")


def test_json_output_of_a_refusal_is_strict_json(files, capsys):
    rc = main(["--json", "params", "upload", str(files / "nope.json")])
    assert rc == 2
    captured = capsys.readouterr()
    for line in (captured.out + captured.err).strip().splitlines():
        if line.startswith("{"):
            json.loads(line)
