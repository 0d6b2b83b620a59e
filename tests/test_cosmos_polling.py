"""COSMOS's polling against the rendering capture source (issue 15): GO, then read the result
length (EDAC 0x004C) every 100 ms, at most 10 times; the result must be ready every time.

The first GO after a catalog commit also waits for the catalog's pattern index, which the device
builds in the background after the commit (0.4-1.6 s, ``PipelineSolver.prepare``): it is the
warm-up here, as an operator's first solve after a catalog upload."""

import time

import guards
import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.image_io import catalog_to_image
from firmware_model.reference_frames import matrix_to_quat
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.cli.end_to_end import pick_attitudes, start_device, stop_device
from ground.link.client import Client
from ground.link.solve_report import solve_record
from protocol import result

POLL_S, POLLS = 0.1, 10  # the COSMOS driver's practice (docs/ICD.md, timing)
GOS = 8


def _polls_until_ready(c: Client) -> int:
    """Polls (every POLL_S) until the result length says ready; POLLS + 1 when COSMOS gives up."""
    for k in range(1, POLLS + 1):
        time.sleep(POLL_S)
        if c.result_length() == result.STANDARD_LENGTH:
            return k
    return POLLS + 1


def test_cosmos_polling_never_times_out_against_the_sky_source(tmp_path):
    catalog = build_catalog(CatalogDesign())
    attitudes = pick_attitudes(catalog, CameraModel.reference_design(), GOS + 1, np.random.default_rng(15))
    schedule = tmp_path / "schedule.csv"
    rows = [",".join(f"{v:.12f}" for v in matrix_to_quat(a)) for a in attitudes]
    schedule.write_text("qw,qx,qy,qz\n" + "\n".join(rows) + "\n")
    proc, pty = start_device(tmp_path / "state", "--sky", str(schedule))
    polls_used, statuses = [], []
    try:
        with Client(pty, timeout=guards.REPLY_S) as c:
            c.init()
            c.upload(0, catalog_to_image(catalog), progress=False)
            c.go_and_wait(timeout=30)  # the warm-up (module docstring)
            for _ in range(GOS):
                c.go()
                polls = _polls_until_ready(c)
                polls_used.append(polls)
                if polls <= POLLS:
                    statuses.append(solve_record(c.read_result_record())["status"])
    finally:
        assert stop_device(proc) == 0
    assert max(polls_used) <= POLLS, polls_used
    assert statuses.count("OK") == GOS, statuses  # the schedule's rows 2..9
