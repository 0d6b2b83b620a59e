"""``ground.solver``: the options become a route in one place, and a solve leaves the caller's
catalog as it found it (the device's twin stays the device after a field-of-view search)."""

from types import SimpleNamespace

import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.pipeline import scale_free
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.sky_search import FieldRange
from firmware_model.pipeline.solve_types import PipelineParams
from ground.solver import InProcessSolver, OptionsError, Route, choose_route


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


def test_a_field_of_view_search_leaves_the_callers_catalog_its_own_patterns(synthetic_catalog):
    """The search matches the given catalog against the sky database's patterns through a view:
    the catalog object keeps matching its own patterns when it is solved as the twin afterwards."""
    cat = synthetic_catalog(300)
    camera = CameraModel.from_horizontal_fov(128, 96, 20.0)
    own = scale_free.catalog_patterns(cat, camera)
    sky = SimpleNamespace(index="the sky database's patterns", search=None, load_s=0.0)
    dark = Frame(np.full((96, 128), 100.0, np.float32), "MONO", white_level=65535.0)  # no star: no search run
    search = InProcessSolver(Route.SKY_SEARCH, PipelineParams(), catalog=cat, database=sky, fov=FieldRange.blind())
    assert search.solve(dark).record["status"] == "TOO_FEW_STARS"
    assert search.patterns == "the sky database's patterns"
    assert scale_free.catalog_patterns(search._catalog_for(camera), camera) == "the sky database's patterns"
    assert scale_free.catalog_patterns(cat, camera) is own  # the twin's index, as before the search
    assert InProcessSolver(Route.TWIN, PipelineParams(), camera=camera, catalog=cat).patterns is None


def test_the_twin_gives_the_same_records_before_and_after_a_search_on_its_catalog(shared_data):
    """The tetra3 frames solved as the device's twin (the datasheet camera and a field catalog
    object) give the same records, timings aside, before and after ``solve_image`` searched a
    frame's field of view with the same catalog object. The search used to leave the sky
    database's patterns on the catalog: one frame then took 1 seed where the twin takes 2."""
    import sys
    from pathlib import Path

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
    solve_image(str(jobs[1]["path"]), catalog=catalog, fov_deg=jobs[1]["fov"])
    after = twin()
    assert [r["status"] for r in before] == ["OK"] * len(jobs)
    assert after == before
