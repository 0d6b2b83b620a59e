"""The device's GO sequence: GO and COMBINATION start it, a worker thread runs the pluggable
solver on a snapshot of the slots (:class:`SolveContext`) while the device keeps answering, and
its result structure is what READ RESULT and COMBINATION return; IMAGE's dark windows are inputs
of the next sequences. The runner tells whether a sequence runs (BUSY) and whether a result is
ready. Scripted faults (``faults``) may leave a sequence's result stuck, freeze the detector or
upset the catalog; a scripted reset (:meth:`SequenceRunner.reset`) clears the result."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from firmware_model.device.cosmos_compat import finish
from firmware_model.device.dispatch import Mode, Pending, Refused
from firmware_model.device.faults import FaultInjector
from firmware_model.device.housekeeping import Housekeeping
from firmware_model.device.transfers import Transfers
from protocol import result
from protocol.commands import AddressedBytes, Combination, DarkWindow, Go, GoBits, NackReason, ReadRange, Slot
from protocol.crc import crc32

log = logging.getLogger("firmware_model.device.device")  # one logger for the device shell

RESULT_PART = 1024  #: result bytes per message of a multi-part reply (ours)
MAX_DARK_WINDOWS = 32  #: per image buffer
COMBINATION_TIMEOUT = 60.0  #: seconds COMBINATION waits for its sequence


class FrameUnavailable(Exception):
    """Raised by a frame source for a frame it cannot deliver (unreadable file, wrong size)."""


@dataclass(frozen=True)
class SolveContext:
    """What a solver sees for one GO sequence (a snapshot; later uploads do not change it)."""

    go_code: int
    sequence: int
    started: float  #: POSIX UTC seconds at GO
    catalog: Any
    frame: Any
    params: Any
    catalog_crc32: int
    frame_crc32: int
    dark_windows: tuple[DarkWindow, ...]
    sensor_shape: tuple[int, int]
    quaternion_order: result.QuaternionOrder  #: of the standard structure's quaternions


#: ``solver(ctx) -> {result field path: value}``; must set ``"return_code"``.
Solver = Callable[[SolveContext], Mapping[str, Any]]


class Settings(Protocol):
    """What a sequence takes from the device when it starts (the device itself)."""

    solver: Solver | None
    frame_source: Callable[[SolveContext], Any] | None
    clock: Callable[[], float]
    sensor_shape: tuple[int, int]
    quaternion_order: result.QuaternionOrder  #: unless the slot-2 parameter set names one
    housekeeping: Housekeeping  #: duty-cycle driven temperatures for the hardware section
    faults: FaultInjector  #: scripted faults (stuck result, frozen detector, upsets)


def _quaternion_order(params: Any, default: result.QuaternionOrder) -> result.QuaternionOrder:
    """The order a sequence writes the standard quaternions in: the slot-2 parameter set's when it
    names one (``DeviceParams.quaternion_order``), else the device's ``default``."""
    order = getattr(params, "quaternion_order", None)
    return order if isinstance(order, result.QuaternionOrder) else default


class SequenceRunner:
    """GO sequences of one device. ``lock`` is the device lock (the worker takes it to publish a
    result); ``solver``, ``frame_source``, ``clock`` and ``sensor_shape`` are read from
    ``settings`` (the device) when a sequence starts, so they may be replaced between sequences."""

    def __init__(self, lock: threading.RLock, mode: Mode, transfers: Transfers, settings: Settings):
        self._lock = lock
        self.mode = mode
        self.transfers = transfers
        self.settings = settings
        self.done = threading.Condition(lock)
        self.hold_s = 0.0  #: a result is published no sooner than this long after its GO (--timing realistic)
        self._epoch = 0  #: bumped by a reset: a sequence started before it publishes nothing
        self._clear()

    def _clear(self) -> None:
        """The state at start: NO_RESULT, sequence 0, no dark windows, no frame captured."""
        no_result = {
            **self.settings.housekeeping.result_fields(),
            "return_code": result.make_return_code(result.Status.NO_RESULT),
        }
        self.result = result.build(finish(no_result, self.settings.quaternion_order), 0)
        self.result_ready = False
        self.sequence = 0
        self._busy: threading.Thread | None = None
        self.dark: dict[int, list[DarkWindow]] = {0: [], 1: []}
        self.last_capture: Any = None  #: the detector's last frame (a frozen detector returns it)

    def reset(self) -> None:
        """A scripted reset (with the lock held): the result cleared to NO_RESULT as at start; a
        running sequence is abandoned."""
        self._epoch += 1
        self._clear()
        self.settings.faults.written("result")
        self.settings.housekeeping.set_busy(False)
        self.done.notify_all()

    @property
    def busy(self) -> bool:
        return self._busy is not None

    # ------------------------------------------------------------------ commands

    def go(self, req: Go) -> bytes:
        self._go(req.code)
        return Go(req.code).pack()

    def _go(self, code: int) -> None:
        if code & ~0x3F:
            raise Refused(NackReason.BAD_PARAMETER, f"unknown GO bits 0x{code & ~0x3F:02X}")
        if code & GoBits.TEST:
            raise Refused(NackReason.NOT_SUPPORTED, "the self-test sequence (GO bit 0x10) is not emulated")
        if not self.mode.app:
            if not code & GoBits.LOAD_NAND:
                raise Refused(NackReason.WRONG_MODE, "GO without LOAD_NAND (0x02) needs application mode")
            self.mode.app = True
        if code & GoBits.COMMAND:
            if self.busy:
                raise Refused(NackReason.BUSY, f"sequence {self.sequence} still running")
            self._start(code)

    def read_result(self, req: ReadRange) -> list[bytes]:
        self.mode.require_app("READ RESULT")
        if req.count < 1 or req.address + req.count > result.TOTAL_LENGTH:
            raise Refused(
                NackReason.BAD_ADDRESS, f"result 0x{req.address:04X}+{req.count} outside 0..{result.TOTAL_LENGTH}"
            )
        return self._result_parts(req.address, req.count)

    def _result_parts(self, address: int, count: int) -> list[bytes]:
        self.settings.faults.read("result", address, count)
        parts = []
        for start in range(address, address + count, RESULT_PART):
            n = min(RESULT_PART, address + count - start)
            parts.append(AddressedBytes(start, self.result[start : start + n]).pack())
        return parts

    def image(self, data: bytes) -> bytes:
        self.mode.require_app("IMAGE")
        if not data:
            raise Refused(NackReason.BAD_LENGTH, "IMAGE needs a subcommand byte")
        if data[0] == 1:
            raise Refused(NackReason.NOT_SUPPORTED, "Rectangular Poke (IMAGE subcommand 1) is not emulated")
        if data[0] != DarkWindow.SUBCOMMAND:
            raise Refused(NackReason.BAD_PARAMETER, f"IMAGE subcommand {data[0]} is reserved")
        win = DarkWindow.unpack(data)
        rows, cols = self.settings.sensor_shape
        if win.buffer not in self.dark:
            raise Refused(NackReason.BAD_PARAMETER, f"image buffer {win.buffer} not 0 or 1")
        if win.rows < 1 or win.cols < 1 or win.row + win.rows > rows or win.col + win.cols > cols:
            raise Refused(NackReason.OUT_OF_RANGE, f"window outside the {rows}x{cols} sensor")
        if len(self.dark[win.buffer]) >= MAX_DARK_WINDOWS:
            raise Refused(NackReason.TOO_LARGE, f"buffer {win.buffer} already has {MAX_DARK_WINDOWS} dark windows")
        self.dark[win.buffer].append(win)
        return data

    def combination(self, req: Combination) -> list[bytes] | Pending:
        if req.mask & result.SELF_TEST_SECTION:
            raise Refused(NackReason.NOT_SUPPORTED, "the self-test result section (0x0800) is not emulated")
        unknown = req.mask & ~sum(result.SECTIONS)
        if unknown:
            raise Refused(NackReason.BAD_PARAMETER, f"unknown section bits 0x{unknown:X}")
        self._go(req.go_code)
        if req.go_code & GoBits.COMMAND:
            return Pending(lambda: self._combination_parts(req.mask, time.monotonic() + COMBINATION_TIMEOUT))
        return self._combination_parts(req.mask, None)

    def _combination_parts(self, mask: int, deadline: float | None) -> list[bytes]:
        """The result sections of ``mask``, once the running sequence is done (by ``deadline``,
        monotonic s; None: at once). Call with the lock held."""
        while deadline is not None and self.busy:
            if not self.done.wait(timeout=max(0.0, deadline - time.monotonic())):
                raise Refused(NackReason.BUSY, "sequence did not complete in time")
        parts: list[bytes] = []
        for bit, (address, length) in sorted(result.SECTIONS.items()):
            if mask & bit:
                parts.extend(self._result_parts(address, length))
        return parts or [b""]

    # ------------------------------------------------------------------ the sequence

    def _start(self, code: int) -> None:
        tr, st = self.transfers, self.settings
        if st.faults.stuck():  # done at once: the last result and its sequence number stay
            self.result_ready = True
            return
        stored = tr.store.active(Slot.CATALOG)
        if stored is not None and st.faults.catalog_access():  # reloaded from its stored image
            tr.objects[Slot.CATALOG] = tr.slots[Slot.CATALOG].activate(stored)
        self.sequence += 1
        self.result_ready = False
        st.housekeeping.set_busy(True)
        params = tr.objects.get(Slot.PARAMS)
        ctx = SolveContext(
            go_code=code,
            sequence=self.sequence,
            started=st.clock(),
            catalog=tr.objects.get(Slot.CATALOG),
            frame=tr.objects.get(Slot.FRAME),
            params=params,
            catalog_crc32=crc32(stored or b""),
            frame_crc32=crc32(tr.store.active(1) or b""),
            dark_windows=tuple(self.dark[0] + self.dark[1]),
            sensor_shape=st.sensor_shape,
            quaternion_order=_quaternion_order(params, st.quaternion_order),
        )
        uploaded, tr.frame_pending = tr.frame_pending, False
        self._busy = threading.Thread(
            target=self._run, args=(ctx, uploaded, self._epoch), name=f"sequence-{ctx.sequence}", daemon=True
        )
        self._busy.start()

    def _fields(self, ctx: SolveContext, uploaded: bool) -> Mapping[str, Any]:
        base: dict[str, Any] = {"epoch": ctx.started, "ext.catalog_crc32": ctx.catalog_crc32}

        def status(st: result.Status, reason: str) -> dict[str, Any]:
            return {
                **base,
                "return_code": result.make_return_code(st),
                "ext.reason": reason.encode()[: result.EXT_REASON_BYTES],
            }

        capture = None if uploaded else self.settings.frame_source  # the emulated detector
        if ctx.catalog is None:
            return status(result.Status.NO_CATALOG, "no catalog: upload one to slot 0")
        if capture is not None:
            frame = self.last_capture
            if frame is None or not self.settings.faults.frozen():
                try:
                    frame = capture(ctx)
                except FrameUnavailable as exc:
                    return status(result.Status.BAD_FRAME, str(exc))
                if frame is None:
                    return status(result.Status.NO_FRAME, "the capture source has no more frames")
                self.last_capture = frame
            ctx = SolveContext(**{**ctx.__dict__, "frame": frame, "frame_crc32": 0})
        if ctx.frame is None:
            return status(result.Status.NO_FRAME, "no frame: no capture source and none uploaded to slot 1")
        base["ext.frame_crc32"] = ctx.frame_crc32
        solver = self.settings.solver
        if solver is None:
            return {**base, "return_code": result.make_return_code(result.Status.NO_SOLVER)}
        t0 = time.perf_counter()
        fields = dict(solver(ctx))
        if "ext.reason" in fields and isinstance(fields["ext.reason"], str):
            fields["ext.reason"] = fields["ext.reason"].encode()[: result.EXT_REASON_BYTES]
        if "return_code" not in fields:
            raise ValueError("solver returned no return_code")
        fields.setdefault("ext.solve_time", time.perf_counter() - t0)
        if capture is not None:
            fields["return_code"] = int(fields["return_code"]) | result.ReturnBits.DETECTOR_IMAGE
        return {**base, **fields}

    def _run(self, ctx: SolveContext, uploaded: bool, epoch: int) -> None:
        try:
            fields = {**self.settings.housekeeping.result_fields(), **self._fields(ctx, uploaded)}
            data = result.build(finish(fields, ctx.quaternion_order), ctx.sequence)
        except Exception as exc:
            log.exception("device: bug while handling a command or sequence")
            failed = {
                **self.settings.housekeeping.result_fields(),
                "epoch": ctx.started,
                "return_code": result.make_return_code(result.Status.SOLVER_ERROR),
                "ext.reason": f"{type(exc).__name__}: {exc}".encode()[: result.EXT_REASON_BYTES],
            }
            data = result.build(finish(failed, ctx.quaternion_order), ctx.sequence)
        held = ctx.started + self.hold_s - self.settings.clock()
        if held > 0:
            time.sleep(held)
        with self._lock:
            if epoch != self._epoch:  # a reset came first: the sequence never ends
                return
            self.result = data
            self.settings.faults.written("result")
            self.result_ready = True
            self._busy = None
            self.settings.housekeeping.set_busy(False)
            self.done.notify_all()
        if log.isEnabledFor(logging.INFO):
            status = result.status_of(int(result.parse(data)["return_code"]))
            name = status.name if isinstance(status, result.Status) else f"status {status}"
            log.info("device: sequence %d done: %s", ctx.sequence, name)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until no sequence runs; False on timeout."""
        with self._lock:
            return self.done.wait_for(lambda: not self.busy, timeout)
