"""Outputs are replaced whole or not at all (``ground.atomic_write``), and output paths are checked
before any work."""

import errno
import os
import pathlib

import pytest

from ground import atomic_write
from ground.cli.main import main


def _fail_half_way(monkeypatch):
    """Make every ``Path.write_bytes`` write half its data, then fail as a full disk does."""

    def write_half(self, data):
        with open(self, "wb") as fh:
            fh.write(data[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    monkeypatch.setattr(pathlib.Path, "write_bytes", write_half)


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_write.atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("interrupted")
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["out.bin"]
    atomic_write.write_bytes(target, b"new")
    assert target.read_bytes() == b"new" and os.listdir(tmp_path) == ["out.bin"]
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's private 0600


def test_a_missing_directory_names_the_target(tmp_path):
    with pytest.raises(FileNotFoundError) as exc:
        atomic_write.write_text(tmp_path / "no" / "x.json", "{}")
    assert exc.value.filename == str(tmp_path / "no" / "x.json")


def test_a_failed_catalog_build_keeps_the_previous_image(tmp_path, capsys, monkeypatch):
    out = tmp_path / "cat.img"
    out.write_bytes(b"previous good image")
    _fail_half_way(monkeypatch)
    assert main(["catalog", "build", "--m-thresh", "3.0", "--theta-fov", "10", "--n-h", "64", "-o", str(out)]) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert out.read_bytes() == b"previous good image" and os.listdir(tmp_path) == ["cat.img"]


def test_an_interrupted_frame_render_keeps_the_previous_frame_sidecar_and_truth(tmp_path, monkeypatch):
    import numpy as np

    out = tmp_path / "f.npy"
    assert main(["frame", "render", "--out", str(out), "--width", "64", "--height", "48", "--random", "3"]) == 0
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert sorted(before) == ["f.json", "f.npy", "f.truth.json"]

    def save_half(file, arr, **kw):
        file.write(b"\x93NUMPY")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "save", save_half)
    with pytest.raises(KeyboardInterrupt):
        main(["--debug", "frame", "render", "--out", str(out), "--width", "64", "--height", "48", "--seed", "5"])
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # no partial or temporary file


@pytest.mark.parametrize(
    "argv",
    [
        ["--log", "{d}/missing/log.jsonl", "ping"],
        ["ping", "--log", "{d}/missing/log.jsonl"],
        ["catalog", "build", "-o", "{d}/missing/cat.img"],
        ["frame", "render", "--out", "{d}"],
    ],
)
def test_output_paths_are_checked_before_any_work(argv, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--port", "/dev/no-such-port", *[a.format(d=tmp_path) for a in argv]])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "error: argument" in err[-1] and ("does not exist" in err[-1] or "is a directory" in err[-1]), err
