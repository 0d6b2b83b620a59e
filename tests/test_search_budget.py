"""Searches bounded by counted work (firmware_model/ident/budget.py): a budget reached is a typed
NO_MATCH naming the count, the clock cannot change an answer, and the flight-timing deadline is
opt-in and reported when it stops a search."""

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import require_shared
from ident_sky import random_attitude, random_catalog, scene

from firmware_model.camera import CameraModel
from firmware_model.device.cli import build_device, build_parser, main
from firmware_model.device.sensor_input import DeviceParams
from firmware_model.ident.budget import SearchBudget, Stop
from firmware_model.ident.consensus import Outcome
from firmware_model.ident.solver import SolveParams
from firmware_model.ident.strategy import IdentificationInput, IdentifyTimings, StrategyParams, identify, solve
from firmware_model.ident.verify import FieldOfView
from firmware_model.pipeline.result_fields import result_fields
from firmware_model.pipeline.solve_types import PipelineOutput, PipelineParams
from ground.link.solve_report import solve_record
from protocol import result
from protocol.commands import SlotRejected
from protocol.result import Status

CAM = CameraModel.reference_design()
PARAMS = SolveParams(mode="colour", sigma_vec=0.2 / CAM.f, fov=FieldOfView.from_camera(CAM, 0.0))


@pytest.fixture(scope="module")
def catalogs():
    return random_catalog(seed=0), random_catalog(seed=1)


def _foreign_scene(catalogs, seed=2):
    """Stars of another sky: every hypothesis is verified, and every one fails."""
    v, rg, bg, _ = scene(
        catalogs[1], random_attitude(np.random.default_rng(seed)), np.random.default_rng(seed), min_stars=10
    )
    return v, rg, bg


def _load_the_clock(monkeypatch) -> None:
    """``time.perf_counter`` jumps a minute at every reading from now on: any machine under any load."""
    now = [time.perf_counter()]

    def busy() -> float:
        now[0] += 60.0
        return now[0]

    monkeypatch.setattr(time, "perf_counter", busy)


def test_a_budget_reached_is_a_no_match_naming_the_count(catalogs):
    v, rg, bg = _foreign_scene(catalogs)
    full = solve(v, rg, bg, catalogs[0], PARAMS)
    assert full.status is Outcome.NO_MATCH and full.stopped is Stop.NONE and full.verifications > 3
    cut = solve(v, rg, bg, catalogs[0], replace(PARAMS, max_verifications=3))
    assert cut.status is Outcome.NO_MATCH
    assert cut.stopped is Stop.COUNT and cut.verifications == 3
    assert cut.reason == "search budget of 3 verifications reached"
    ledger = IdentifyTimings()
    found = identify(
        IdentificationInput(v, rg, bg), catalogs[0], StrategyParams(solve=replace(PARAMS, max_verifications=3)), ledger
    )
    assert found.status is Outcome.NO_MATCH and ledger.stopped is Stop.COUNT and ledger.verifications >= 3


def test_the_clock_cannot_change_an_answer(catalogs, monkeypatch):
    """A clock that jumps a minute at every reading (a machine under any load) gives the same
    answers, down to the counted work, as the real one."""
    cat = catalogs[0]
    rng = np.random.default_rng(7)
    scenes = [_foreign_scene(catalogs, 3)]
    for _ in range(4):
        v, rg, bg, _ = scene(cat, random_attitude(rng), rng, min_stars=6)
        false = CAM.pixel_to_vector(rng.uniform(0, CAM.width, 5), rng.uniform(0, CAM.height, 5))
        scenes.append((np.vstack([false, v]), np.r_[rng.uniform(0.3, 1.3, 5), rg], np.r_[rng.uniform(0.3, 1.4, 5), bg]))

    def answers():
        out = []
        for mode in ("colour", "geometric"):
            for v, rg, bg in scenes:
                s = solve(v, rg, bg, cat, replace(PARAMS, mode=mode))
                out.append((s.status, s.reason, s.matched_cat.tolist(), s.verifications, s.stopped, s.q_icrs_to_sensor))
        return out

    quiet = answers()
    _load_the_clock(monkeypatch)
    loaded = answers()
    assert [a[:5] for a in loaded] == [a[:5] for a in quiet]
    assert all((a[5] is None and b[5] is None) or np.array_equal(a[5], b[5]) for a, b in zip(quiet, loaded))
    assert any(a[0] is Outcome.HIGH_CONFIDENCE for a in quiet) and any(a[0] is Outcome.NO_MATCH for a in quiet)


def test_flight_timing_deadline_stops_the_search_and_says_so(catalogs):
    v, rg, bg = _foreign_scene(catalogs)
    late = solve(v, rg, bg, catalogs[0], replace(PARAMS, deadline=time.perf_counter() - 1.0))
    assert late.status is Outcome.NO_MATCH and late.stopped is Stop.DEADLINE
    assert late.reason == "flight-timing deadline missed"
    budget = SearchBudget(5, deadline=None)
    for _ in range(4):
        budget.spend()
    assert not budget.exhausted and budget.reason == ""
    budget.spend()
    assert budget.exhausted and budget.stopped is Stop.COUNT


def test_the_result_carries_the_search_block():
    out = PipelineOutput(Status.NO_MATCH, "search budget of 48 pattern seeds reached")
    out.timings.seeds, out.timings.verifications, out.timings.stopped = 48, 1234, Stop.COUNT
    fields = result_fields(out)
    assert fields["ext.search_flags"] == result.SEARCH_BUDGET_REACHED
    assert (fields["ext.seeds"], fields["ext.verifications"]) == (48, 1234)
    out.timings.stopped = Stop.DEADLINE
    assert result_fields(out)["ext.search_flags"] == result.DEADLINE_MISSED
    fields["ext.search_flags"] = result.SEARCH_BUDGET_REACHED
    search = solve_record(result.parse(result.build(fields)))["search"]
    assert search == {"verifications": 1234, "seeds": 48, "budget_reached": True, "deadline_missed": False}


def test_the_parameter_file_sets_the_counted_budgets():
    p = DeviceParams.from_json(b'{"max_verifications": 50, "max_seeds": 7, "max_frame_verifications": 900}')
    applied = p.apply(PipelineParams())
    assert applied.solve.max_verifications == 50
    assert applied.optics is not None and (applied.optics.max_seeds, applied.optics.max_verifications) == (7, 900)
    for bad in (b'{"max_seeds": 0}', b'{"max_verifications": 2.5}', b'{"max_seeds": true}', b'{"max_seeds": 1000001}'):
        with pytest.raises(SlotRejected, match="must be a whole number in"):
            DeviceParams.from_json(bad)
    with pytest.raises(SlotRejected, match="time_budget_s is gone: searches are bounded by counted work") as exc:
        DeviceParams.from_json(b'{"time_budget_s": 0.05}')
    assert "\n" not in exc.value.message


def test_the_deadline_is_flight_timing_only(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--pty", "--deadline-ms", "500"])
    assert exc.value.code == 2
    assert "--deadline-ms and --boot-ms need --timing realistic" in capsys.readouterr().err
    args = build_parser().parse_args(["--pty", "--timing", "realistic", "--deadline-ms", "500"])
    solver = build_device(args).solver
    assert solver.params.flight_deadline_s == 0.5
    assert build_device(build_parser().parse_args(["--pty"])).solver.params.flight_deadline_s is None


TREE = Path(__file__).resolve().parents[2] / "shared" / "data" / "frames" / "colour-real" / "tree.jpg"


def test_a_real_frame_spending_its_whole_search_gives_one_answer_under_any_clock(monkeypatch):
    """tree.jpg with its field of view only: clutter holds the brightest detections, so the optics
    search spends its counted budget (seeds or the frame's verifications); on a loaded machine
    its old 1.5 s clock ran out earlier."""
    require_shared(TREE)
    from ground.api import solve_image

    fov = json.loads((TREE.parent / "reference_pointing.json").read_text())["tree.jpg"]["fov_deg"][0]
    quiet = solve_image(TREE, fov_deg=fov)
    _load_the_clock(monkeypatch)
    loaded = solve_image(TREE, fov_deg=fov)
    search = quiet.record["search"]
    assert search["budget_reached"] and (search["seeds"] == 48 or search["verifications"] >= 2000)
    assert quiet.reason.startswith(("search budget of 48 pattern seeds reached", "search budget of 2000 verifications"))
    for key in ("status", "reason", "q_icrs_to_sensor"):
        assert getattr(loaded, key) == getattr(quiet, key)
    assert [s.catalog_id for s in loaded.stars] == [s.catalog_id for s in quiet.stars]
    assert loaded.record["search"] == quiet.record["search"]


def test_the_documented_solve_plan_is_the_code_s():
    from firmware_model.pipeline.run import SOLVE_PLAN, plan_table

    docs = (Path(__file__).resolve().parents[1] / "docs" / "identification.md").read_text()
    assert plan_table() in docs
    names = {s.name for s in SOLVE_PLAN} | {"done"}
    assert all(set(s.hands_to) <= names for s in SOLVE_PLAN)  # every hand-off names a stage of the plan


def test_a_camera_gets_the_same_pattern_index_whatever_was_solved_before(catalogs):
    """The pattern index serving a camera is a function of the camera alone (a fixed grid of
    fields), not of the fields an earlier solve left cached: a field a few per cent off solved first
    used to lend its index to the next one."""
    from firmware_model.pipeline import scale_free

    cat = catalogs[0]
    a, b = CameraModel.from_fov(1024, 1024, 10.0), CameraModel.from_fov(1024, 1024, 10.3)
    key_b = scale_free.pattern_field(b)
    scale_free.set_catalog_patterns(cat, scale_free.pattern_field(a), "a's index")
    assert scale_free.pattern_field(b) == key_b != scale_free.pattern_field(a)
    assert scale_free.catalog_patterns(cat, a) == "a's index"
    fitted = replace(a, f=a.f * 1.001)  # a focal length fitted to one frame: the same index
    assert scale_free.pattern_field(fitted) == scale_free.pattern_field(a)
    assert scale_free.catalog_patterns(cat, fitted) == "a's index"
    cat.__dict__.pop("_pattern_cache")


def test_a_budget_reason_counts_in_plain_words():
    from firmware_model.ident.budget import stop_reason

    assert stop_reason(Stop.COUNT, 1, "pattern seed") == "search budget of 1 pattern seed reached"
    assert (
        stop_reason(Stop.COUNT, 2000, "verification", " per frame")
        == "search budget of 2000 verifications per frame reached"
    )
    assert stop_reason(Stop.DEADLINE, 5, "verification") == "flight-timing deadline missed"
    assert stop_reason(Stop.NONE, 5, "verification") == ""
