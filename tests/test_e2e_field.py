"""Field workflows end to end: the device rendering the sky from an attitude schedule, a colour
calibration fitted from a run and uploaded as a parameter set, and the table-5 replay."""

import subprocess
import sys
from pathlib import Path

import guards
import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.catalog.image_io import catalog_to_image
from firmware_model.pipeline.frame_readers import frame_files, read_frame
from firmware_model.pipeline.raw_frame import frame_to_bytes
from firmware_model.reference_frames import matrix_to_quat, quat_to_matrix, rotation_angle
from ground.analysis.replay import replay
from ground.analysis.table5 import TABLE5_MODES, table5
from ground.calibration.corrections import ColourCorrection
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.link.client import Client
from ground.link.solve_report import solve_record
from ground.sim.device_process import pick_attitudes, start_device, stop_device
from ground.sim.frame_writer import write_rendered
from ground.sim.sensor_sim import DetectorModel, Stars, render_frame
from ground.sim.sky_model import sky_stars
from ground.solver import in_process_solver

CAMERA = CameraModel.reference_design()
#: The "atmosphere" of these tests: observed rg, bg are a linear map of the catalog's.
BIAS = np.array([[0.85, 0.0], [0.05, 0.8]]), np.array([0.02, -0.05])


@pytest.fixture(scope="module")
def catalog():
    return build_catalog(CatalogDesign())


def biased_sky() -> Stars:
    s = sky_stars()
    obs = np.column_stack([s.rg, s.bg]) @ BIAS[0].T + BIAS[1]
    return Stars(ids=s.ids, vectors=s.vectors, vmag=s.vmag, rg=obs[:, 0], bg=obs[:, 1])


def test_device_renders_the_sky_from_a_schedule(catalog, tmp_path):
    atts = pick_attitudes(catalog, CAMERA, 2, np.random.default_rng(9))
    schedule = tmp_path / "schedule.csv"
    schedule.write_text(
        "# two exposures\nqw,qx,qy,qz,pattern\n"
        + "".join(",".join(f"{v:.12f}" for v in matrix_to_quat(a)) + f",{p}\n" for a, p in zip(atts, ("RGGB", "MONO")))
    )
    proc, pty = start_device(tmp_path / "state", "--sky", str(schedule))
    try:
        with Client(pty, timeout=guards.REPLY_S) as c:
            c.init()
            c.upload(0, catalog_to_image(catalog), progress=False)
            recs = [solve_record(c.go_and_wait(timeout=60)) for _ in atts]
    finally:
        assert stop_device(proc) == 0
    for rec, a, method in zip(recs, atts, ("colour", "pattern")):  # mono: the brightest stars' pattern
        assert rec["status"] == "OK" and rec["method"] == method
        err = np.degrees(rotation_angle(quat_to_matrix(rec["q_icrs_to_sensor"]), a))
        assert err < 0.01


def test_bad_schedule_is_refused(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("qw,qx,qy,qz\n1,0,0,0.5\n")
    run = subprocess.run(
        [sys.executable, "-m", "firmware_model.device.cli", "--pty", "--sky", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 2 and "row 1: quaternion norm" in run.stderr


@pytest.fixture(scope="module")
def biased_frames(catalog, tmp_path_factory):
    """Six colour frames through the biased 'atmosphere', with truth."""
    d = tmp_path_factory.mktemp("biased")
    sky = biased_sky()
    for k, a in enumerate(pick_attitudes(catalog, CAMERA, 6, np.random.default_rng(21))):
        r = render_frame(sky, a, CAMERA, DetectorModel(), seed=300 + k)
        write_rendered(r, d / f"b{k}.dng")
    return d


def test_colour_calibration_from_a_run_and_on_the_device(catalog, biased_frames, tmp_path):
    summary = replay(
        biased_frames,
        in_process_solver(camera=CAMERA, catalog=catalog),
        tmp_path / "run",
        progress=False,
        make_plots=False,
    )
    assert summary["counts"].get("correct", 0) >= 4
    image = tmp_path / "cat.st16cat"
    image.write_bytes(catalog_to_image(catalog))
    exe = Path(sys.executable).parent / "st16-ground"
    out = tmp_path / "cc.json"
    run = subprocess.run(
        [str(exe), "colour", "fit", str(tmp_path / "run" / "results.jsonl"), "--catalog", str(image), "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    fit = ColourCorrection.from_json(out.read_text())
    assert fit.rms_after < 0.5 * fit.rms_before and fit.n_used >= 20
    # star colours lie near a one-dimensional locus, so the 2 x 2 map is only determined along
    # it: check that the fit takes the biased colours of the catalog's stars back to the catalog
    cat = np.column_stack([catalog.rg, catalog.bg]).astype(float)
    cat = cat[np.isfinite(cat).all(axis=1)]
    observed = cat @ BIAS[0].T + BIAS[1]
    rg, bg = fit.apply(observed[:, 0], observed[:, 1])
    back = np.sqrt(np.mean((np.column_stack([rg, bg]) - cat) ** 2))
    assert back < 0.25 * np.sqrt(np.mean((observed - cat) ** 2))
    # the parameter set goes to the device, which then sees catalog-like colours on the same frame
    frame = frame_to_bytes(read_frame(frame_files(biased_frames)[0]))
    proc, pty = start_device(tmp_path / "state")
    try:
        with Client(pty, timeout=guards.REPLY_S) as c:
            c.init()
            c.upload(0, image.read_bytes(), progress=False)
            c.upload(1, frame, progress=False)
            before = solve_record(c.go_and_wait(timeout=60)), float(c.read_result_record()["ext"]["colour_rms"])
            params = out.with_suffix(".params.json")
            run = subprocess.run(
                [str(exe), "--port", pty, "params", "upload", str(params)], capture_output=True, text=True, timeout=60
            )
            assert run.returncode == 0, run.stderr
            assert c.slot_info(2).active
            c.upload(1, frame, progress=False)
            after = solve_record(c.go_and_wait(timeout=60)), float(c.read_result_record()["ext"]["colour_rms"])
    finally:
        assert stop_device(proc) == 0
    assert before[0]["q_icrs_to_sensor"] is not None and after[0]["status"] == "OK"
    assert after[0]["method"] == "colour"
    assert after[1] < 0.75 * before[1]  # what remains is mostly photon noise of the fainter stars


def test_table5_modes_on_frames_with_truth(catalog, biased_frames):
    out = table5(frame_files(biased_frames), CAMERA, catalog, progress=False)
    assert out["frames"] == 6 and list(out["table"]) == list(TABLE5_MODES)
    for counts in out["table"].values():
        assert sum(counts.values()) == 6
    # removing each star's mean colour error can only help a biased run
    assert out["table"]["ideal colour"]["correct"] >= out["table"]["basic"]["correct"]


def test_offline_replay_corrects_refraction(catalog, tmp_path):
    """A field 20 deg above the horizon rendered through the atmosphere: the refraction-corrected
    solve recovers the attitude; the raw one cannot (refraction ~2.6 arcmin, varying across
    the field by ~2 arcmin)."""
    import astropy.units as u
    from astropy.coordinates import ICRS, SkyCoord
    from astropy.time import Time

    from firmware_model.reference_frames import attitude_from_radec_roll, radec_to_vec, vec_to_radec
    from ground.analysis.replay import Truth, score
    from ground.calibration.corrections import Site, _altaz_frames

    site, when = Site(43.66, -79.38, 100.0, pressure_hpa=1010, temperature_c=0), "2012-02-10T03:00:00"
    vacuum, air = _altaz_frames(site, Time(when, scale="utc"))
    centre = SkyCoord(az=200 * u.deg, alt=20 * u.deg, frame=vacuum).transform_to(ICRS())
    a = attitude_from_radec_roll(centre.ra.rad, centre.dec.rad, 0.7)
    sky = sky_stars()
    near = np.flatnonzero(sky.vectors @ a[2] > np.cos(np.radians(14)))
    true = SkyCoord(*vec_to_radec(sky.vectors[near]), unit="rad", frame=ICRS())
    app = true.transform_to(air)
    seen = SkyCoord(az=app.az, alt=app.alt, frame=vacuum).transform_to(ICRS())
    stars = Stars(
        ids=sky.ids[near],
        vectors=radec_to_vec(seen.ra.rad, seen.dec.rad),
        vmag=sky.vmag[near],
        rg=sky.rg[near],
        bg=sky.bg[near],
    )
    frame = render_frame(stars, a, CAMERA, DetectorModel(), seed=5, timestamp=when + "Z").frame
    truth = Truth(matrix_to_quat(a), np.empty(0, np.int64), np.empty(0), np.empty(0))
    raw = in_process_solver(camera=CAMERA, catalog=catalog).solve(frame).record
    fixed = in_process_solver(camera=CAMERA, catalog=catalog, site=site).solve(frame).record
    assert fixed["refraction"] == "corrected" and fixed["status"] == "OK"
    err_fixed = score(fixed, truth)["attitude_error_deg"] * 3600
    assert err_fixed < 10, err_fixed
    # uncorrected, the differential refraction across the field (~2 arcmin) defeats the
    # rigorous match, or at best leaves the attitude off by about the refraction
    raw_score = score(raw, truth)
    assert raw_score["outcome"] == "no_match" or raw_score["attitude_error_deg"] * 3600 > 60


def _bench_field():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import bench_field

    return bench_field


def test_single_arc_correction_changes_the_delta_zeta_arc_only_by_its_error():
    bf = _bench_field()
    v = CAMERA.pixel_to_vector(np.array([400.0, 500.0, 600.0]), np.array([300.0, 310.0, 330.0]))
    d, e, z = bf.correct_arc(*v, np.radians(2.5e-3))
    assert np.degrees(bf.arc(v[0], v[2]) - bf.arc(d, z)) == pytest.approx(2.5e-3, abs=1e-9)
    assert np.array_equal(e, v[1])
    assert np.cross(v[0], v[2]) @ d == pytest.approx(0, abs=1e-12)  # delta stays on its great circle


def test_the_papers_three_star_run_on_two_belt_frames(catalog, tmp_path):
    """Two rendered belt frames: only the three belt detections go to the matcher, colours through
    the exact inverse of the bench's atmosphere, the coverage test off as for the paper's cut field."""
    from dataclasses import replace

    from firmware_model.pipeline.solve_types import PipelineParams

    bf = _bench_field()
    bf.render_orion(tmp_path, 2, CAMERA)
    b_inv = np.linalg.inv(bf.ATMOSPHERE[0])
    c = -b_inv @ bf.ATMOSPHERE[1]
    beta = (*b_inv.ravel(), *c)
    p = PipelineParams(colour_fallback=False)
    p = replace(p, solve=replace(p.solve, verify=replace(p.solve.verify, min_coverage=0.0)))
    t = bf.belt_table5(frame_files(tmp_path), CAMERA, catalog, beta, p)
    assert (t["frames"], t["missing"]) == (2, 0)
    assert t["table"]["basic"] == {"correct": 2, "incorrect": 0, "no_match": 0, "three_matched": 2}
    assert set(t["stars"]) == {"delta", "epsilon", "zeta"}
    assert abs(t["arc_error_deg"]) < 0.02
    # the default pipeline refuses three stars where some 20 catalog stars are predicted
    d = bf.belt_table5(frame_files(tmp_path), CAMERA, catalog, beta, PipelineParams())
    assert d["table"]["basic"]["no_match"] == 2
