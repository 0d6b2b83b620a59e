"""COSMOS's polling against the rendering capture source: GO, then read the result length (EDAC
0x004C) every 100 ms until it says ready; every GO's result must come, with its status OK. Every
GO is polled, the first after a catalog COMMIT and the first after a device start included (the
GOs a warm-up would hide: the COMMIT's pattern index may still be building, a start loads it).

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
GOS = 4  #: polled GOs per device run (two runs: after a COMMIT, after a start)


def _poll_until_ready(c: Client) -> int:
    """Polls (every POLL_S) until the result length says ready (a hang guard of guards.HANG_S);
    the number of polls."""
    for polls in range(1, int(guards.HANG_S / POLL_S) + 1):
        time.sleep(POLL_S)
        if c.result_length() == result.STANDARD_LENGTH:
            return polls
    raise AssertionError(f"no result after {guards.HANG_S} s of polling")


def _polled_gos(c: Client, n: int) -> list[tuple[str, int, int]]:
    """``n`` GOs, each polled: (status, sequence, polls) of each."""
    out = []
    for _ in range(n):
        c.go()
        polls = _poll_until_ready(c)
        rec = c.read_result_record()
        out.append((solve_record(rec)["status"], int(rec["sequence"]), polls))
    return out


def test_cosmos_polling_never_times_out_against_the_sky_source(tmp_path):
    catalog = build_catalog(CatalogDesign())
    attitudes = pick_attitudes(catalog, CameraModel.reference_design(), GOS, np.random.default_rng(15))
    schedule = tmp_path / "schedule.csv"
    rows = [",".join(f"{v:.12f}" for v in matrix_to_quat(a)) for a in attitudes]
    schedule.write_text("qw,qx,qy,qz\n" + "\n".join(rows) + "\n")
    runs = {}
    for run in ("after COMMIT", "after start"):  # the second: the same state, the catalog kept
        proc, pty = start_device(tmp_path / "state", "--sky", str(schedule))
        try:
            with Client(pty, timeout=guards.REPLY_S) as c:
                c.init()
                if run == "after COMMIT":
                    c.upload(0, catalog_to_image(catalog), progress=False)  # its COMMIT builds the index
                runs[run] = _polled_gos(c, GOS)  # the first GO of each run polled like the others
        finally:
            assert stop_device(proc) == 0
    print({run: [polls for *_, polls in gos] for run, gos in runs.items()})  # polls: a figure, not a test
    for run, gos in runs.items():
        assert [status for status, *_ in gos] == ["OK"] * GOS, (run, gos)
        assert [seq for _, seq, _ in gos] == list(range(1, GOS + 1)), (run, gos)  # each GO its own result
