"""Ready at once: where the compiled kernels are cached (an unwritable cache is one line), the
device's pattern index built before it says ``listening`` and, after a catalog COMMIT, in another
process while the link keeps answering (a GO during the build waits for it and gives the same
answer), and a first solve's ``timings_s`` accounting for all the time it took. Behaviour only:
the times themselves are bench/bench_start.py's."""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from guards import HANG_S, REPLY_S

ROOT = Path(__file__).resolve().parents[1]


def _run(script: str, env: dict | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})},
        cwd=cwd or ROOT,
    )


def test_an_unwritable_kernel_cache_is_one_line_and_the_kernels_still_run(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    unwritable = blocker / "cache"  # under a file: no one can create it, root included
    module = tmp_path / "kernel_module.py"
    module.write_text("from numba import njit\n\n\n@njit(cache=True)\ndef twice(x):\n    return 2 * x\n")
    run = _run(
        """
        import firmware_model
        import kernel_module
        print(kernel_module.twice(21))
        """,
        env={"NUMBA_CACHE_DIR": str(unwritable), "PYTHONPATH": f"{ROOT}{os.pathsep}{tmp_path}"},
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "42"
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and str(unwritable) in lines[0] and "not writable" in lines[0], run.stderr


def test_the_kernel_cache_goes_where_it_can_be_written(tmp_path):
    from firmware_model import kernel_cache_dir

    assert kernel_cache_dir({"NUMBA_CACHE_DIR": str(tmp_path / "mine")}) == (tmp_path / "mine", True)
    assert kernel_cache_dir({}, package=tmp_path) == (None, True)  # writable: numba's own __pycache__
    where, _ = kernel_cache_dir({}, package=tmp_path / "not" / "there")  # a folder that cannot be written
    assert where is not None and where.parts[-2:] == ("colour-st16", "numba")


def test_warm_up_command_says_the_kernels_and_the_sky_database_are_ready():
    """Into the run's own cache (tests/conftest.py), never the user's ~/.cache."""
    from conftest import PRIVATE_HOME

    from ground.catalog.sky_database import default_path

    run = _run("from ground.cli.main import main; raise SystemExit(main(['warm-up']))")
    assert run.returncode == 0, run.stderr
    kernels, database = run.stdout.strip().splitlines()
    assert kernels.startswith("kernels: ready in ") and database.startswith("sky database ")
    assert "patterns of" in database and "fields 5-60 deg" in database
    assert default_path().is_relative_to(PRIVATE_HOME) and default_path().is_file()


def test_the_suite_runs_on_its_own_caches():
    """tests/conftest.py: a private HOME and XDG cache for this process and the processes it
    starts; the compiled kernels stay where the user's install keeps them."""
    from conftest import PRIVATE_HOME

    from firmware_model import user_cache_dir

    assert user_cache_dir().is_relative_to(PRIVATE_HOME)
    run = _run("from firmware_model import user_cache_dir; print(user_cache_dir())")
    assert run.returncode == 0, run.stderr
    assert Path(run.stdout.strip()).is_relative_to(PRIVATE_HOME)
    assert not os.environ.get("NUMBA_CACHE_DIR", "").startswith(str(PRIVATE_HOME))  # kernels: shared


# ------------------------------------------------------------------ the device


@pytest.fixture(scope="module")
def scene():
    """The reference catalog (image and object), a rendered mono frame and its camera."""
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_from_image, catalog_to_image
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.sim.device_process import pick_attitudes
    from ground.sim.sensor_sim import DetectorModel, render_frame
    from ground.sim.sky_model import sky_stars

    camera = CameraModel.reference_design()
    image = catalog_to_image(build_catalog(CatalogDesign()))
    catalog = catalog_from_image(image)
    (a,) = pick_attitudes(catalog, camera, 1, np.random.default_rng(27))
    frame = render_frame(sky_stars(), a, camera, DetectorModel(pattern="MONO"), seed=27).frame
    return image, catalog, frame, camera


def _attitude_error_deg(q, scene) -> float:
    """The angle (deg) between ``q`` and the scene frame's true attitude (rendered at it)."""
    from firmware_model.reference_frames import quat_to_matrix, rotation_angle
    from ground.sim.device_process import pick_attitudes

    (a,) = pick_attitudes(scene[1], scene[3], 1, np.random.default_rng(27))  # the scene's own draw
    return float(np.degrees(rotation_angle(quat_to_matrix(q), a)))


def test_the_device_builds_its_stored_catalogs_index_before_it_says_listening(tmp_path, scene):
    from firmware_model.device.slots import SlotStore

    image = scene[0]
    SlotStore(tmp_path / "state").set_active(0, image)  # a catalog committed before this start
    proc = subprocess.Popen(
        [sys.executable, "-m", "firmware_model.device.cli", "--pty", "--state", str(tmp_path / "state")]
        + ["--log-level", "info"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,  # one pipe: the lines in the order the device wrote them
        text=True,
        cwd=ROOT,
    )
    try:
        assert proc.stdout is not None
        before = []
        for line in proc.stdout:
            if line.startswith("listening on "):
                break
            before.append(line)
        else:
            pytest.fail(f"the device never said listening: {before}")
    finally:
        proc.terminate()
        proc.wait(timeout=HANG_S)
        if proc.stdout is not None:
            proc.stdout.close()
    said = "".join(before)
    assert "pipeline kernels ready" in said and "catalog pattern index ready" in said, said


def gated_index(gate: str, *args):
    """``scale_free.pattern_index`` once the file ``gate`` exists (run in the index-building
    process: the test holds the build open for as long as it likes)."""
    from firmware_model.pipeline.scale_free import pattern_index

    deadline = time.monotonic() + 120.0
    while not Path(gate).exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    return pattern_index(*args)


def test_a_commit_builds_the_index_elsewhere_the_link_answers_and_a_go_waits_for_it(tmp_path, scene):
    from firmware_model.device.catalog_slot import catalog_slot_handler
    from firmware_model.device.device import Device
    from firmware_model.device.link import PtyLink, serve
    from firmware_model.device.sensor_input import PipelineSolver
    from firmware_model.pipeline.run import run_pipeline
    from firmware_model.pipeline.solve_types import PipelineParams
    from ground.link.client import Client
    from ground.link.solve_report import record_from_output, solve_record
    from protocol.commands import Slot

    image, catalog, frame, camera = scene
    gate = tmp_path / "gate"
    solver = PipelineSolver(camera, PipelineParams(), build_index=functools.partial(gated_index, str(gate)))
    solver.serving()
    device = Device(
        solver=solver,
        slots={Slot.CATALOG: catalog_slot_handler(prepare=solver.prepare)},
        frame_source=lambda ctx: frame,
        sensor_shape=(camera.height, camera.width),
    )
    link, stop = PtyLink(), threading.Event()
    thread = threading.Thread(target=serve, args=(device, link, stop), daemon=True)
    thread.start()
    try:
        with Client(link.path, timeout=REPLY_S) as client:
            client.init()
            client.upload(Slot.CATALOG, image, progress=False)
            active = device.transfers.objects[Slot.CATALOG]
            _, build = active.__dict__["_pattern_build"]
            assert "APPLICATION" in client.ping()  # answered while the index is being built
            client.go()
            assert "BUSY" in client.ping()  # the GO waits for the index; the link still answers
            assert client.result_length() == 0 and not build.done()
            gate.touch()  # the build may finish now
            deadline = time.monotonic() + HANG_S
            while client.result_length() == 0 and time.monotonic() < deadline:
                time.sleep(0.02)
            rec = solve_record(client.read_result_record())
    finally:
        stop.set()
        thread.join(HANG_S)
        link.close()
        solver.close()
    assert build.done() and "_pattern_build" not in active.__dict__
    alone = record_from_output(run_pipeline(frame, camera, catalog, PipelineParams()))
    assert rec["status"] == alone["status"] == "OK"
    assert _attitude_error_deg(rec["q_icrs_to_sensor"], scene) < 0.01  # the truth
    assert rec["q_icrs_to_sensor"] == pytest.approx(alone["q_icrs_to_sensor"], abs=1e-6)
    assert [s["catalog_id"] for s in rec["stars"]] == [s["catalog_id"] for s in alone["stars"]]


# ------------------------------------------------------------------ a first solve's timings


def test_a_first_solves_stages_add_up_to_its_total(tmp_path, scene):
    """In a fresh process: the first solve_image pays for loading the kernels (``compile``),
    loading the catalog (``catalog``) and building its pattern index (``index``); the stages add
    up to the total, which is the whole wait. The offline replay's first solve loads the kernels
    too, the next does not."""
    image, _, frame, camera = scene
    (tmp_path / "cat.st16cat").write_bytes(image)
    np.save(tmp_path / "frame.npy", frame.pixels)
    (tmp_path / "camera.json").write_text(json.dumps(camera.to_dict()))
    run = _run(
        f"""
        import json, time
        import numpy as np
        from firmware_model.camera import CameraModel
        from ground.api import solve_image
        camera = CameraModel.from_dict(json.loads(open({str(tmp_path / "camera.json")!r}).read()))
        pixels = np.load({str(tmp_path / "frame.npy")!r})
        t0 = time.perf_counter()
        s = solve_image(pixels, camera=camera, catalog={str(tmp_path / "cat.st16cat")!r})
        waited = time.perf_counter() - t0
        again = solve_image(pixels, camera=camera, catalog={str(tmp_path / "cat.st16cat")!r})
        print(json.dumps({{"first": s.record["timings_s"], "waited": waited, "status": s.status,
                          "again": again.record["timings_s"], "q": s.q_icrs_to_sensor}}))
        """
    )
    assert run.returncode == 0, run.stderr
    got = json.loads(run.stdout.strip().splitlines()[-1])
    first = got["first"]
    assert got["status"] == "OK" and _attitude_error_deg(got["q"], scene) < 0.01  # the truth
    assert first["compile"] > 0 and first["catalog"] > 0 and first["index"] > 0  # the device's twin
    parts = sum(v for k, v in first.items() if k != "total")
    # orderings, not speeds (a loaded machine stretches the gaps between stages, never reverses them):
    # the stages lie inside the total, and the total inside the caller's wait
    assert 0 < parts <= first["total"] + 1e-6 and first["total"] <= got["waited"] + 1e-6
    assert "compile" not in got["again"]  # loaded once per process


def test_the_offline_replays_first_solve_loads_the_kernels(scene):
    run = _run(
        """
        import json
        from firmware_model.camera import CameraModel
        from firmware_model.pipeline.raw_frame import Frame
        from ground.catalog.build import build_catalog
        from ground.solver import in_process_solver
        from ground.catalog.design import CatalogDesign
        import numpy as np
        camera = CameraModel.reference_design()
        solver = in_process_solver(camera=camera, catalog=build_catalog(CatalogDesign()))
        frame = Frame(pixels=np.zeros((camera.height, camera.width), np.uint16), pattern="MONO", white_level=65535.0)
        print(json.dumps([solver.solve(frame).record["timings_s"], solver.solve(frame).record["timings_s"]]))
        """
    )
    assert run.returncode == 0, run.stderr
    first, second = json.loads(run.stdout.strip().splitlines()[-1])
    assert first["compile"] > 0 and "compile" not in second


def test_a_kept_pattern_index_is_the_built_one_and_a_damaged_one_is_built_again(tmp_path, synthetic_catalog):
    from firmware_model.pipeline.scale_free import cached_pattern_index, pattern_index

    cat = synthetic_catalog(300)
    args = (cat.vec, cat.mag, cat.n_pattern_stars, 90)
    built = pattern_index(*args)
    first = cached_pattern_index(tmp_path, *args)
    (kept,) = tmp_path.glob("*.pickle")
    again = cached_pattern_index(tmp_path, *args)
    kept.write_bytes(b"not a pickle")
    rebuilt = cached_pattern_index(tmp_path, *args)
    for index in (first, again, rebuilt):
        for mine, theirs in zip(index.arrays().values(), built.arrays().values()):
            np.testing.assert_array_equal(mine, theirs)
    assert kept.read_bytes() != b"not a pickle"  # written again
