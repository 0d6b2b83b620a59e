"""The whole chain with the device in a separate process: catalog upload over a pty, solves on
rendered colour and monochrome frames with known attitudes, bad frames, a replay directory, and
a device that dies mid-replay (TCP, so the restarted device is at the same address)."""

import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import guards
import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.catalog.image_io import catalog_to_image
from firmware_model.pipeline.raw_frame import Frame, frame_to_bytes
from ground.analysis.replay import Truth, replay, score
from ground.arg_types import InputError
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.link.client import Client, Nack
from ground.link_solver import LinkSolver
from ground.sim.device_process import pick_attitudes, start_device, stop_device
from ground.sim.frame_writer import write_rendered
from ground.sim.sensor_sim import DetectorModel, render_frame
from ground.sim.sky_model import sky_stars
from protocol import result

CAMERA = CameraModel.reference_design()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Catalog image and a directory of rendered frames (2 colour, 1 mono) with truth."""
    root = tmp_path_factory.mktemp("scene")
    catalog = build_catalog(CatalogDesign())
    image = catalog_to_image(catalog)
    frames = root / "frames"
    frames.mkdir()
    stars = sky_stars()
    for k, a in enumerate(pick_attitudes(catalog, CAMERA, 3, np.random.default_rng(42))):
        pattern = "MONO" if k == 2 else "RGGB"
        r = render_frame(stars, a, CAMERA, DetectorModel(pattern=pattern), seed=100 + k)
        write_rendered(r, frames / f"f{k}_{pattern.lower()}.dng")
    return {"image": image, "frames": frames, "root": root}


@pytest.fixture
def device(tmp_path):
    proc, path = start_device(tmp_path / "state")
    yield path
    assert stop_device(proc) == 0


def _upload_catalog(path, image):
    with Client(path, timeout=guards.REPLY_S) as c:
        c.init()
        c.upload(0, image, progress=False)
        info = c.slot_info(0)
        assert info.active and info.length == len(image)


def test_solve_without_catalog_says_so(device):
    with Client(device, timeout=guards.REPLY_S) as c:
        c.init()
        rec = c.go_and_wait(timeout=guards.HANG_S)
    assert result.status_of(int(rec["return_code"])) == result.Status.NO_CATALOG
    assert b"catalog" in bytes(rec["ext"]["reason"])
    assert not np.any(rec["quaternion"])  # never a fake attitude


def test_colour_and_mono_solves_over_pty(device, scene):
    _upload_catalog(device, scene["image"])
    solver = LinkSolver(device, timeout=guards.REPLY_S)
    try:
        from firmware_model.pipeline.frame_readers import read_frame

        for path in sorted(scene["frames"].glob("*.dng")):
            rec = solver.solve(read_frame(path)).record
            sc = score(rec, Truth.for_frame(path))
            assert rec["status"] == "OK", (path.name, rec["reason"])
            assert rec["method"] == ("pattern" if "mono" in path.name else "colour")  # mono: the brightest pattern
            assert sc["outcome"] == "correct" and sc["attitude_error_deg"] < 0.01, (path.name, sc)
            assert rec["n_matched"] >= 4 and len([s for s in rec["stars"] if s["catalog_id"]]) == rec["n_matched"]
            assert set(rec["timings_s"]) >= {"detect", "fit", "identify", "total"}
    finally:
        solver.close()


def test_wrong_size_frame_is_refused_and_nothing_changes(device, scene):
    _upload_catalog(device, scene["image"])
    small = Frame(pixels=np.full((100, 120), 64, np.uint16), pattern="RGGB", black_level=64, white_level=4095)
    with Client(device, timeout=guards.REPLY_S) as c:
        with pytest.raises(Nack) as err:
            c.upload(1, frame_to_bytes(small), progress=False)
        assert err.value.reason == 0x0301 and "2592 x 1944" in str(err.value)
        assert not c.slot_info(1).active
        assert c.slot_info(0).active  # the catalog is untouched
        assert c.diagnostic().nacked >= 1
        rec = c.go_and_wait(timeout=guards.HANG_S)
    assert result.status_of(int(rec["return_code"])) == result.Status.NO_FRAME


def test_replay_directory_counts_unreadable_frames(device, scene, tmp_path):
    _upload_catalog(device, scene["image"])
    frames = tmp_path / "replay"
    frames.mkdir()
    for p in sorted(scene["frames"].iterdir())[:2]:
        (frames / p.name).symlink_to(p)
    (frames / "broken.fits").write_bytes(b"SIMPLE  =   garbage")
    solver = LinkSolver(device, timeout=guards.REPLY_S)
    try:
        summary = replay(frames, solver, tmp_path / "out", progress=False)
    finally:
        solver.close()
    assert summary["counts"] == {"correct": 1, "unreadable": 1}
    log = [json.loads(line) for line in (tmp_path / "out" / "results.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in log] == ["broken.fits", frames.glob("*.dng").__next__().name]
    assert (tmp_path / "out" / "error_cdf.png").stat().st_size > 1000


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_replay_survives_device_restart(scene, tmp_path):
    """The device dies after the first solve; the ground side waits, resumes, loses nothing."""
    port = _free_port()
    state = tmp_path / "state"
    args = [sys.executable, "-m", "firmware_model.device.cli", "--tcp", f"127.0.0.1:{port}", "--state", str(state)]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().startswith("listening on")
    url = f"socket://127.0.0.1:{port}"
    _upload_catalog(url, scene["image"])
    frames = tmp_path / "replay"
    frames.mkdir()
    for p in sorted(scene["frames"].iterdir()):
        (frames / p.name).symlink_to(p)
    out = tmp_path / "out"
    restarted = []

    def kill_and_restart():
        log = out / "results.jsonl"
        deadline = time.monotonic() + guards.HANG_S
        while time.monotonic() < deadline and not (log.exists() and log.read_text().strip()):
            time.sleep(0.05)
        proc.kill()
        proc.wait()
        time.sleep(1.0)  # the ground side finds the device gone (no assertion depends on this)
        p2 = subprocess.Popen(args, stdout=subprocess.PIPE, text=True)
        p2.stdout.readline()
        restarted.append(p2)

    killer = threading.Thread(target=kill_and_restart)
    killer.start()
    solver = LinkSolver(url, reconnect_timeout=guards.HANG_S, timeout=guards.REPLY_S)
    try:
        summary = replay(frames, solver, out, progress=False, make_plots=False)
    finally:
        solver.close()
        killer.join()
        for p in restarted:
            p.terminate()
            p.wait()
    assert restarted and solver.reconnects >= 1
    assert summary["counts"] == {"correct": 3}  # the persisted catalog survived the restart
    names = [json.loads(line)["frame"] for line in (out / "results.jsonl").read_text().splitlines()]
    assert names == sorted(p.name for p in frames.glob("*.dng"))  # each frame logged exactly once


def test_cli_solve_json_and_results_log(device, scene, tmp_path):
    _upload_catalog(device, scene["image"])
    frame = sorted(scene["frames"].glob("*rggb.dng"))[0]
    exe = Path(sys.executable).parent / "st16-ground"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "ground.cli"]
    run = subprocess.run(
        cmd + ["--port", device, "--json", "solve", "--frame", str(frame), "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    rec = json.loads(run.stdout)
    assert rec["status"] == "OK" and len(rec["q_icrs_to_sensor"]) == 4
    assert 0 <= rec["ra_deg"] < 360 and -90 <= rec["dec_deg"] <= 90 and 0 <= rec["roll_deg"] < 360
    assert rec["attitude_error_deg"] < 0.01
    matched = [s for s in rec["stars"] if s["catalog_id"] is not None]
    assert matched and all(s["x"] is not None and s["rg"] is not None for s in matched[:3])
    assert (tmp_path / "results.jsonl").exists() and (tmp_path / "results.csv").read_text().count("\n") == 2


def test_refused_frame_is_an_answer_not_silence(device, scene, tmp_path):
    """A frame of the wrong size is NACKed: `solve` ends at once with that one line (it used to
    wait for a 'silent' device and retry for minutes), and a replay logs it and goes on."""
    from ground.sim.frame_writer import write_dng

    _upload_catalog(device, scene["image"])
    small = tmp_path / "small.dng"
    write_dng(Frame(pixels=np.full((480, 640), 64, np.uint16), pattern="RGGB", black_level=64, white_level=4095), small)
    exe = Path(sys.executable).parent / "st16-ground"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "ground.cli"]
    run = subprocess.run(  # the timeout: a hang guard (it used to retry for minutes)
        cmd + ["--port", device, "solve", "--frame", str(small), "--out", str(tmp_path / "s")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 5 and "Traceback" not in run.stderr  # 5: refused (st16-ground --help)
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "NACKed" in lines[0] and "640 x 480" in lines[0], run.stderr
    frames = tmp_path / "replay"
    frames.mkdir()
    (frames / "a_small.dng").symlink_to(small)
    (frames / "b_good.dng").symlink_to(sorted(scene["frames"].glob("*rggb.dng"))[0])
    solver = LinkSolver(device, reconnect_timeout=guards.HANG_S, timeout=guards.REPLY_S)
    try:
        summary = replay(frames, solver, tmp_path / "out", progress=False)
    finally:
        solver.close()
    assert summary["counts"] == {"refused": 1, "unscored": 1}  # no truth beside the linked frame
    log = [json.loads(line) for line in (tmp_path / "out" / "results.jsonl").read_text().splitlines()]
    assert log[0]["frame"] == "a_small.dng" and "NACKed" in log[0]["reason"]
    assert log[1]["frame"] == "b_good.dng" and log[1]["status"] == "OK"
    good = sorted(scene["frames"].glob("*rggb.dng"))[0]
    assert score(log[1], Truth.for_frame(good))["outcome"] == "correct"  # the truth beside the linked frame


def test_replay_refuses_to_mix_runs_and_resumes_where_it_stopped(scene, tmp_path):
    from firmware_model.catalog.image_io import catalog_from_image
    from ground.solver import in_process_solver

    solver = in_process_solver(camera=CAMERA, catalog=catalog_from_image(scene["image"]))
    frames = sorted(scene["frames"].glob("*.dng"))
    out = tmp_path / "out"
    first = tmp_path / "first"
    first.mkdir()
    for p in frames[:2]:  # the run that was interrupted after two frames
        for f in (p, p.with_name(p.stem + ".truth.json")):
            (first / f.name).symlink_to(f)
    replay(first, solver, out, progress=False, make_plots=False)
    with pytest.raises(InputError, match="--resume"):
        replay(scene["frames"], solver, out, progress=False, make_plots=False)
    summary = replay(scene["frames"], solver, out, progress=False, make_plots=False, resume=True)
    log = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert sorted(r["frame"] for r in log) == sorted(p.name for p in frames)  # each frame once
    assert summary["counts"] == {"correct": len(frames)}


def test_frame_upload_can_show_its_progress(device, scene, capsys):
    from firmware_model.pipeline.frame_readers import read_frame

    _upload_catalog(device, scene["image"])
    path = sorted(scene["frames"].glob("*rggb.dng"))[0]
    frame = read_frame(path)
    for shown in (False, True):
        solver = LinkSolver(device, upload_progress=shown, timeout=guards.REPLY_S)
        try:
            rec = solver.solve(frame).record
        finally:
            solver.close()
        assert rec["status"] == "OK" and score(rec, Truth.for_frame(path))["outcome"] == "correct"
        assert ("slot 1" in capsys.readouterr().err) == shown


def test_a_frame_poked_in_through_the_link_solves_as_an_uploaded_one(device, scene):
    """IMAGE Rectangular Poke writes a rendered frame's pixels into image buffer 0 and a GO with bit
    0x40 INJECTED solves that buffer (docs/ICD.md §6-§7): image injection through NSP alone."""
    from firmware_model.pipeline.frame_readers import read_frame
    from ground.link.solve_report import solve_record

    _upload_catalog(device, scene["image"])
    path = sorted(scene["frames"].glob("*_rggb.dng"))[0]
    frame = read_frame(path)
    with Client(device, timeout=guards.REPLY_S) as c:
        c.poke_image(0, 0, 0, frame.pixels)
        rec = c.go_and_wait(0x0B | 0x40, timeout=guards.HANG_S)
    out = solve_record(rec)
    sc = score(out, Truth.for_frame(path))
    assert out["status"] == "OK", out["reason"]
    assert sc["outcome"] == "correct" and sc["attitude_error_deg"] < 0.01, sc
    assert not int(rec["return_code"]) & result.ReturnBits.DETECTOR_IMAGE  # the buffer, not the detector
