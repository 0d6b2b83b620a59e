"""``st16-device``: serve the emulated tracker on a pty, a serial port or TCP.

The first stdout line is ``listening on <path>`` (flushed), printed once the device is ready: its
compiled kernels loaded and the stored catalog's pattern index built, so the first GO takes as
long as any other. The device then serves until SIGINT or SIGTERM and exits 0. Options are parsed
in :func:`build_parser`, the device is assembled in :func:`build_device` and the transport in
:func:`build_link`, so frame sources and solvers can be added as further options without touching
the serving code.
"""

from __future__ import annotations

import os

# One BLAS thread: the pipeline's small fits lose to thread contention on a busy machine
# (docs/pipeline.md); set before numpy is imported, unless the user chose otherwise.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import faulthandler
import functools
import gc
import logging
import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import protocol
from firmware_model import user_cache_dir, user_files
from firmware_model.device.clock import ClockModel
from firmware_model.device.faults import Fault, parse_script
from firmware_model.device.link import DEFAULT_IDLE_TIMEOUT, Link, open_link, serve
from firmware_model.device.sequence import Timing
from protocol import nsp
from protocol.commands import MAX_FAULT_SCRIPT, Slot, SlotRejected
from protocol.result import QuaternionOrder

if TYPE_CHECKING:  # the device's heavy modules load when it is built (a spawned helper process imports this module)
    from firmware_model.camera import CameraModel
    from firmware_model.device.device import Device, SolveContext
    from firmware_model.device.sensor_input import DeviceParams

DEFAULT_PACED_TURNAROUND_MS = 1.0  #: ours; the research documents no turnaround
DEFAULT_TIMING = Timing()  #: --timing realistic's defaults: about 2 Hz, the real unit's cadence
DEFAULT_DEADLINE_MS = 1500.0  #: ours: flight timing's search deadline, inside the 2 s GO-to-result budget
#: The interpreter's thread switch interval in the device (Python's default is 5 ms): the link
#: thread waits up to this long for the GIL each time it wakes (select, read, write) while a GO
#: sequence computes in its worker thread; it costs the worker nothing while the link is quiet
#: (docs/ICD.md: PING p99 <= 50 ms during any GO, bench/bench_link_during_go.py).
SWITCH_INTERVAL_S = 0.001

#: The longest a stop may take (s), from SIGINT or SIGTERM to the end of the process: beyond it,
#: something that will not finish (a thread, a child process) holds the exit, a defect; every
#: thread's stack is written to stderr and the process ends with status 1 (docs/bad_input.md).
STOP_WATCHDOG_S = 20.0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="st16-device", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {protocol.__version__}")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="create a pseudo-terminal and print its path")
    where.add_argument("--port", help="serve on this serial device (pyserial URL or path)")
    where.add_argument(
        "--tcp",
        metavar="HOST:PORT",
        help="serve on TCP (host defaults to 127.0.0.1); one client at "
        "a time, a new connection takes over (docs/bad_input.md)",
    )
    parser.add_argument(
        "--address",
        type=lambda s: int(s, 0),
        default=nsp.DEVICE_ADDRESS,
        help="NSP address of the device (default 0x0E)",
    )
    parser.add_argument("--state", help="directory for persistent state (slots); in memory if absent")
    parser.add_argument(
        "--heads",
        metavar="FILE",
        help="serve 1-4 heads on the one link, each at its address and mounting (JSON; docs/ICD.md section 14)",
    )
    parser.add_argument("--baud", type=int, default=115200, help="line rate for --port and for --pace")
    parser.add_argument(
        "--tcp-idle",
        type=float,
        default=DEFAULT_IDLE_TIMEOUT,
        metavar="SECONDS",
        help=f"with --tcp, close a client silent this long (default {DEFAULT_IDLE_TIMEOUT:g})",
    )
    parser.add_argument("--pace", action="store_true", help="model UART timing at --baud (10 bits per byte)")
    parser.add_argument(
        "--turnaround-ms",
        type=float,
        default=None,
        help=f"delay from a command's last byte to its reply (default 0, {DEFAULT_PACED_TURNAROUND_MS} with --pace)",
    )
    parser.add_argument(
        "--camera",
        help="camera model JSON (CameraModel.to_dict); default: the Enright & McVittie "
        "reference design, 2592 x 1944 at f = 7383 px",
    )
    capture = parser.add_mutually_exclusive_group()
    capture.add_argument("--frames", metavar="DIR|GLOB", help="capture source: replay these frame files in order")
    capture.add_argument(
        "--sky",
        metavar="SCHEDULE",
        help="capture source: render each exposure with the sensor simulator at the attitudes of this schedule file",
    )
    capture.add_argument(
        "--attitude-feed",
        metavar="URL",
        help="capture source: render each exposure along the attitude path a simulator streams to "
        "tcp://HOST:PORT or udp://HOST:PORT (docs/hil.md)",
    )
    parser.add_argument("--loop", action="store_true", help="with --frames, start again after the last file")
    parser.add_argument(
        "--timing",
        choices=("fast", "realistic"),
        default="fast",
        help="fast: a result as soon as it is computed, an emulator convenience (default); realistic: "
        "held until --exposure-ms + --processing-ms after GO, the real unit's cadence of about 2 Hz, "
        "and the functional processor's boot takes --boot-ms",
    )
    parser.add_argument(
        "--exposure-ms", type=float, help=f"with --timing realistic (default {DEFAULT_TIMING.exposure_s * 1e3:g})"
    )
    parser.add_argument(
        "--processing-ms", type=float, help=f"with --timing realistic (default {DEFAULT_TIMING.processing_s * 1e3:g})"
    )
    parser.add_argument(
        "--boot-ms",
        type=float,
        help=f"with --timing realistic: a GO with LOAD_NAND's boot (default {DEFAULT_TIMING.boot_s * 1e3:g})",
    )
    clock = parser.add_argument_group("device clock (TIME; docs/ICD.md section 6; also the --params keys clock_*)")
    clock.add_argument(
        "--clock-epoch-s", type=float, help="the TIME count at power-on and after a reset, s (default 0)"
    )
    clock.add_argument("--clock-drift-ppm", type=float, help="rate error, ppm, -1000..1000 (default 0)")
    clock.add_argument("--clock-jitter-us", type=float, help="1-sigma jitter of a TIME latch, us, 0..1000 (default 0)")
    clock.add_argument("--clock-seed", type=int, default=0, help="seed of the jitter (default 0)")
    parser.add_argument(
        "--deadline-ms",
        type=float,
        help="with --timing realistic: flight timing's deadline from the frame's extraction; a search "
        "still running then stops, and the result says so (ext.search_flags, reason) "
        f"(default {DEFAULT_DEADLINE_MS:g}; without --timing realistic only counted budgets bound a "
        "search, the same answer on any machine)",
    )
    parser.add_argument("--params", help="default parameter set JSON (the slot-2 schema); an uploaded set wins")
    parser.add_argument(
        "--faults",
        metavar="FILE",
        help="arm this fault script at start (docs/ICD.md section 13; implies --fault-injection)",
    )
    parser.add_argument(
        "--fault-injection",
        action="store_true",
        help="accept the FAULT command (scripted faults for tests; off: FAULT is NACKed NOT_SUPPORTED)",
    )
    parser.add_argument(
        "--log-level",
        choices=("debug", "info", "warning", "error"),
        default="warning",
        help="messages on stderr from this level up (state damage, link faults, bugs: warning)",
    )
    return parser


def load_camera(path: str | None) -> CameraModel:
    from firmware_model.camera import CameraModel

    if path is None:
        return CameraModel.reference_design()
    try:
        return CameraModel.from_dict(user_files.load_json_file(path))
    except user_files.UserFileError as exc:  # it names the file
        raise ValueError(f"camera model {exc}") from None
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
        raise ValueError(f"camera model {path}: {exc}") from None


def load_params(path: str) -> DeviceParams:
    """The ``--params`` file (a regular file of at most ``user_files.MAX_JSON_BYTES``, JSON of
    bounded depth); ValueError naming the file."""
    from firmware_model.device.sensor_input import DeviceParams

    try:
        data = user_files.read_bytes(path, user_files.MAX_JSON_BYTES)
    except user_files.UserFileError as exc:
        raise ValueError(f"--params {exc}") from None
    try:
        return DeviceParams.from_json(data)
    except SlotRejected as exc:
        raise ValueError(f"--params {path}: {exc.message}") from None


def build_device(args: argparse.Namespace, shared_source: Callable[[SolveContext], Any] | None = None) -> Device:
    """The device the options describe: slots for catalog (0), frame (1) and parameters (2), the
    pipeline solver on the camera model, the capture source if one is given, and the ``--params``
    set's settings as the defaults (pipeline, ``quaternion_order``) until a set is uploaded. It is
    ready when this returns: kernels loaded, the stored catalog's pattern index built.
    ``shared_source``: a capture source several heads share (made ready by their bus), used in
    place of the options' own, its simulated clocks included."""
    from firmware_model.device.catalog_slot import catalog_slot_handler
    from firmware_model.device.device import Device, SlotHandler
    from firmware_model.device.sensor_input import (
        DeviceParams,
        PipelineSolver,
        frame_slot_handler,
        params_slot_handler,
    )
    from firmware_model.device.slots import SlotStore
    from firmware_model.pipeline import scale_free
    from firmware_model.pipeline.solve_types import PipelineParams

    if not 0 <= args.address <= 0xFF:
        raise ValueError(f"address 0x{args.address:X} outside 0x00-0xFF")
    camera = load_camera(args.camera)
    device_params = load_params(args.params) if args.params else DeviceParams()
    source = shared_source if shared_source is not None else _capture_source(args, camera)
    store = SlotStore(args.state, volatile={Slot.FRAME}) if args.state else None
    clock = clock_model(args, device_params)
    solver = PipelineSolver(
        camera,
        device_params.apply(PipelineParams()),
        tracking=bool(device_params.tracking),
        # a catalog seen before (by this install) loads its index in a few hundredths of a second
        build_index=functools.partial(scale_free.cached_pattern_index, user_cache_dir() / "pattern-index"),
        ephemerides=getattr(source, "timestamps", True),  # a source's frames without a time need none
    )
    slots: dict[int, SlotHandler] = {
        Slot.CATALOG: catalog_slot_handler(prepare=solver.prepare),
        Slot.FRAME: frame_slot_handler(camera),
        Slot.PARAMS: params_slot_handler(),
    }
    device = Device(
        args.address,
        store=store,
        slots=slots,
        solver=solver,
        frame_source=source,
        sensor_shape=(camera.height, camera.width),
        quaternion_order=device_params.quaternion_order or QuaternionOrder.SCALAR_FIRST,
        fault_injection=bool(args.fault_injection or args.faults),
        clock_model=clock,
        **_simulated_clocks(source),
    )
    if args.timing == "realistic":
        ms = {"exposure_s": args.exposure_ms, "processing_s": args.processing_ms, "boot_s": args.boot_ms}
        device.runner.timing = replace(DEFAULT_TIMING, **{k: v / 1000.0 for k, v in ms.items() if v is not None})
        deadline = DEFAULT_DEADLINE_MS if args.deadline_ms is None else args.deadline_ms
        solver.params = replace(solver.params, flight_deadline_s=deadline / 1000.0)
        from firmware_model.device.nand import ICD_PAGE_READ_S

        device.maintenance.pace_s = ICD_PAGE_READ_S  # the read disturbance test at the real unit's pace
    solver.serving()  # the stored catalog's index is built; a COMMIT's is built in another process
    ready = None if shared_source is not None else getattr(source, "ready", None)
    if ready is not None:  # a capture source's own start-up (a rendering source's noise), drawn meanwhile
        ready()
    return device


def _capture_source(args: argparse.Namespace, camera: CameraModel) -> Callable[[SolveContext], Any] | None:
    """The capture source the options name (``--frames``, ``--sky``, ``--attitude-feed``), or None."""
    from firmware_model.device.sensor_input import FileFrames, load_frame_source

    if args.frames:
        return FileFrames(args.frames, camera, loop=args.loop)
    if args.sky:
        return _named(f"--sky {args.sky}", lambda: load_frame_source("sky", args.sky, camera))
    if args.attitude_feed:
        return load_frame_source("attitude_feed", args.attitude_feed, camera)
    return None


def _simulated_clocks(source: Any) -> dict[str, Any]:
    """A capture source in simulated time (``simulated_clock``: the attitude feed's ``clock=sim``,
    a ``42://`` feed) gives the device both its clocks: POSIX time and the device clock's source
    (docs/hil.md "Simulated time"); otherwise none (the machine's)."""
    sim = getattr(source, "simulated_clock", None)
    return {} if sim is None else {"clock": sim.posix, "clock_source": sim.elapsed}


def clock_model(args: argparse.Namespace, params: DeviceParams) -> ClockModel:
    """The device clock's model: the options over the ``--params`` file's clock keys over the
    defaults; ValueError (one line) for a value out of range."""
    model = params.clock_model(ClockModel(seed=args.clock_seed))
    given = {"epoch_s": args.clock_epoch_s, "drift_ppm": args.clock_drift_ppm, "jitter_us": args.clock_jitter_us}
    model = replace(model, **{k: v for k, v in given.items() if v is not None})
    problems = model.problems()
    if problems:
        raise ValueError("; ".join(problems))
    return model


def _named(what: str, make: Callable[[], Any]) -> Any:
    """``make()``, its one-line errors naming ``what`` when they do not already (a binary file
    given to ``--sky`` said only ``'utf-8' codec can't decode byte 0xb4 ...``)."""
    try:
        return make()
    except UnicodeDecodeError as exc:
        raise ValueError(f"{what}: not UTF-8 text (byte 0x{exc.object[exc.start]:02X} at offset {exc.start})") from None
    except (ValueError, OSError) as exc:
        text = str(exc)
        if what.split(" ", 1)[1] in text:
            raise
        raise ValueError(f"{what}: {text}") from None


def load_fault_file(path: str) -> tuple[Fault, ...]:
    """The faults of the script at ``path``; ValueError (one line naming the line) if it does not
    parse or cannot be read: a FIFO or a device is refused, and a file over the
    ``MAX_FAULT_SCRIPT`` bytes one FAULT load carries is refused before it is read."""
    try:
        text = user_files.read_text(path, MAX_FAULT_SCRIPT)
    except user_files.UserFileError as exc:
        raise ValueError(f"fault file {exc}") from None
    try:
        return parse_script(text, path)
    except ValueError as exc:  # a 5000-digit count was echoed whole
        raise ValueError(user_files.shorten_words(str(exc))) from None


def build_link(args: argparse.Namespace) -> Link:
    """The transport the options name; OSError naming the port or address (``--tcp
    127.0.0.1:5000: [Errno 98] Address already in use``)."""
    url = "pty://" if args.pty else args.port if args.port else f"tcp://{args.tcp}"
    try:
        return open_link(url, baud=args.baud, tcp_idle=args.tcp_idle)
    except OSError as exc:
        option = "--pty" if args.pty else f"--port {args.port}" if args.port else f"--tcp {args.tcp}"
        detail = f"[Errno {exc.errno}] {exc.strerror}" if exc.errno is not None and exc.strerror else str(exc)
        raise OSError(f"{option}: {detail}") from None


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.baud <= 0:
        parser.error("--baud must be positive")
    turnaround_ms = args.turnaround_ms
    if turnaround_ms is None:
        turnaround_ms = DEFAULT_PACED_TURNAROUND_MS if args.pace else 0.0
    if turnaround_ms < 0:
        parser.error("--turnaround-ms must be >= 0")
    if not args.tcp_idle > 0:
        parser.error("--tcp-idle must be > 0")
    timed = (args.exposure_ms, args.processing_ms, args.deadline_ms, args.boot_ms)
    if args.timing != "realistic" and any(v is not None for v in timed):
        parser.error("--exposure-ms, --processing-ms, --deadline-ms and --boot-ms need --timing realistic")
    if any(v is not None and not 0 <= v <= 60_000 for v in timed):
        parser.error("--exposure-ms, --processing-ms, --deadline-ms and --boot-ms must be 0..60000")
    from firmware_model.device.sensor_input import DeviceParams

    try:
        clock_model(args, DeviceParams())  # the options alone, before the slow start (the --params file's later)
    except ValueError as exc:
        parser.error(str(exc))
    if args.heads:
        from firmware_model.device import heads

        return serve_until_stopped(args, turnaround_ms, heads.build_from_file)
    return serve_until_stopped(args, turnaround_ms, _build_armed_device)


def _build_armed_device(args: argparse.Namespace, faults: tuple[Fault, ...]) -> Device:
    """The one device the options describe, ``faults`` armed."""
    device = build_device(args)
    device.arm(faults)
    return device


def serve_until_stopped(
    args: argparse.Namespace, turnaround_ms: float, build: Callable[[argparse.Namespace, tuple[Fault, ...]], Any]
) -> int:
    """Start (the fault file and the port checked before the slow build), say ``listening on``,
    serve until SIGINT or SIGTERM, then stop cleanly: 0; 2 with one line on stderr for bad input.
    ``build(args, faults)``: what serves the link (a ``Device``, or the heads' ``Bus``), with
    ``arm``, ``drop_delayed``, ``wait_idle`` and ``close``."""
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr, format="%(message)s")
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    link: Link | None = None
    try:
        faults = load_fault_file(args.faults) if args.faults else ()  # before the slow start
        link = build_link(args)  # so is the port: a busy address is one line at once, naming it
        target = build(args, faults)
    except (ValueError, OSError) as exc:
        if link is not None:
            link.close()
        print(f"st16-device: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def stop_bounded(*_: object) -> None:
        # armed once, at the first signal (a later one would restart its count), until the process
        # ends: it watches the interpreter's exit too (its joins)
        if not stop.is_set():
            faulthandler.dump_traceback_later(STOP_WATCHDOG_S, exit=True, file=2)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, stop_bounded)
    # a device that seems hung: ``kill -USR1 PID`` writes every thread's stack to stderr (fd 2)
    faulthandler.register(signal.SIGUSR1, file=2, all_threads=True)
    # start-up's objects (modules, kernels, the catalog) live as long as the device: out of every
    # full collection, which walks them holding the GIL from the link and the running sequence
    gc.freeze()
    print(f"listening on {link.describe()}", flush=True)
    try:
        serve(target, link, stop, baud=args.baud if args.pace else None, turnaround=turnaround_ms / 1000.0)
    finally:
        target.drop_delayed()
        target.wait_idle(timeout=5.0)
        link.close()
        target.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
