"""Ready at once: what a start imports and draws (no clock here: which modules a fresh interpreter
has loaded, and whether a noise bank was drawn or loaded).

* ``st16-device``'s module imports none of the pipeline, so that the index-building process the
  device spawns (it imports the device's main module first) stays light, and that process runs at
  the device's priority; the ``--sky`` source's
  module imports neither ``scipy.stats`` nor astropy, which only some schedules need.
* A device whose frames carry no time loads no ephemerides (astropy); an uploaded frame with a
  time loads them at its COMMIT, not inside the GO.
* A noise bank kept in a cache folder has the values of a fresh draw, and a damaged file is
  drawn again.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from ground.sim import noise_bank
from ground.sim.noise_bank import NoiseBank
from ground.sim.sensor_sim import DetectorModel

#: Imported by the pipeline or by the sky source's optional features, never by the modules below.
HEAVY = ("numba", "scipy", "astropy", "firmware_model.pipeline.run", "firmware_model.device.sensor_input")


def imported_after(code: str, names=HEAVY) -> dict[str, bool]:
    """Which of ``names`` a fresh interpreter has imported after running ``code``."""
    probe = f"{code}\nimport json, sys\nprint(json.dumps({{m: m in sys.modules for m in {list(names)!r}}}))"
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.splitlines()[-1])


def test_device_module_imports_no_pipeline():
    assert imported_after("import firmware_model.device.cli") == dict.fromkeys(HEAVY, False)


def test_index_process_module_imports_no_pipeline():
    assert imported_after("import firmware_model.device.index_process") == dict.fromkeys(HEAVY, False)


def test_the_index_process_runs_at_the_device_s_priority():
    """Its builds are on the path of the GO that waits for them: a process 10 nice steps lower
    starved them on a busy machine (beside three busy loops the first GO after a new catalog's
    COMMIT waited 15.0 s, against 1.7 s at the device's priority: docs/e2e.md)."""
    code = (
        "import os\nfrom firmware_model.device import index_process\n"
        "before = os.nice(0)\nindex_process.init()\nindex_process.ready()\nprint(os.nice(0) - before)"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert int(run.stdout) == 0


def test_sky_source_module_imports_neither_scipy_stats_nor_astropy():
    names = ("scipy.stats", "astropy")
    assert imported_after("import ground.sim.sky_source", names) == dict.fromkeys(names, False)


SMALL_CAMERA = "from firmware_model.camera import CameraModel\ncam = CameraModel(64, 48, 100.0, 31.5, 23.5)\n"


@pytest.mark.parametrize("timestamp", [None, "2026-03-01T12:00:00"])
def test_a_frame_with_a_time_loads_the_ephemerides_at_its_commit(timestamp):
    code = SMALL_CAMERA + (
        "import numpy as np\n"
        "from firmware_model.device.sensor_input import frame_slot_handler\n"
        "from firmware_model.pipeline.raw_frame import Frame, frame_to_bytes\n"
        f"frame = Frame(np.zeros((48, 64), np.uint16), timestamp={timestamp!r})\n"
        "frame_slot_handler(cam).activate(frame_to_bytes(frame))\n"
    )
    assert imported_after(code, ("astropy",)) == {"astropy": timestamp is not None}


def test_solver_loads_the_ephemerides_unless_told_no_frame_has_a_time():
    code = SMALL_CAMERA + "from firmware_model.device.sensor_input import PipelineSolver\n"
    assert imported_after(code + "PipelineSolver(cam, ephemerides=False)", ("astropy",)) == {"astropy": False}
    assert imported_after(code + "PipelineSolver(cam)", ("astropy",)) == {"astropy": True}


SHAPE = (24, 32)


def test_a_cached_noise_bank_is_the_fresh_draw(tmp_path, monkeypatch):
    det = DetectorModel()
    fresh = NoiseBank(det, SHAPE, seed=4)
    first = NoiseBank(det, SHAPE, seed=4, cache_dir=tmp_path)  # drawn and kept
    assert len(list(tmp_path.glob("bank-*.npy"))) == 1

    def no_draw(*args):
        raise AssertionError("drawn again")

    monkeypatch.setattr(noise_bank, "_draw", no_draw)
    loaded = NoiseBank(det, SHAPE, seed=4, cache_dir=tmp_path)
    for bank in (first, loaded):
        assert len(bank.banks) == len(fresh.banks)
        for a, b in zip(bank.banks, fresh.banks, strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(bank.base, fresh.base)
    with pytest.raises(AssertionError, match="drawn again"):  # another seed is another file
        NoiseBank(det, SHAPE, seed=5, cache_dir=tmp_path)


def test_a_damaged_noise_bank_file_is_drawn_again(tmp_path):
    det = DetectorModel()
    NoiseBank(det, SHAPE, seed=4, cache_dir=tmp_path)
    (kept,) = tmp_path.glob("bank-*.npy")
    kept.write_bytes(kept.read_bytes()[:100])
    again = NoiseBank(det, SHAPE, seed=4, cache_dir=tmp_path)
    for a, b in zip(again.banks, NoiseBank(det, SHAPE, seed=4).banks, strict=True):
        np.testing.assert_array_equal(a, b)
    assert kept.stat().st_size > 100  # written whole again


def test_the_cache_keeps_the_newest_banks_only(tmp_path):
    for seed in range(noise_bank.CACHE_FILES_KEPT + 2):
        NoiseBank(DetectorModel(), SHAPE, seed=seed, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("bank-*.npy"))) == noise_bank.CACHE_FILES_KEPT
