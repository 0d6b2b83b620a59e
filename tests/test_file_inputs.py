"""Files users name, and the input checks that come before any heavy work (issue 40 sections 8
and 9, issue 42 "Slow input checks"; docs/bad_input.md): special files refused in one line
(a FIFO used to hang until killed, ``/dev/zero`` to fill memory), sizes checked before reading,
JSON depth bounded, crafted ``.npz`` members refused before loading, whole-or-nothing database
saves, replays that go on past a bad frame, short messages with the cause first.

Each case is one line on stderr, exit 2, no traceback. No assertion measures time: a hang is
caught by the timeout marks (pytest-timeout), a broken check only then."""

from __future__ import annotations

import io
import json
import os
import socket
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest

from firmware_model import user_files
from firmware_model.pipeline.frame_readers import FrameReadError, read_frame
from firmware_model.pipeline.raw_frame import Frame

DEEP = "[" * 100_000 + "]" * 100_000


def _lines(text: str) -> list[str]:
    return [line for line in text.strip().splitlines() if line]


def _one_line(capsys) -> str:
    err = _lines(capsys.readouterr().err)
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def _ground(argv: list[str]) -> int:
    from ground.cli.main import main

    try:
        return main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's refusals
        return int(exc.code or 0)


def _device(argv: list[str]) -> int:
    from firmware_model.device.cli import main

    try:
        return main([str(a) for a in argv])
    except SystemExit as exc:
        return int(exc.code or 0)


def _write_frame(path: Path, shape=(48, 64)) -> Path:
    from ground.sim.frame_writer import write_frame

    write_frame(Frame(np.zeros(shape, np.uint16), "MONO", white_level=4095), path)
    return path


@pytest.fixture
def fifo(tmp_path) -> Path:
    path = tmp_path / "pipe"
    os.mkfifo(path)
    return path


@pytest.fixture
def loop(tmp_path) -> Path:
    a, b = tmp_path / "loop_a", tmp_path / "loop_b"
    a.symlink_to(b)
    b.symlink_to(a)
    return a


# ------------------------------------------------------------------- the shared helper


def test_the_helper_names_each_kind_of_file_it_refuses(tmp_path, fifo, loop):
    small = tmp_path / "small.json"
    small.write_text('{"a": [1, 2]}')
    assert user_files.load_json_file(small) == {"a": [1, 2]}
    cases = {
        tmp_path / "nope": "no such file",
        tmp_path: "a directory, not a file",
        fifo: "a FIFO (named pipe), not a regular file",
        Path("/dev/zero"): "a device, not a regular file",
        loop: "a symlink loop",
    }
    for path, reason in cases.items():
        with pytest.raises(user_files.UserFileError) as err:
            user_files.read_bytes(path, 1000)
        assert str(err.value) == f"{path}: {reason}"
    with pytest.raises(user_files.UserFileError, match=r"13 bytes, over the 12-byte limit"):
        user_files.read_bytes(small, 12)


def test_json_depth_is_bounded_before_the_parser_recurses():
    assert user_files.loads('{"a": "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["}')["a"]
    assert user_files.loads("[" * 64 + "]" * 64) is not None
    with pytest.raises(ValueError, match="JSON nested 65 deep, over the limit of 64"):
        user_files.loads("[" * 65 + "]" * 65)
    with pytest.raises(ValueError, match="JSON nested 100000 deep"):
        user_files.loads(DEEP.encode())


def test_a_long_value_is_echoed_cut():
    assert user_files.echo("1234") == "1234"
    assert len(user_files.echo("9" * 5000)) < 80


# ------------------------------------------------------------------- parameter files (JSON depth)


def test_deeply_nested_parameters_are_nacked_as_json_and_refused_in_one_line(tmp_path, capsys):
    from firmware_model.device.sensor_input import REJECT_PARAMS_JSON, DeviceParams, params_slot_handler
    from protocol.commands import SlotRejected

    with pytest.raises(SlotRejected) as err:  # the slot-2 validator: the COMMIT's NACK reason
        params_slot_handler().validate(DEEP.encode())
    assert err.value.code == REJECT_PARAMS_JSON == 0x0400  # it was 0x0007 (a RecursionError)
    with pytest.raises(SlotRejected):
        DeviceParams.from_json(DEEP.encode())
    deep = tmp_path / "deep.json"
    deep.write_text(DEEP)
    frame = _write_frame(tmp_path / "f.npy")
    for argv in (
        ["--port", tmp_path / "no-port", "params", "upload", deep],
        ["solve-file", frame, "--params", deep, "--fov-deg", "10"],
    ):
        assert _ground(argv) == 2
        assert "JSON nested 100000 deep" in _one_line(capsys)
    assert _device(["--pty", "--params", deep]) == 2
    assert _one_line(capsys) == (
        f"st16-device: --params {deep}: parameter set is not UTF-8 JSON: JSON nested 100000 deep, over the limit of 64"
    )
    assert _device(["--pty", "--camera", deep]) == 2
    assert "camera model" in _one_line(capsys)


# ------------------------------------------------------------------- special files, sizes


@pytest.mark.timeout(60)
def test_a_fifo_or_a_device_as_a_fault_script_is_refused_before_reading(tmp_path, fifo, capsys):
    for path, what in ((fifo, "a FIFO (named pipe), not a regular file"), (Path("/dev/zero"), "a device")):
        assert _device(["--pty", "--faults", path]) == 2
        assert _one_line(capsys).startswith(f"st16-device: fault file {path}: {what}")
        assert _ground(["--port", tmp_path / "no-port", "fault", "load", path]) == 2
        assert f"fault file {path}: {what}" in _one_line(capsys)
    big = tmp_path / "big.txt"
    big.write_text("# a comment\n" * 1000)  # 12 000 bytes: refused by its size, not after reading
    assert _device(["--pty", "--faults", big]) == 2
    assert "12000 bytes, over the 4159-byte limit" in _one_line(capsys)


@pytest.mark.timeout(60)
def test_a_fifo_device_or_symlink_loop_as_a_database_is_one_line(tmp_path, fifo, loop, capsys):
    frame = _write_frame(tmp_path / "f.npy")
    for path, what in ((fifo, "a FIFO"), (Path("/dev/zero"), "a device"), (loop, "a symlink loop")):
        for argv in (["database", "info", "--database", path], ["solve-file", frame, "--database", path]):
            assert _ground(argv) == 2, argv
            assert f"sky database {path}: {what}" in _one_line(capsys)


def _npz(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return path


def _npy(array=None, header: dict | None = None, tail: bytes = b"") -> bytes:
    buf = io.BytesIO()
    if header is None:
        np.save(buf, array)
    else:
        np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue() + tail


@pytest.mark.timeout(60)
def test_a_crafted_npz_member_is_refused_before_it_is_loaded(tmp_path, capsys):
    from ground.catalog import sky_database

    meta = {"format": "colour-st16 sky database", "version": sky_database.VERSION, "recipe": sky_database.recipe()}
    bomb = _npz(
        tmp_path / "bomb.npz",
        {
            "meta.npy": _npy(np.frombuffer(json.dumps(meta).encode(), np.uint8)),
            "vec.npy": _npy(header={"descr": "<f8", "fortran_order": False, "shape": (10**12,)}, tail=bytes(64)),
        },
    )
    with pytest.raises(sky_database.DatabaseError, match=r"member vec.npy claims 1000000000000 <f8|float64"):
        sky_database.load(bomb)
    assert _ground(["database", "info", "--database", bomb]) == 2
    assert "member vec.npy claims" in _one_line(capsys)


def test_a_killed_database_save_leaves_nothing_the_next_save_keeps(tmp_path):
    from ground.catalog import sky_database

    class Index:
        def arrays(self):
            return {}

    target = tmp_path / "sky.npz"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = [
        tmp_path / f".sky.{int(dead.stdout)}.part.npz",  # a build killed in its save (its process gone)
        tmp_path / ".sky.k3j_x9ab.part.npz",  # the earlier naming (tempfile's random part)
    ]
    running = tmp_path / f".sky.{os.getppid()}.part.npz"  # a save still running in another process
    for part in [*stale, running]:
        part.write_bytes(b"x" * 1000)
    db = sky_database.SkyDatabase(Index(), np.zeros(3), np.arange(3), {"format": "x"})
    sky_database.save(db, target)
    assert target.is_file()
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([target.name, running.name]), left


# ------------------------------------------------------------------- frames


def test_a_frame_too_narrow_or_too_tall_is_refused_when_read(tmp_path, capsys):
    import tifffile

    for shape in ((1, 100_000), (100_000, 1), (2, 70_000)):
        path = tmp_path / f"f{shape[0]}x{shape[1]}.tiff"
        tifffile.imwrite(path, np.ones(shape, np.uint16))
        with pytest.raises(FrameReadError, match=r"a frame needs 2 to 65535 px on each side"):
            read_frame(path)
    assert _ground(["solve-file", tmp_path / "f1x100000.tiff", "--fov-deg", "10"]) == 2
    assert _one_line(capsys).endswith("f1x100000.tiff: a 100000 x 1 px image: a frame needs 2 to 65535 px on each side")


def test_an_all_nan_tiff_is_one_line_without_warnings(tmp_path):
    import tifffile

    path = tmp_path / "nan.tiff"
    tifffile.imwrite(path, np.full((64, 64), np.nan, np.float32))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        with pytest.raises(FrameReadError):  # one line, and no RuntimeWarning beside it (there were two)
            read_frame(path)
    assert not said, [str(w.message) for w in said]


@pytest.mark.timeout(60)
def test_a_fifo_or_a_symlink_loop_frame_is_named_for_what_it_is(fifo, loop):
    with pytest.raises(FrameReadError, match="a FIFO"):
        read_frame(fifo)
    with pytest.raises(FrameReadError, match="a symlink loop"):
        read_frame(loop)
    with pytest.raises(FrameReadError, match="a device"):
        read_frame("/dev/zero")


def test_a_cut_dng_is_one_line_without_librarys_own(tmp_path, capfd):
    from ground.sim.frame_writer import write_frame

    whole = tmp_path / "g.dng"
    pixels = np.random.default_rng(0).integers(0, 4000, (480, 640)).astype(np.uint16)
    write_frame(Frame(pixels, "RGGB", white_level=4095), whole)
    cut = tmp_path / "cut.dng"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    capfd.readouterr()
    with pytest.raises(FrameReadError) as err:
        read_frame(cut)
    out, errs = capfd.readouterr()
    assert errs == "" and out == "", (out, errs)  # LibRaw's own line is not on stderr ...
    assert "Unexpected end of file" in str(err.value)  # ... but in the one line's reason


def test_the_bad_frame_reason_says_the_cause_first_with_the_files_name_only(tmp_path):
    from firmware_model.camera import CameraModel
    from firmware_model.device.device import FrameUnavailable
    from firmware_model.device.sensor_input import FileFrames

    folder = tmp_path / ("a-long-folder-name-of-field-frames-" * 3)
    folder.mkdir()
    (folder / "b.npy").write_bytes(b"")
    source = FileFrames(str(folder), CameraModel.reference_design())
    with pytest.raises(FrameUnavailable) as err:
        source(None)  # type: ignore[arg-type]
    assert str(err.value) == "file is empty (b.npy)"  # it was "b.npy: /tmp/.../b.npy: file is empty"


# ------------------------------------------------------------------- replays go on


def test_a_replay_counts_a_frame_whose_solve_fails_and_goes_on(tmp_path):
    from ground.analysis.replay import replay

    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("a.npy", "b.npy", "c.npy"):
        _write_frame(frames / name)
    (frames / "d.tiff").write_bytes(b"II*\x00garbage")

    class Failing:
        def solve(self, frame, say=None):
            raise OverflowError("Python integer 100000 out of bounds for uint16")

    summary = replay(frames, Failing(), tmp_path / "out", progress=False, make_plots=False)
    assert summary["frames"] == 4 and summary["counts"] == {"failed": 3, "unreadable": 1}, summary
    rows = [json.loads(line) for line in (tmp_path / "out" / "results.jsonl").read_text().splitlines()]
    assert rows[0]["reason"] == "OverflowError: Python integer 100000 out of bounds for uint16"


# ------------------------------------------------------------------- checks before heavy work (issue 42)


@pytest.mark.timeout(120)
def test_solve_file_of_a_directory_fails_before_any_database_is_built(tmp_path):
    """On a fresh cache ``solve-file DIR`` built the 86 MB database (21 s) before it looked at DIR."""
    (tmp_path / "dir").mkdir()
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache"), "HOME": str(tmp_path)}
    run = subprocess.run(
        [sys.executable, "-m", "ground.cli", "solve-file", str(tmp_path / "dir")],
        capture_output=True,
        text=True,
        env=env,
        timeout=110,
    )
    assert run.returncode == 2 and _lines(run.stderr) == [
        f"st16-ground: {tmp_path / 'dir'}: a directory, not a frame file"
    ]
    assert not list((tmp_path / "cache").rglob("sky-*.npz"))


def test_a_busy_tcp_port_is_one_line_naming_the_address(capsys):
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        assert _device(["--tcp", f"127.0.0.1:{port}"]) == 2
    line = _one_line(capsys)
    assert line.startswith(f"st16-device: --tcp 127.0.0.1:{port}: [Errno 98] Address already in use"), line


def test_a_binary_sky_schedule_is_one_line_naming_the_file(tmp_path, capsys):
    cat = tmp_path / "cat.st16cat"
    cat.write_bytes(b"ST16\xb4\x00\xff" + bytes(range(256)))
    assert _device(["--pty", "--sky", cat]) == 2
    line = _one_line(capsys)  # `--sky F: not UTF-8 text ...`, or the schedule reader's own line naming F
    assert line.startswith("st16-device: ") and str(cat) in line and "utf-8" in line.lower(), line


def test_a_replay_of_an_empty_directory_is_an_input_error(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert _ground(["replay", tmp_path / "empty", "--offline", "-o", tmp_path / "out"]) == 2
    assert _one_line(capsys).endswith("empty: no frame files (DNG/raw, FITS, TIFF, PNG, JPEG, .npy) in the directory")
    assert not (tmp_path / "out").exists()


def test_a_refused_value_is_echoed_cut(capsys):
    assert _ground(["frame", "render", "--random", "9" * 5000]) == 2
    line = _one_line(capsys)
    assert len(line) < 300 and "(5000 characters)" in line, len(line)


def test_a_long_count_in_a_fault_script_is_echoed_cut(tmp_path, capsys):
    script = tmp_path / "faults.txt"
    script.write_text(f"stuck_result count={'9' * 4100}\n")  # under the 4159-byte limit
    assert _device(["--pty", "--faults", script]) == 2
    line = _one_line(capsys)
    assert len(line) < 400 and "(4106 characters) outside 0..1000000" in line and str(script) in line, len(line)
    assert _ground(["--port", tmp_path / "no-port", "fault", "load", script]) == 2
    line = _one_line(capsys)
    assert len(line) < 500 and "(4106 characters)" in line and str(script) in line, len(line)
