"""A pytest plugin for flight-software teams: ``st16-device`` started on a pty for each test, ready
(its ``listening on`` line seen, its catalog committed), and stopped with its children reaped at
teardown, also when the test fails or the run is interrupted (docs/testing.md).

Registered through the ``pytest11`` entry point ``st16`` (``pip install colour-st16`` is enough).
Fixtures:

* ``st16_device``: a running device (:class:`St16Device`: ``.port``, ``.client``, ``.state_dir``,
  ``.log``, ``.truth``), configured per test by ``@pytest.mark.st16(**options)`` (:data:`OPTIONS`);
* ``st16_device_factory``: ``factory(**options)`` starts more devices in one test;
* ``st16_feed``: a sender for the device's attitude feed (:class:`St16Feed`; requesting it gives
  ``st16_device`` an attitude feed unless the marker names another capture source);
* ``st16_session_device``: one device for the whole session, configured by the overridable
  ``st16_session_options`` fixture;
* ``st16_catalog``: the bundled default catalog, built once per session.

Nothing heavy is imported until a fixture is used: the plugin costs a run that uses none of its
fixtures nothing but its import. Every command the plugin sends goes through
``ground.link.client`` (whose codes come from ``protocol``).
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    import numpy as np

    from ground.link.client import Client
    from ground.sim.feed_wire import Sender
    from ground.sim.sky_source import Exposure

MARKER = "st16"
START_TIMEOUT_S = 300.0  #: default bound on start-up (ini ``st16_start_timeout``): a cold start compiles the kernels
STOP_TIMEOUT_S = 10.0  #: seconds after SIGTERM before the device's process group is killed
TAIL_LINES = 12  #: lines of the device's stderr quoted by a start-up error

#: The options of ``@pytest.mark.st16(...)``, ``st16_device_factory(...)`` and
#: ``st16_session_options``: name -> what it does.
OPTIONS: dict[str, str] = {
    "catalog": '"default" (the bundled Hipparcos catalog, built once per session; the default), '
    "a catalog image file (st16-ground catalog build), or None: no catalog",
    "sky": "capture source: a sky schedule CSV file, a number N (N well-populated random attitudes, "
    "written to a schedule), or a list of scalar-first quaternions q_icrs_to_sensor",
    "frames": "capture source: a folder or glob of frame files, replayed in order",
    "loop": "with frames: start again after the last file",
    "attitude_feed": "capture source: True (a free loopback TCP port) or a feed URL tcp://HOST:PORT",
    "timing": '"fast" (default) or "realistic" (--timing)',
    "exposure_ms": "with timing realistic (--exposure-ms)",
    "processing_ms": "with timing realistic (--processing-ms)",
    "deadline_ms": "with timing realistic (--deadline-ms)",
    "faults": "a fault script (docs/ICD.md section 13), a file or the script's text, armed with FAULT load "
    "once the device is ready (the plugin's own commands never hit it)",
    "fault_injection": "accept the FAULT command (--fault-injection; implied by faults)",
    "params": "default parameter set: a dict or a JSON file (--params)",
    "camera": "camera model JSON file (--camera)",
    "pace": "model UART timing (--pace)",
    "baud": "line rate for pace (--baud)",
    "log_level": "the device's stderr log level (default warning)",
    "init": "send INIT before the test (application mode; default False: the device in its bootloader)",
    "seed": "seed of the attitudes sky=N picks (default 2026)",
    "start_timeout": f"seconds the device may take to become ready (default {START_TIMEOUT_S:g})",
    "args": "further st16-device arguments, a list of strings",
}
TIMINGS = ("fast", "realistic")

_LIVE: set[subprocess.Popen[str]] = set()  #: devices started and not yet stopped (the atexit net)
_LIVE_LOCK = threading.Lock()


class SetupError(Exception):
    """A device the plugin could not start as asked: the test errors at setup with this text."""


# ---------------------------------------------------------------------------------------------- options


def check_options(options: dict[str, Any], where: str) -> dict[str, Any]:
    """``options`` when every name is known; SetupError naming the first unknown one."""
    for name in options:
        if name not in OPTIONS:
            raise SetupError(f"{where}: unknown option {name!r} (known: {', '.join(OPTIONS)})")
    sources = [k for k in ("sky", "frames", "attitude_feed") if options.get(k) not in (None, False)]
    if len(sources) > 1:
        raise SetupError(f"{where}: one capture source at a time, not {' and '.join(sources)}")
    if options.get("timing", "fast") not in TIMINGS:
        raise SetupError(f"{where}: timing {options['timing']!r} is not one of {', '.join(TIMINGS)}")
    # the files named, before anything is built or started
    if options.get("catalog", "default") not in ("default", None):
        _existing(options["catalog"], "catalog file")
    if isinstance(options.get("sky"), (str, os.PathLike)):
        _existing(options["sky"], "sky schedule")
    frames = options.get("frames")
    if frames is not None and not any(c in str(frames) for c in "*?["):
        _existing(frames, "frames folder")
    if options.get("faults") is not None:
        St16Device.fault_text(options["faults"])
    if options.get("params") is not None and not isinstance(options["params"], dict):
        _existing(options["params"], "parameter file")
    if options.get("camera") is not None:
        _existing(options["camera"], "camera file")
    return options


def marker_options(node: pytest.Item) -> dict[str, Any]:
    """The ``st16`` markers' options, the closest marker's winning (a test's over its class's)."""
    merged: dict[str, Any] = {}
    for mark in reversed(list(node.iter_markers(MARKER))):
        if mark.args:
            raise SetupError(f"@pytest.mark.{MARKER}: options are keywords, got {mark.args!r}")
        merged.update(mark.kwargs)
    return check_options(merged, f"@pytest.mark.{MARKER}")


def _existing(value: Any, what: str) -> Path:
    path = Path(value).expanduser()
    if not path.exists():
        raise SetupError(f"st16: {what} {path} does not exist")
    return path.resolve()


def _free_tcp_url() -> str:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"tcp://127.0.0.1:{port}"


# ---------------------------------------------------------------------------------------------- catalog


@dataclass
class St16Catalog:
    """A catalog image and, for the default, the catalog it was made from (``pick`` needs it)."""

    image: bytes
    path: Path
    crc32: int
    catalog: Any = None  #: firmware_model.catalog.onboard.OnboardCatalog, or None for a file


class _Catalogs:
    """The session's catalogs: the default built once, files read once."""

    def __init__(self, folder: Callable[[], Path]):
        self._folder = folder
        self._cache: dict[str, St16Catalog] = {}
        self._lock = threading.Lock()

    def get(self, spec: Any) -> St16Catalog:
        from protocol.crc import crc32

        key = "default" if spec == "default" else str(_existing(spec, "catalog file"))
        with self._lock:
            if key not in self._cache:
                if key == "default":
                    from firmware_model.catalog.image_io import catalog_to_image
                    from ground.catalog.build import build_catalog
                    from ground.catalog.design import CatalogDesign

                    catalog = build_catalog(CatalogDesign())
                    image = catalog_to_image(catalog)
                    path = self._folder() / "default.st16cat"
                    path.write_bytes(image)
                    self._cache[key] = St16Catalog(image, path, crc32(image), catalog)
                else:
                    image = Path(key).read_bytes()
                    self._cache[key] = St16Catalog(image, Path(key), crc32(image))
            return self._cache[key]


# ---------------------------------------------------------------------------------------------- the device


#: Run before the device's own program (exec'd in the same process): PR_SET_PDEATHSIG (1) asks
#: Linux to send it SIGTERM when the process that started it dies, however it dies.
_PARENT_DEATH_GUARD = (
    "import ctypes, os, signal, sys; ctypes.CDLL(None).prctl(1, signal.SIGTERM); os.execvp(sys.argv[1], sys.argv[1:])"
)


def _device_argv() -> list[str]:
    from ground.testing.device_proc import device_command

    cmd = device_command()
    if sys.platform.startswith("linux"):  # the device dies with the test process, even on SIGKILL
        return [sys.executable, "-c", _PARENT_DEATH_GUARD, *cmd]
    return cmd


def _stop_process(proc: subprocess.Popen[str], timeout: float = STOP_TIMEOUT_S) -> int:
    """SIGTERM, then after ``timeout`` s SIGKILL to its process group; whatever else of the group
    is left is killed too. Its exit code."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGTERM)
    try:
        rc = proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
        rc = proc.wait()
    with contextlib.suppress(ProcessLookupError, PermissionError):  # children it left behind
        os.killpg(proc.pid, signal.SIGKILL)
    with _LIVE_LOCK:
        _LIVE.discard(proc)
    return rc


@atexit.register
def _kill_leftovers() -> None:
    with _LIVE_LOCK:
        left = list(_LIVE)
    for proc in left:
        _stop_process(proc, timeout=2.0)


class St16Device:
    """A running ``st16-device --pty``: :attr:`port` the pty a driver opens, :attr:`client` a
    connected ``ground.link.client.Client``, :attr:`state_dir`, :attr:`log` (its stderr so far),
    :attr:`truth` (a sky schedule's rows, else None)."""

    def __init__(self, options: dict[str, Any], state_dir: Path, catalogs: _Catalogs, default_timeout: float):
        self.options = options
        self.state_dir = state_dir
        self.log_path = state_dir.parent / f"{state_dir.name}.log"
        self.truth: list[Exposure] | None = None
        self.schedule: Path | None = None
        self.feed_url: str | None = None
        self.catalog: St16Catalog | None = None
        self.port = ""
        self._client: Client | None = None
        self._lines: deque[str] = deque(maxlen=50)
        self._listening = threading.Event()
        self.proc: subprocess.Popen[str] | None = None
        self.args = self._arguments(catalogs)
        self.start_timeout = float(options.get("start_timeout", default_timeout))
        self._start()

    # -- configuration

    def _arguments(self, catalogs: _Catalogs) -> list[str]:
        o, args = self.options, ["--pty", "--state", str(self.state_dir)]
        self.state_dir.mkdir(parents=True, exist_ok=True)
        spec = o.get("catalog", "default")
        if spec is not None:
            self.catalog = catalogs.get(spec)
            from firmware_model.device.slots import SlotStore
            from protocol.commands import Slot

            store = SlotStore(self.state_dir)  # committed before the device starts: it loads it ready
            try:
                store.set_active(Slot.CATALOG, self.catalog.image)
            finally:
                store.close()
        side = self.state_dir.parent / f"{self.state_dir.name}-inputs"
        side.mkdir(exist_ok=True)
        if o.get("sky") is not None:
            args += ["--sky", str(self._schedule(o["sky"], side))]
        if o.get("frames") is not None:
            frames = o["frames"]
            args += [
                "--frames",
                str(frames) if any(c in str(frames) for c in "*?[") else str(_existing(frames, "frames folder")),
            ]
        if o.get("loop"):
            args.append("--loop")
        if o.get("attitude_feed") not in (None, False):
            self.feed_url = _free_tcp_url() if o["attitude_feed"] is True else str(o["attitude_feed"])
            args += ["--attitude-feed", self.feed_url]
        if o.get("timing") is not None:
            args += ["--timing", o["timing"]]
        for key in ("exposure_ms", "processing_ms", "deadline_ms", "baud"):
            if o.get(key) is not None:
                args += [f"--{key.replace('_', '-')}", str(o[key])]
        self.fault_script: str | None = None
        if o.get("faults") is not None:  # armed over the link once ready: the plugin's own commands never hit it
            self.fault_script = self.fault_text(o["faults"])
        if o.get("fault_injection") or self.fault_script is not None:
            args.append("--fault-injection")
        if o.get("params") is not None:
            if isinstance(o["params"], dict):
                path = side / "params.json"
                path.write_text(json.dumps(o["params"]))
            else:
                path = _existing(o["params"], "parameter file")
            args += ["--params", str(path)]
        if o.get("camera") is not None:
            args += ["--camera", str(_existing(o["camera"], "camera file"))]
        if o.get("pace"):
            args.append("--pace")
        args += ["--log-level", str(o.get("log_level", "warning"))]
        return args + [str(a) for a in o.get("args", ())]

    def _schedule(self, sky: Any, side: Path) -> Path:
        from ground.sim.sky_source import read_schedule

        if isinstance(sky, bool):
            raise SetupError(f"st16: sky={sky!r}: a schedule file, a number of attitudes or a list of quaternions")
        if isinstance(sky, int):
            quats = self._pick(sky)
        elif isinstance(sky, (str, os.PathLike)):
            quats = None
            path = _existing(sky, "sky schedule")
        else:
            quats = [list(map(float, q)) for q in sky]
        if quats is not None:
            path = side / "schedule.csv"
            path.write_text(
                "qw,qx,qy,qz,seed\n"
                + "".join(f"{q[0]!r},{q[1]!r},{q[2]!r},{q[3]!r},{k}\n" for k, q in enumerate(quats))
            )
        try:
            self.truth = read_schedule(path)
        except ValueError as exc:
            raise SetupError(f"st16: sky schedule: {exc}") from None
        self.schedule = path
        return path

    def _pick(self, n: int) -> list[list[float]]:
        import numpy as np

        from firmware_model.camera import CameraModel
        from firmware_model.reference_frames import matrix_to_quat
        from ground.sim.device_process import pick_attitudes

        if n < 1:
            raise SetupError(f"st16: sky={n}: at least one attitude")
        if self.catalog is None or self.catalog.catalog is None:
            raise SetupError("st16: sky=N picks attitudes from the default catalog: give catalog='default'")
        camera = CameraModel.reference_design()
        if self.options.get("camera") is not None:
            camera = CameraModel.from_dict(json.loads(Path(self.options["camera"]).read_text()))
        rng = np.random.default_rng(int(self.options.get("seed", 2026)))
        return [[float(v) for v in matrix_to_quat(a)] for a in pick_attitudes(self.catalog.catalog, camera, n, rng)]

    @staticmethod
    def fault_text(faults: Any) -> str:
        """The fault script's text: ``faults`` names a file, or is the text (a string holding
        whitespace that names no file)."""
        text = str(faults)
        if isinstance(faults, str) and any(c.isspace() for c in text.strip()) and not Path(text).exists():
            return text
        return _existing(faults, "fault script").read_text()

    # -- process

    def _start(self) -> None:
        log = self.log_path.open("w")
        try:
            self.proc = subprocess.Popen(
                [*_device_argv(), *self.args],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=log,
                text=True,
                start_new_session=True,  # its own process group: stopped with whatever it starts
            )
        finally:
            log.close()
        with _LIVE_LOCK:
            _LIVE.add(self.proc)
        threading.Thread(target=self._read_stdout, name="st16-device stdout", daemon=True).start()
        try:
            self._wait_ready()
        except BaseException:
            self.stop()
            raise

    def _read_stdout(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for line in self.proc.stdout:
            line = line.rstrip("\n")
            self._lines.append(line)
            if not self._listening.is_set() and line.startswith("listening on "):
                self.port = line[len("listening on ") :].strip()
                self._listening.set()

    def _wait_ready(self) -> None:
        assert self.proc is not None
        deadline = time.monotonic() + self.start_timeout
        while not self._listening.wait(0.05):
            if self.proc.poll() is not None:
                raise SetupError(self._why(f"st16-device exited {self.proc.returncode} before it was listening"))
            if time.monotonic() > deadline:
                raise SetupError(self._why(f"st16-device was not listening within {self.start_timeout:g} s"))
        from ground.link.client import Client, LinkError, Nack
        from protocol.commands import Slot

        try:
            self._client = Client(self.port, timeout=2.0)
            self._client.ping()
            if self.catalog is not None:
                info = self._client.slot_info(Slot.CATALOG)
                if not info.active or info.crc32 != self.catalog.crc32:
                    raise SetupError(
                        self._why(f"st16-device did not commit the catalog {self.catalog.path} (SLOT_INFO {info})")
                    )
            if self.options.get("init"):
                self._client.init()
            if self.fault_script is not None:
                from protocol.commands import FaultAction

                try:
                    self._client.fault(FaultAction.LOAD, self.fault_script)
                except Nack as exc:
                    raise SetupError(f"st16: fault script refused: {exc}") from None
        except LinkError as exc:
            raise SetupError(self._why(f"st16-device on {self.port} did not answer: {exc}")) from None

    def _why(self, what: str) -> str:
        tail = self.log.splitlines()[-TAIL_LINES:]
        return f"{what}; command: {' '.join(self.args)}; its last stderr lines:\n" + (
            "\n".join(f"    {ln}" for ln in tail) if tail else "    (none)"
        )

    # -- what a test uses

    @property
    def client(self) -> Client:
        """A ``ground.link.client.Client`` connected to :attr:`port` (idle unless used: a driver
        under test may open the same pty; do not use both at the same moment)."""
        if self._client is None:
            raise RuntimeError("the device has stopped")
        return self._client

    @property
    def log(self) -> str:
        """The device's stderr so far."""
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def expected(self, capture: int) -> np.ndarray:
        """The true scalar-first q_icrs_to_sensor of the ``capture``-th exposure (0 the first; a
        schedule wraps around)."""
        if not self.truth:
            raise RuntimeError("no truth: the device has no sky schedule (sky=...)")
        return self.truth[capture % len(self.truth)].q_icrs_to_sensor

    def fault_counters(self) -> dict[str, int]:
        """The device's fault counters (docs/ICD.md section 13), read with FAULT status through
        :attr:`client` (a device with ``faults`` or ``fault_injection``)."""
        from protocol.commands import FaultAction
        from protocol.edac import FAULT_COUNTERS

        return dict(zip(FAULT_COUNTERS, self.client.fault(FaultAction.STATUS).counters, strict=True))

    def stop(self) -> int | None:
        """Close the client, stop the device (SIGTERM, its process group killed after
        STOP_TIMEOUT_S) and reap it; its exit code (None if it never started)."""
        if self._client is not None:
            with contextlib.suppress(Exception):
                self._client.close()
            self._client = None
        if self.proc is None:
            return None
        rc = _stop_process(self.proc)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return rc

    def __repr__(self) -> str:
        return f"St16Device(port={self.port!r}, state_dir={str(self.state_dir)!r}, alive={self.alive})"


def attitude_error_arcsec(q_a: Sequence[float], q_b: Sequence[float]) -> float:
    """The angle between two scalar-first unit quaternions, in arcseconds."""
    import math

    dot = abs(sum(float(a) * float(b) for a, b in zip(q_a, q_b, strict=True)))
    return math.degrees(2.0 * math.acos(min(1.0, dot))) * 3600.0


# ---------------------------------------------------------------------------------------------- the feed


class St16Feed:
    """The simulator's side of a device's attitude feed (``ground.sim.feed_wire``): :meth:`send`
    one sample, or :meth:`hold` an attitude, streamed from a thread until :meth:`stop`."""

    def __init__(self, url: str):
        from ground.sim.feed_wire import Sender

        self.url = url
        self.sender: Sender = Sender(url)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def send(self, q: Sequence[float], w: Sequence[float] = (0.0, 0.0, 0.0), t: float | None = None, r=None) -> None:
        """One sample: attitude ``q`` (scalar-first q_icrs_to_sensor), rate ``w`` (rad/s, sensor
        axes), at POSIX time ``t`` (now), GCRS position ``r`` (km) or None."""
        import numpy as np

        from ground.sim.feed_wire import Sample

        sample = Sample(
            time.time() if t is None else t,
            np.asarray(q, float),
            np.asarray(w, float),
            None if r is None else np.asarray(r, float),
        )
        with self._lock:
            self.sender.send(sample)

    def hold(self, q: Sequence[float], w: Sequence[float] = (0.0, 0.0, 0.0), hz: float = 50.0) -> None:
        """Stream attitude ``q`` at rate ``w`` now, every 1/``hz`` s, until :meth:`stop` or the
        next :meth:`hold`."""
        self.stop()
        self._stop = stop = threading.Event()

        def run() -> None:
            while not stop.is_set():
                try:
                    self.send(q, w)
                except OSError:
                    return
                stop.wait(1.0 / hz)

        self.send(q, w)
        self._thread = threading.Thread(target=run, name="st16 feed", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None

    def close(self) -> None:
        self.stop()
        self.sender.close()


# ---------------------------------------------------------------------------------------------- pytest hooks and fixtures


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addini(
        "st16_start_timeout",
        f"seconds st16-device may take to become ready (default {START_TIMEOUT_S:g})",
        default=str(START_TIMEOUT_S),
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        f"{MARKER}(**options): configure the st16_device fixture (catalog, sky, frames, attitude_feed, "
        "timing, faults, params, ...; docs/testing.md)",
    )


def _setup_error(exc: SetupError) -> BaseException:
    """The test's setup error: ``exc``'s text alone, no traceback and no chained exception."""
    return pytest.fail.Exception(str(exc), pytrace=False)


class _Starter:
    """Starts devices into one folder and stops them all at :meth:`close` (newest first)."""

    def __init__(self, folder: Path, catalogs: _Catalogs, timeout: float):
        self.folder, self.catalogs, self.timeout = folder, catalogs, timeout
        self.devices: list[St16Device] = []

    def __call__(self, where: str = "st16_device_factory", **options: Any) -> St16Device:
        try:
            check_options(options, where)
            state = self.folder / f"device{len(self.devices)}"
            device = St16Device(options, state, self.catalogs, self.timeout)
        except SetupError as exc:
            raise _setup_error(exc) from None
        self.devices.append(device)
        return device

    def close(self) -> None:
        while self.devices:
            self.devices.pop().stop()


def _timeout(config: pytest.Config) -> float:
    try:
        return float(config.getini("st16_start_timeout"))
    except (ValueError, TypeError):
        return START_TIMEOUT_S


@pytest.fixture(scope="session")
def _st16_catalogs(tmp_path_factory: pytest.TempPathFactory) -> _Catalogs:
    return _Catalogs(lambda: tmp_path_factory.mktemp("st16-catalog"))


@pytest.fixture(scope="session")
def st16_catalog(_st16_catalogs: _Catalogs) -> St16Catalog:
    """The bundled default catalog (Hipparcos, the default design), built once per session."""
    return _st16_catalogs.get("default")


@pytest.fixture
def st16_device_factory(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, _st16_catalogs: _Catalogs
) -> Iterator[Callable[..., St16Device]]:
    """``factory(**options)`` -> a ready :class:`St16Device`; every one started is stopped at teardown."""
    starter = _Starter(tmp_path_factory.mktemp("st16"), _st16_catalogs, _timeout(request.config))
    try:
        yield starter
    finally:
        starter.close()


@pytest.fixture
def st16_device(request: pytest.FixtureRequest, st16_device_factory: _Starter) -> St16Device:
    """A ready device on a pty, configured by ``@pytest.mark.st16(**options)``; with ``st16_feed``
    requested and no other capture source, it has an attitude feed."""
    try:
        options = dict(marker_options(request.node))
    except SetupError as exc:
        raise _setup_error(exc) from None
    if "st16_feed" in request.fixturenames and not any(options.get(k) for k in ("sky", "frames", "attitude_feed")):
        options["attitude_feed"] = True
    return st16_device_factory(f"@pytest.mark.{MARKER}", **options)


@pytest.fixture
def st16_feed(st16_device: St16Device) -> Iterator[St16Feed]:
    """A sender connected to ``st16_device``'s attitude feed (:class:`St16Feed`)."""
    if st16_device.feed_url is None:
        pytest.fail("st16_feed: the device has another capture source than an attitude feed", pytrace=False)
    feed = St16Feed(st16_device.feed_url)
    try:
        yield feed
    finally:
        feed.close()


@pytest.fixture(scope="session")
def st16_session_options() -> dict[str, Any]:
    """The session device's options (override this fixture in a conftest.py); none by default."""
    return {}


@pytest.fixture(scope="session")
def st16_session_device(
    request: pytest.FixtureRequest,
    tmp_path_factory: pytest.TempPathFactory,
    _st16_catalogs: _Catalogs,
    st16_session_options: dict[str, Any],
) -> Iterator[St16Device]:
    """One device for the whole session (its state, sequence numbers and captures carry over from
    test to test), configured by ``st16_session_options``."""
    starter = _Starter(tmp_path_factory.mktemp("st16-session"), _st16_catalogs, _timeout(request.config))
    try:
        yield starter("st16_session_options", **st16_session_options)
    finally:
        starter.close()
