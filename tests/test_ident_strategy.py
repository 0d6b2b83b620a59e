"""The identification strategy (firmware_model/ident/strategy.py): mode and method enums, the
order of the geometric ladder, typed timings, and that the frame-level entry point gives the
answers of the vector-level solver and its mono fallback."""

import json

import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.device.sensor_input import DeviceParams
from firmware_model.ident.consensus import Outcome
from firmware_model.ident.solver import Method, Mode, SolveParams, SolveTimings, method_code
from firmware_model.ident.strategy import (
    IdentificationInput,
    IdentifyTimings,
    SolveResult,
    StrategyParams,
    bound_roll,
    brightest_eta,
    geometric_fallback,
    geometric_route,
    identify,
    solve,
)
from firmware_model.ident.verify import FieldOfView
from firmware_model.pipeline.solve_types import STAGES, PipelineOutput, PipelineParams, StageTimings
from firmware_model.reference_frames import attitude_from_radec_roll
from ground.link.solve_report import METHODS, record_from_output
from ground.sim import whole_sky as skysim
from protocol.commands import SlotRejected
from protocol.result import MethodCode, Status

CAM = CameraModel.reference_design()


@pytest.fixture(scope="module")
def catalog():
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    return build_catalog(CatalogDesign(sigma_rg=0.05, sigma_bg=0.05))


def test_mode_parses_user_text_with_a_one_line_error():
    assert Mode.parse("colour") is Mode.COLOUR and Mode.parse(Mode.AUTO) is Mode.AUTO
    assert Mode.GEOMETRIC == "geometric" and f"{Mode.AUTO}" == "auto" and json.dumps(Mode.COLOUR) == '"colour"'
    for bad in ("psychic", 3, None, ["auto"]):
        with pytest.raises(ValueError, match=r"^mode must be auto, colour or geometric, got ") as exc:
            Mode.parse(bad)
        assert "\n" not in str(exc.value)
    with pytest.raises(SlotRejected, match="mode must be auto, colour or geometric, got 'psychic'"):
        DeviceParams.from_json(b'{"mode": "psychic"}')
    assert DeviceParams.from_json(b'{"mode": "geometric"}').mode is Mode.GEOMETRIC


def test_roll_sigma_bound_holds_high_confidence_back_and_is_a_parameter():
    deg2 = np.radians(1.0) ** 2
    loose = SolveResult(Outcome.HIGH_CONFIDENCE, covariance=np.diag([1e-8, 1e-8, 0.2**2 * deg2]))
    out = bound_roll(loose, np.radians(0.1))
    assert out.status is Outcome.LOW_CONFIDENCE and out.roll_limited and "roll sigma 0.2 deg" in out.reason
    tight = SolveResult(Outcome.HIGH_CONFIDENCE, covariance=np.diag([1e-8, 1e-8, 0.05**2 * deg2]))
    assert bound_roll(tight, np.radians(0.1)).status is Outcome.HIGH_CONFIDENCE
    assert SolveParams().max_roll_sigma == pytest.approx(np.radians(0.1))
    dp = DeviceParams.from_json(b'{"max_roll_sigma_deg": 0.5}')
    assert dp.apply(PipelineParams()).solve.max_roll_sigma == pytest.approx(np.radians(0.5))
    with pytest.raises(SlotRejected, match="max_roll_sigma_deg must be a number"):
        DeviceParams.from_json(b'{"max_roll_sigma_deg": -1}')


def test_noise_probe_is_a_parameter_of_the_device_and_the_offline_paths():
    assert SolveParams().noise_probe_px == 1.0
    dp = DeviceParams.from_json(b'{"noise_probe_px": 0}')
    assert dp.apply(PipelineParams()).solve.noise_probe_px == 0.0
    assert DeviceParams.from_json(b'{"noise_probe_px": 2.5}').apply(PipelineParams()).solve.noise_probe_px == 2.5
    with pytest.raises(SlotRejected, match=r"noise_probe_px must be a number in \[0, 20\)"):
        DeviceParams.from_json(b'{"noise_probe_px": 25}')


def test_eta_on_the_brightest_detections():
    from firmware_model.ident.consensus import ConsensusParams

    cp = ConsensusParams()
    assert brightest_eta(np.array([0, 1, 3, 30, 31]), cp)  # 3 of the brightest 4
    assert not brightest_eta(np.array([0, 5, 9, 20]), cp)  # never eta of a prefix of at least 4
    assert not brightest_eta(np.array([0, 1, 2, 30]), ConsensusParams(eta_prefix_min=0))


def test_method_codes_are_the_wire_values_and_the_report_names():
    assert [m.code for m in Method] == [
        MethodCode.COLOUR,
        MethodCode.GEOMETRIC,
        MethodCode.GEOMETRIC_CONSENSUS,
        MethodCode.PATTERN,
        MethodCode.TRACKING,
    ]
    assert [int(c) for c in MethodCode] == [0, 1, 2, 3, 4, 5]
    assert method_code(None) == 0 and method_code(Method.PATTERN) == 4 and method_code(Method.TRACKING) == 5
    assert METHODS == {0: "", 1: "colour", 2: "geometric", 3: "geometric-consensus", 4: "pattern", 5: "tracking"}


def test_outcome_prints_its_value():
    assert str(Outcome.NO_MATCH) == "NO_MATCH" and f"{Outcome.HIGH_CONFIDENCE}" == "HIGH_CONFIDENCE"
    assert json.dumps({"status": Outcome.LOW_CONFIDENCE}) == '{"status": "LOW_CONFIDENCE"}'


def test_geometric_route_is_one_solve_up_to_the_cap(catalog, monkeypatch):
    """No ladder of smaller solves: one solve on the brightest detections up to the density cap,
    every detection without a cap (the whole-sky simulation)."""
    from firmware_model.ident import strategy

    scene = _scene(catalog, colour=False)
    det = IdentificationInput(scene.vectors, scene.rg, scene.bg)
    sizes: list[int] = []
    real = strategy.solve_rows

    def counted(det, rows, *args):
        sizes.append(len(rows))
        return real(det, rows, *args)

    monkeypatch.setattr(strategy, "solve_rows", counted)
    for cap, given in ((12, 12), (len(det) + 5, len(det)), (None, len(det))):
        sizes.clear()
        found = geometric_route(
            det, catalog, StrategyParams(solve=_params(Mode.GEOMETRIC), geometric_cap=cap), IdentifyTimings()
        )
        assert sizes == [given] and found.status is not Outcome.NO_MATCH


def test_timings_are_records_with_the_reported_stages():
    assert list(StageTimings().to_dict()) == list(STAGES)
    t = StageTimings(detect=0.001, fit=0.002, vectors=0.003)
    t.add_solve(solve(np.zeros((2, 2)), None, None, None, SolveParams()))  # refused before the catalog
    assert isinstance(t, IdentifyTimings) and t.identify >= 0.0 and t.attitude == 0.0
    rec = record_from_output(PipelineOutput(Status.NO_MATCH, "x", timings=t))
    assert list(rec["timings_s"]) == list(STAGES)
    assert rec["timings_s"]["fit"] == pytest.approx(0.002) and rec["timings_s"]["total"] == 0.0
    assert set(vars(SolveTimings())) == {"validate", "match", "verify", "total"}


def _scene(catalog, colour, seed=3):
    rng = np.random.default_rng(seed)
    a = attitude_from_radec_roll(1.1, 0.3, 0.7)
    model = skysim.ErrorModel(0.2, 0.05, 2.0, 0.05)
    return skysim.observe(catalog, a, CAM, model, rng, colour=colour)


def _params(mode):
    return SolveParams(mode=mode, sigma_vec=0.2 / CAM.f, fov=FieldOfView.from_camera(CAM, 0.0))


@pytest.mark.parametrize("mode", [Mode.COLOUR, Mode.GEOMETRIC, Mode.AUTO])
def test_identify_on_every_detection_is_the_solver(catalog, mode):
    scene = _scene(catalog, colour=mode is not Mode.GEOMETRIC)
    params = _params(mode)
    one = solve(scene.vectors, scene.rg, scene.bg, catalog, params)
    strategy = StrategyParams(solve=params, geometric_fallback=False, colour_fallback=False)
    timings = IdentifyTimings()
    found = identify(IdentificationInput(scene.vectors, scene.rg, scene.bg), catalog, strategy, timings)
    assert found.status is one.status is Outcome.HIGH_CONFIDENCE
    assert np.array_equal(found.rows, np.arange(len(scene.vectors)))
    assert np.array_equal(found.solution.matched_star_id, one.matched_star_id)
    assert np.array_equal(found.solution.q_icrs_to_sensor, one.q_icrs_to_sensor)
    assert found.solution.method == (Method.GEOMETRIC if mode is Mode.GEOMETRIC else Method.COLOUR)
    assert timings.identify > 0.0 and timings.attitude > 0.0


def test_mono_fallback_runs_consensus_on_geometry_when_geometry_finds_nothing(catalog):
    # pose 6656 of the impaired mono whole-sky run: 4-star and triangle matching find nothing
    cfg = skysim.ColourSimConfig(
        n_boresights=5000, n_roll=2, colour=False, model=skysim.ErrorModel(0.2, 0.05, 3.0, 0.1)
    )
    b_idx, r_idx = divmod(6656, cfg.n_roll)
    rng = np.random.default_rng([cfg.seed, 6656])
    roll = 2 * np.pi * (r_idx + rng.random()) / cfg.n_roll
    ra, dec = skysim.vec_to_radec(skysim.spiral_boresights(cfg.n_boresights)[b_idx])
    scene = skysim.observe(
        catalog, attitude_from_radec_roll(float(ra), float(dec), roll), CAM, cfg.model, rng, colour=False
    )
    det = IdentificationInput(scene.vectors, scene.rg, scene.bg)
    params = _params(Mode.GEOMETRIC)
    off = identify(det, catalog, StrategyParams(solve=params, geometric_fallback=False))
    assert off.status is Outcome.NO_MATCH and off.solution.method is Method.GEOMETRIC
    found = identify(det, catalog, StrategyParams(solve=params))
    assert found.status is Outcome.HIGH_CONFIDENCE and found.solution.method is Method.GEOMETRIC_CONSENSUS
    assert np.all(scene.truth[found.rows[found.solution.matched_det]] == found.solution.matched_cat)
    assert not off.fallback_due and not found.fallback_due
    # deferred (the pipeline's optics search goes first): the route's answer says the fallback is due,
    # and the fallback run afterwards is the answer identify would have given
    deferred = StrategyParams(solve=params, defer_fallback=True)
    due = identify(det, catalog, deferred)
    assert due.status is Outcome.NO_MATCH and due.fallback_due
    late = geometric_fallback(det, catalog, deferred, IdentifyTimings())
    assert late.status is Outcome.HIGH_CONFIDENCE and late.solution.method is Method.GEOMETRIC_CONSENSUS
    assert np.array_equal(late.solution.matched_star_id, found.solution.matched_star_id)
    assert np.array_equal(late.solution.q_icrs_to_sensor, found.solution.q_icrs_to_sensor)


def test_a_deferred_fallback_that_finds_nothing_says_why_on_no_detection(catalog):
    """The mono fallback its caller runs (deferred) answers NO_MATCH with its own reason and no
    detection rows when its consensus finds nothing (a frame of scattered hot pixels)."""
    rng = np.random.default_rng(5)
    n = 12
    vectors = CAM.pixel_to_vector(rng.uniform(0, CAM.width, n), rng.uniform(0, CAM.height, n))
    nothing = IdentificationInput(vectors, np.full(n, np.nan), np.full(n, np.nan))
    late = geometric_fallback(nothing, catalog, StrategyParams(solve=_params(Mode.GEOMETRIC)), IdentifyTimings())
    assert late.status is Outcome.NO_MATCH and late.solution.reason.startswith("mono consensus fallback: ")
    assert len(late.rows) == 0
