"""``ground.solver``: the options become a route in one place, and a solve leaves the caller's
catalog as it found it (the device's twin stays the device after a field-of-view search)."""

import os
import sys
from pathlib import Path
from types import SimpleNamespace

import guards
import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.sky_search import FieldRange
from firmware_model.pipeline.solve_types import PipelineParams
from ground.solver import InProcessSolver, OptionsError, Route, choose_route, in_process_solver


@pytest.mark.parametrize(
    "camera,catalog,fov,site,route",
    [
        (True, True, False, False, Route.TWIN),
        (True, True, False, True, Route.TWIN),
        (True, False, False, False, Route.FIELD_CATALOG),
        (True, False, False, True, Route.FIELD_CATALOG),
        (False, True, True, False, Route.SKY_SEARCH),
        (False, False, True, False, Route.SKY_SEARCH),
        (False, False, False, False, Route.SKY_SEARCH),  # blind
    ],
)
def test_each_set_of_options_has_one_route(camera, catalog, fov, site, route):
    assert choose_route(camera, catalog, fov, site) is route


@pytest.mark.parametrize(
    "camera,fov,site,words",
    [(True, True, False, "not both"), (False, True, True, "needs a calibrated camera"), (False, False, True, "site")],
)
def test_contradicting_options_are_refused_in_one_line(camera, fov, site, words):
    with pytest.raises(OptionsError, match=words) as err:
        choose_route(camera, False, fov, site)
    assert "\n" not in str(err.value) and isinstance(err.value, ValueError)


def _untimed(record: dict) -> dict:
    """``record`` without its timings (``bench/check_solve_records.py``'s comparison)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from check_solve_records import untimed

    return untimed(record)


def _state(catalog) -> dict:
    """What a solve could leave on a catalog object: each attribute's object, and the entries of
    its own pattern indexes (``scale_free.catalog_patterns``)."""
    return {**{k: id(v) for k, v in vars(catalog).items()}, "patterns": dict(vars(catalog).get("_pattern_cache", {}))}


def test_a_field_of_view_search_leaves_the_callers_catalog_as_it_found_it(synthetic_catalog):
    """A frame of the synthetic catalog's stars solved as the twin (the catalog's own patterns),
    then its field of view searched with the same catalog object and a whole-sky index of those
    stars given as the solve's argument: the search adds, replaces and removes nothing on the
    object, and the twin's record is the same after it."""
    from firmware_model.pipeline.sky_patterns import sky_pattern_index
    from firmware_model.pipeline.sky_search import SkySearch
    from firmware_model.reference_frames import radec_to_vec

    cat = synthetic_catalog(300)
    camera = CameraModel.from_horizontal_fov(640, 480, 20.0)
    z = radec_to_vec(0.3, 0.0)
    east = np.cross([0.0, 0.0, 1.0], z) / np.linalg.norm(np.cross([0.0, 0.0, 1.0], z))
    px, py = camera.vector_to_pixel(cat.vec @ np.vstack([east, np.cross(z, east), z]).T)
    on = np.flatnonzero(np.isfinite(px) & (px > 3) & (px < 636) & (py > 3) & (py < 476))
    yy, xx = np.mgrid[0:480, 0:640]
    pixels = np.full((480, 640), 100.0)
    for i in on:  # 1.2 px Gaussian stars, 4000 counts at V 1
        pixels += 4000.0 * 10 ** (-0.4 * (cat.mag[i] - 1.0)) * np.exp(-((xx - px[i]) ** 2 + (yy - py[i]) ** 2) / 2.88)
    frame = Frame(np.random.default_rng(1).normal(pixels, 3.0).astype(np.float32), "MONO", white_level=65535.0)
    twin = InProcessSolver(Route.TWIN, PipelineParams(), camera=camera, catalog=cat)
    assert twin.patterns is None
    before = twin.solve(frame).record
    state = _state(cat)
    order = np.argsort(cat.mag, kind="stable")
    index = sky_pattern_index(cat.vec[order], cat.mag[order])
    sky = SimpleNamespace(index=index, search=SkySearch(index, cat.mag[order]), load_s=0.0)
    search = InProcessSolver(Route.SKY_SEARCH, PipelineParams(), catalog=cat, database=sky, fov=FieldRange.hint(20.0))
    assert search.patterns is index
    found = search.solve(frame).record
    assert found["status"] == "OK" and found["sky"]["taken"]
    assert _state(cat) == state
    assert before["status"] == "OK" and _untimed(twin.solve(frame).record) == _untimed(before)


def test_the_twin_gives_the_same_records_before_and_after_a_search_on_its_catalog(shared_data):
    """The tetra3 frames solved as the device's twin (the datasheet camera and a field catalog
    object) give the same records, timings aside, before and after ``solve_image`` searched a
    frame's field of view with the same catalog object, which the search leaves as it found it.
    The search used to leave the sky database's patterns on the catalog: one frame then took 1
    seed where the twin takes 2."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from bench_realframes import frames
    from check_solve_records import untimed
    from conftest import require_shared

    from firmware_model.pipeline.frame_readers import read_frame
    from ground.api import solve_image
    from ground.catalog.field_catalogs import catalog_for_field

    require_shared(shared_data / "frames" / "tetra3-mono")
    jobs = [job for job in frames() if job["set"] == "tetra3"]
    frame = read_frame(jobs[0]["path"])
    camera = CameraModel.from_focal(frame.width, frame.height, *jobs[0]["datasheet"])
    catalog = catalog_for_field(frame.width, frame.height, jobs[0]["fov"])

    def twin() -> list:
        return [untimed(solve_image(str(job["path"]), camera=camera, catalog=catalog).record) for job in jobs]

    before = twin()
    state = _state(catalog)
    solve_image(str(jobs[1]["path"]), catalog=catalog, fov_deg=jobs[1]["fov"])
    assert _state(catalog) == state
    after = twin()
    assert [r["status"] for r in before] == ["OK"] * len(jobs)
    assert after == before


@pytest.mark.timeout(guards.HANG_S)
@pytest.mark.parametrize(
    "name,words", [("nope.st16cat", "no such file"), ("a_dir", "a directory"), ("a_fifo", "a FIFO")]
)
def test_a_catalog_path_that_is_not_a_file_is_one_line_naming_it(tmp_path, name, words):
    """Checked before it is read: a FIFO given as the catalog blocked the read for ever."""
    (tmp_path / "a_dir").mkdir()
    os.mkfifo(tmp_path / "a_fifo")
    with pytest.raises(OptionsError) as err:
        in_process_solver(camera=CameraModel.reference_design(), catalog=tmp_path / name)
    assert str(err.value).startswith(f"catalog {tmp_path / name}: ")
    assert words in str(err.value) and "\n" not in str(err.value)
