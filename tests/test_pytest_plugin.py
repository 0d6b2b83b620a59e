"""The ``st16`` pytest plugin (``ground.testing.pytest_plugin``, docs/testing.md), run as a user's
test session would run it (pytester): bad input is one setup error naming it with no device left,
a device that does not start is quoted, and a device is stopped and reaped after a passing, a
failing and an interrupted test, and when the test process is killed. The long tests (marked slow)
run the docs' example test file as it is, and the attitude feed, the factory and the session device."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "docs" / "examples" / "test_flight_driver.py"


def devices_under(folder: Path) -> list[str]:
    """Command lines of the running processes (zombies included) that name ``folder``."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if str(folder) in cmd and ("st16-device" in cmd or "firmware_model.device.cli" in cmd):
            found.append(f"{proc.name}: {cmd}")
    return found


def gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_the_plugin_is_registered_and_its_fixtures_do_not_clash_with_the_projects(request):
    import ast

    from ground.testing import pytest_plugin

    assert request.config.pluginmanager.has_plugin("st16")  # auto-loaded from the pytest11 entry point
    plugin = {name for name in vars(pytest_plugin) if name.startswith(("st16_", "_st16_"))}
    assert {"st16_device", "st16_device_factory", "st16_feed", "st16_session_device"} <= plugin
    project = set()  # every fixture the project's tests define (conftest.py and the test modules)
    for path in (ROOT / "tests").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef) and any("fixture" in ast.unparse(d) for d in node.decorator_list):
                project.add(node.name)
    assert project and not plugin & project, plugin & project


#: A marker's options -> what its one-line setup error names.
BAD_INPUT = {
    "skyy=3": "@pytest.mark.st16: unknown option 'skyy' (known: catalog, sky, ",
    "catalog='/nowhere/cat.st16cat'": "st16: catalog file /nowhere/cat.st16cat does not exist",
    "sky='/nowhere/schedule.csv'": "st16: sky schedule /nowhere/schedule.csv does not exist",
    "faults='/nowhere/faults.txt'": "st16: fault script /nowhere/faults.txt does not exist",
    "timing='slow'": "@pytest.mark.st16: timing 'slow' is not one of fast, realistic",
}


def test_bad_input_is_one_setup_error_naming_it_and_starts_no_device(pytester):
    pytester.makepyfile(
        "import pytest\n"
        + "".join(
            f"\n\n@pytest.mark.st16({marker})\ndef test_{k}(st16_device):\n    pass\n"
            for k, marker in enumerate(BAD_INPUT)
        )
    )
    result = pytester.runpytest_subprocess("-q", "-p", "no:cacheprovider")
    result.assert_outcomes(errors=len(BAD_INPUT))
    for k, named in enumerate(BAD_INPUT.values()):
        at = next(n for n, ln in enumerate(result.outlines) if f"ERROR at setup of test_{k} " in ln)
        assert result.outlines[at + 1].startswith(named), result.outlines[at : at + 3]  # the message alone,
        assert result.outlines[at + 2].startswith("_" if k + 1 < len(BAD_INPUT) else "="), result.outlines[at : at + 3]
    assert not devices_under(pytester.path)  # the inner run's devices (its basetemp is under it)


def test_a_device_that_does_not_start_is_quoted_and_one_that_is_slow_is_stopped(pytester):
    (pytester.path / "bad.json").write_text("not json")
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.st16(catalog=None, params="bad.json")
        def test_exits(st16_device):
            pass

        @pytest.mark.st16(catalog=None, start_timeout=0.3)
        def test_slow(st16_device):
            pass
        """
    )
    result = pytester.runpytest_subprocess("-q", "-p", "no:cacheprovider")
    result.assert_outcomes(errors=2)
    result.stdout.fnmatch_lines(
        [
            "*st16-device exited 2 before it was listening; command: --pty --state * --params *bad.json*",
            "*st16-device: --params *bad.json: parameter set is not UTF-8 JSON*",
            "*st16-device was not listening within 0.3 s; command:*",
        ]
    )
    assert not devices_under(pytester.path)  # the inner run's devices (its basetemp is under it)


def test_a_device_is_ready_and_reaped_after_a_failing_and_an_interrupted_test(pytester):
    pids = pytester.path / "pids.txt"
    pytester.makepyfile(
        f"""
        import pytest

        def test_fails(st16_device):
            with open({str(pids)!r}, "a") as f:
                f.write(f"{{st16_device.proc.pid}}\\n")
            assert st16_device.client.ping().startswith("ST16-EMU BOOTLOADER")
            info = st16_device.client.slot_info(0)  # the catalog, committed
            assert info.active and info.crc32 == st16_device.catalog.crc32
            assert st16_device.state_dir.is_dir() and st16_device.port.startswith("/dev/")
            assert "Traceback" not in st16_device.log
            assert False, "a failing test"

        def test_interrupted(st16_device):
            with open({str(pids)!r}, "a") as f:
                f.write(f"{{st16_device.proc.pid}}\\n")
            raise KeyboardInterrupt
        """
    )
    result = pytester.runpytest_subprocess("-q", "-p", "no:cacheprovider")
    assert result.ret == pytest.ExitCode.INTERRUPTED
    result.stdout.fnmatch_lines(["*AssertionError: a failing test*"])
    started = [int(p) for p in pids.read_text().split()]
    assert len(started) == 2 and all(gone(p) for p in started)
    assert not devices_under(pytester.path)  # the inner run's devices (its basetemp is under it)


@pytest.mark.slow
def test_a_killed_test_process_takes_its_device_with_it(pytester):
    pid_file = pytester.path / "pid.txt"
    pytester.makepyfile(
        f"""
        import time

        def test_waits(st16_device):
            open({str(pid_file)!r}, "w").write(str(st16_device.proc.pid))
            time.sleep(600)
        """
    )
    run = subprocess.Popen(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--basetemp", str(pytester.path / "bt")],
        cwd=pytester.path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 180
        while not pid_file.exists() or not pid_file.read_text():
            assert run.poll() is None and time.monotonic() < deadline, "the device did not start"
            time.sleep(0.2)
        device = int(pid_file.read_text())
        run.send_signal(signal.SIGKILL)
        run.wait()
        deadline = time.monotonic() + 20
        while not gone(device) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert gone(device) or "Z" in Path(f"/proc/{device}/stat").read_text().split()[2]
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()


@pytest.mark.slow
def test_the_docs_example_passes_as_a_user_runs_it(pytester):
    shutil.copy(EXAMPLE, pytester.path / EXAMPLE.name)
    result = pytester.runpytest_subprocess("-q", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=3)
    assert not devices_under(pytester.path)  # the inner run's devices (its basetemp is under it)


@pytest.mark.slow
def test_the_feed_the_factory_and_the_session_device(pytester):
    pytester.makeconftest(
        """
        import pytest

        @pytest.fixture(scope="session")
        def st16_session_options():
            return {"catalog": None, "init": True}
        """
    )
    pytester.makepyfile(
        """
        import numpy as np
        import pytest

        from ground.testing.pytest_plugin import attitude_error_arcsec


        @pytest.mark.st16(init=True, seed=5)
        def test_the_fed_attitude_is_solved(st16_device, st16_feed, st16_catalog):
            from firmware_model.camera import CameraModel
            from firmware_model.reference_frames import matrix_to_quat
            from ground.sim.device_process import pick_attitudes

            assert st16_device.feed_url.startswith("tcp://127.0.0.1:")
            a = pick_attitudes(st16_catalog.catalog, CameraModel.reference_design(), 1, np.random.default_rng(3))[0]
            st16_feed.hold(matrix_to_quat(a))
            rec = st16_device.client.go_and_wait()
            assert (int(rec["return_code"]) >> 8) & 0xFF == 0, st16_device.log
            assert attitude_error_arcsec(rec["quaternion"], matrix_to_quat(a)) < 60


        def test_two_devices_from_the_factory(st16_device_factory):
            one, two = st16_device_factory(catalog=None), st16_device_factory(catalog=None, init=True)
            assert one.port != two.port
            assert one.client.ping().startswith("ST16-EMU BOOTLOADER")
            assert two.client.ping().startswith("ST16-EMU APPLICATION")


        @pytest.mark.parametrize("k", range(2))
        def test_the_session_device_is_shared(st16_session_device, k):
            assert st16_session_device.client.ping().startswith("ST16-EMU APPLICATION")  # one INIT, at start
            open("session_pids.txt", "a").write(f"{st16_session_device.proc.pid}\\n")
        """
    )
    result = pytester.runpytest_subprocess("-q", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=4)
    pids = set((pytester.path / "session_pids.txt").read_text().split())
    assert len(pids) == 1 and all(gone(int(p)) for p in pids)
    assert not devices_under(pytester.path)  # the inner run's devices (its basetemp is under it)
