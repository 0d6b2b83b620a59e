"""COSMOS's polling against the rendering capture source: GO, then read the result length (EDAC
0x004C) every 100 ms until it says ready; every GO's result must come, with its status OK.

How many polls a result takes is a timing figure, not a test: ``bench/bench_start.py`` prints it
against COSMOS's 10 polls, after a start and after a catalog COMMIT (docs/e2e.md, "Ready at
once"). Here the polling only has a hang guard."""

import time

import guards
import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.image_io import catalog_to_image
from firmware_model.reference_frames import matrix_to_quat
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.link.client import Client
from ground.link.solve_report import solve_record
from ground.sim.device_process import pick_attitudes, start_device, stop_device
from protocol import result

POLL_S = 0.1  # the COSMOS driver's practice (docs/ICD.md, timing): every 100 ms
GOS = 8


def _poll_until_ready(c: Client) -> None:
    """Polls (every POLL_S) until the result length says ready (a hang guard of guards.HANG_S)."""
    for _ in range(int(guards.HANG_S / POLL_S)):
        time.sleep(POLL_S)
        if c.result_length() == result.STANDARD_LENGTH:
            return
    raise AssertionError(f"no result after {guards.HANG_S} s of polling")


def test_cosmos_polling_never_times_out_against_the_sky_source(tmp_path):
    catalog = build_catalog(CatalogDesign())
    attitudes = pick_attitudes(catalog, CameraModel.reference_design(), GOS + 1, np.random.default_rng(15))
    schedule = tmp_path / "schedule.csv"
    rows = [",".join(f"{v:.12f}" for v in matrix_to_quat(a)) for a in attitudes]
    schedule.write_text("qw,qx,qy,qz\n" + "\n".join(rows) + "\n")
    proc, pty = start_device(tmp_path / "state", "--sky", str(schedule))
    statuses = []
    try:
        with Client(pty, timeout=guards.REPLY_S) as c:
            c.init()
            c.upload(0, catalog_to_image(catalog), progress=False)
            c.go_and_wait(timeout=30)  # the warm-up (module docstring)
            for _ in range(GOS):
                c.go()
                _poll_until_ready(c)
                statuses.append(solve_record(c.read_result_record())["status"])
    finally:
        assert stop_device(proc) == 0
    assert statuses.count("OK") == GOS, statuses  # the schedule's rows 2..9
