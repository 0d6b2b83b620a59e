"""Shared fixtures: the read-only data in ../shared (skipped cleanly when absent, a failure under
CI=true, where CI lays ../shared beside the clone); the [test] extra's packages (a failure when one
cannot be imported: a broken install, never a skip); the long tests' markers (:data:`LONG_TESTS`);
the run's own caches (:data:`PRIVATE_HOME`).

The suite runs on caches of its own, as a new user's first run does: before any test module is
imported, ``HOME`` and the ``XDG_*_HOME`` folders point into a fresh temporary folder (removed at
the end of the run), so the sky database, the field catalogs, the device's pattern indexes and
the console history are built there, never read from or written to the user's ``~/.cache``;
device and command-line subprocesses inherit it. The compiled kernels stay shared (numba's cache
beside the package, or ``NUMBA_CACHE_DIR``: settled by importing ``firmware_model`` before the
switch, which exports ``NUMBA_CACHE_DIR`` when it is the user cache's), so a run does not
compile them again; ``tests/test_ready.py`` compiles its own where it needs a cold start."""

import atexit
import importlib
import os
import shutil
import tempfile
import threading
import warnings
from pathlib import Path

import pytest
from hypothesis import settings

import firmware_model  # noqa: F401 - settles where the kernels are cached, with the user's own HOME


def _private_home() -> Path:
    """A fresh HOME with its own cache, config, data and state folders, exported for this process
    and every process it starts; removed when the run ends."""
    known = os.environ.get("ST16_TESTS_HOME")
    if known and Path(known).is_dir():
        return Path(known)  # this module imported again in the same run: the same HOME
    home = Path(tempfile.mkdtemp(prefix="st16-tests-home-"))
    atexit.register(shutil.rmtree, home, True)
    os.environ["HOME"] = os.environ["ST16_TESTS_HOME"] = str(home)
    for name, sub in (
        ("XDG_CACHE_HOME", ".cache"),
        ("XDG_CONFIG_HOME", ".config"),
        ("XDG_DATA_HOME", ".local/share"),
        ("XDG_STATE_HOME", ".local/state"),
    ):
        (home / sub).mkdir(parents=True)  # made: astropy ignores (with a warning) an XDG folder that is absent
        os.environ[name] = str(home / sub)
    return home


#: The run's own HOME (its caches under ``.cache``): :func:`_private_home`.
PRIVATE_HOME = _private_home()

# Property tests check behaviour, not speed: no per-example deadline (the machine is shared).
settings.register_profile("project", deadline=None)
settings.load_profile("project")

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


def require_shared(path: Path) -> Path:
    """``path`` (under ../shared) when it exists; else a clean skip, or a failure under CI=true."""
    if path.exists():
        return path
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"{path} is absent, and CI=true: CI lays ../shared beside the clone", pytrace=False)
    pytest.skip(f"{path} is absent")


def required(module: str):
    """Import ``module``, a package the [test] extra installs: one that cannot be imported fails
    the test (a broken install must show, not skip)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        pytest.fail(
            f"{module} is declared in [test] but cannot be imported ({exc}): pip install -e '.[test]'", pytrace=False
        )


#: Tests the default run leaves out (pyproject's ``addopts`` deselects these markers; CI runs them
#: in a second invocation, ``-m "slow or hil or realdata"``): test name -> marker. Kept here, in
#: one table, so a long test is marked without touching its module. Seconds: one run on the quiet
#: 2-core machine.
LONG_TESTS = {
    # real frames in ../shared/data through the command line or the device
    "tests/test_real_colour_frames.py::test_colour_frames_solve_through_the_cli_with_fov_only": "realdata",  # 52 s
    "tests/test_real_frames.py::test_real_frames_solve_through_the_cli": "realdata",  # 19 + 4 s
    "tests/test_real_frames.py::test_device_and_offline_replay_give_the_same_answers": "realdata",
    "tests/test_real_frames.py::test_camera_calibrates_from_the_datasheet_alone": "realdata",  # 4 s
    "tests/test_wcs_api.py::test_solve_file_cli": "realdata",  # 13 s
    "tests/test_sky_search.py::test_real_frames_solve_blind_and_with_the_field_of_view_25_per_cent_off": "realdata",  # 15 s
    "tests/test_wcs_api.py::test_solve_image_on_the_real_frames_and_their_wcs": "realdata",  # 4 s
    # the closed loop through a paced device in real time
    "tests/test_hil.py::test_short_closed_loop_through_the_paced_device": "hil",  # 11 + 3 s
    "tests/test_hil_scenarios.py::test_short_moon_slew_through_the_paced_device": "hil",  # 58 s
    "tests/test_two_heads_loop.py::test_the_two_head_loop_through_the_device": "hil",
    # long end-to-end runs of device processes
    "tests/test_attitude_feed.py::test_device_cli_solves_along_a_fed_path": "slow",  # 31 s
    "tests/test_link_pty.py::test_ctrl_c_during_an_upload_keeps_what_was_sent_and_the_next_upload_resumes": "slow",
    "tests/test_e2e_field.py::test_colour_calibration_from_a_run_and_on_the_device": "slow",  # 9 + 2 s
    "tests/test_e2e_link.py::test_replay_survives_device_restart": "slow",  # 7 s
    # kill -9 of export processes at every file event and at random moments (26 s together)
    "tests/test_export_atomic.py::test_a_kill_at_any_file_event_leaves_no_target_or_a_whole_one": "slow",
    "tests/test_export_atomic.py::test_kill_9_at_random_moments_leaves_no_target_or_a_whole_one": "slow",
    # asserts COSMOS's 1 s polling window: a timing, meaningful on a quiet machine only
    "tests/test_cosmos_polling.py::test_cosmos_polling_never_times_out_against_the_sky_source": "slow",  # 6 s
}


@pytest.fixture
def served_device():
    """Path of a pty served by an in-process default Device (stopped after the test)."""
    from firmware_model.device.device import Device
    from firmware_model.device.link import PtyLink, serve

    link, stop = PtyLink(), threading.Event()
    thread = threading.Thread(target=serve, args=(Device(), link, stop), daemon=True)
    thread.start()
    yield link.path
    stop.set()
    thread.join(2)
    link.close()


@pytest.fixture(scope="session")
def synthetic_catalog():
    """``build(n, **kw)``: an ``OnboardCatalog`` of ``n`` random stars (rng seed 7) in a 0.6 x 0.6 rad
    patch, ids from 100, with colours (B-V lookup); ``kw`` adds build settings (``dphi_star``)."""
    import numpy as np

    from firmware_model.catalog.onboard import OnboardCatalog
    from firmware_model.reference_frames import radec_to_vec

    def build(n: int, **kw):
        rng = np.random.default_rng(7)
        return OnboardCatalog.build(
            np.arange(100, 100 + n),
            radec_to_vec(rng.uniform(0, 0.6, n), rng.uniform(-0.3, 0.3, n)),
            rng.uniform(1, 5, n),
            rng.uniform(0.7, 1.3, n),
            rng.uniform(0.6, 1.1, n),
            phi_min=1e-3,
            phi_max=0.3,
            n_h=32,
            meta={"epoch": 2025.0, "source": "hipparcos", "colour_source": np.full(n, 2)},
            **kw,
        )

    return build


@pytest.fixture(scope="session")
def shared_data() -> Path:
    return require_shared(SHARED / "data")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Marks the tests of :data:`LONG_TESTS` (before ``-m`` selects); warns of a name in the table
    that names no test of a module this run collected (a renamed test would run by default)."""
    seen, files = set(), set()
    for item in items:
        name = item.nodeid.split("[", 1)[0]
        files.add(name.split("::", 1)[0])
        marker = LONG_TESTS.get(name)
        if marker is not None:
            item.add_marker(getattr(pytest.mark, marker))
            seen.add(name)
    for name in LONG_TESTS.keys() - seen:
        if name.split("::", 1)[0] in files:
            warnings.warn(pytest.PytestWarning(f"conftest LONG_TESTS names no collected test: {name}"), stacklevel=1)
