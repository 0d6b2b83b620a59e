"""The device's GO sequence: GO and COMBINATION start it, a worker thread runs the pluggable
solver on a snapshot of the slots (:class:`SolveContext`) while the device keeps answering, and
its result structure is what READ RESULT and COMBINATION return; a GO without COMMAND terminates a
running sequence. IMAGE's dark windows are inputs of the next sequences, and its Rectangular Poke
writes the image buffers a GO with INJECTED processes instead of exposing. A GO with LOAD_NAND in
bootloader mode boots the functional processor. The runner tells whether a sequence runs (BUSY),
whether a result is ready, and the sequence state a COMBINATION failure reply carries;
:class:`Timing` holds a real sensor's cadence (``--timing realistic``). Scripted faults
(``faults``) may leave a sequence's result stuck, freeze the detector or upset the catalog; a
scripted reset (:meth:`SequenceRunner.reset`) clears the result."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from firmware_model.device.clock import DeviceClock
from firmware_model.device.cosmos_compat import finish
from firmware_model.device.dispatch import Mode, Pending, Refused
from firmware_model.device.faults import FaultInjector
from firmware_model.device.housekeeping import Housekeeping
from firmware_model.device.transfers import Transfers
from protocol import result
from protocol.commands import (
    CACHED_TABLE_BITS,
    AddressedBytes,
    Combination,
    DarkWindow,
    Go,
    GoBits,
    NackReason,
    ReadRange,
    RectangularPoke,
    SequenceState,
    Slot,
)
from protocol.crc import crc32

log = logging.getLogger("firmware_model.device.device")  # one logger for the device shell

RESULT_PART = 1024  #: result bytes per message of a multi-part reply (ours)
MAX_DARK_WINDOWS = 32  #: per image buffer
COMBINATION_TIMEOUT = 60.0  #: seconds COMBINATION waits for its sequence
KNOWN_GO_BITS = 0x7F  #: bit 7 is unassigned: NACKed BAD_PARAMETER
MAX_EXPOSURE_S = 60.0  #: a frame stamped more than this after its GO was not exposed by it
#: the boot message a GO with LOAD_NAND leaves in EDAC (ICD page 1-35916 names an ASIC ID message;
#: its text is ours)
BOOT_MESSAGE = "ASIC ID 0x5316 rev 1; boot NAND 0-3; application NAND 0x8000"


@dataclass(frozen=True)
class Timing:
    """A real sensor's cadence (``st16-device --timing realistic``; docs/ICD.md section 7, "Timing"),
    all in seconds: GO to result is ``exposure_s + processing_s``, of which ``table_s`` builds the
    triangle table; with the parameter ``cache_triangle_table`` and a GO with bits 2 and 5 the first
    such GO spends ``cache_write_s`` more to cache it and later ones skip ``table_s`` (ICD page
    1-35924: the first GO is slower than the rest). ``boot_s`` is the functional processor's boot
    from NAND. The defaults make about 2 Hz, the real unit's cadence (ICD page 1-35923); each
    split is an assumption."""

    exposure_s: float = 0.100
    processing_s: float = 0.400
    table_s: float = 0.150
    cache_write_s: float = 0.100
    boot_s: float = 0.800

    def hold(self, table: str) -> float:
        """Seconds from GO to result for a sequence whose triangle table is ``built`` (every GO
        without the cache), ``cached`` (written this GO) or ``reused``."""
        extra = {"built": 0.0, "cached": self.cache_write_s, "reused": -self.table_s}[table]
        return self.exposure_s + self.processing_s + extra


@dataclass(frozen=True)
class InjectedFormat:
    """How the device reads its image buffers (IMAGE Rectangular Poke, GO bit INJECTED): the
    emulated detector's CFA pattern, black and white levels (DN)."""

    pattern: str = "RGGB"
    black_level: float = 64.0
    white_level: float = 4095.0


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
    device_time: float = 0.0  #: the device clock at GO (s of the TIME count)


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
    device_clock: DeviceClock  #: the clock TIME reads and every reported time is on

    def arrival(self) -> float:
        """When the command being handled arrived (its final FEND; the clock source's time)."""

    def injected(self, pixels: np.ndarray) -> Any:
        """The frame of an image buffer (GO bit INJECTED)."""


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
        self.timing: Timing | None = None  #: --timing realistic; None: a result as soon as computed
        self._epoch = 0  #: bumped by a reset or a terminate: a sequence started before publishes nothing
        #: inboxes of the worker threads free for the next sequence, the last freed at the end
        self._free: list[queue.SimpleQueue[tuple[Any, ...]]] = []
        self.workers = 0  #: worker threads started (the sequences run on them, kept between sequences)
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
        self._busy = False  #: a sequence runs (until it publishes, or a reset or a terminate abandons it)
        self.dark: dict[int, list[DarkWindow]] = {0: [], 1: []}
        self.buffers: dict[int, np.ndarray] = {}  #: image buffers written by Rectangular Poke (zero until then)
        self.last_capture: Any = None  #: the detector's last frame (a frozen detector returns it)
        self.state = SequenceState.IDLE  #: what a COMBINATION failure reply says
        self.booting = False  #: the functional processor is loading from NAND
        self.boot_message = ""  #: EDAC 0x00C0 after a boot
        self._table_cached = False  #: the triangle table is cached (since the last boot or reset)
        self._running_epoch = self._running_utc = 0.0  #: the running sequence's GO: device clock s, POSIX s

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
        return self._busy or self.booting

    # ------------------------------------------------------------------ commands

    def go(self, req: Go) -> bytes:
        self._go(req.code)
        return Go(req.code).pack()

    def _go(self, code: int) -> None:
        if code & ~KNOWN_GO_BITS:
            raise Refused(NackReason.BAD_PARAMETER, f"unknown GO bits 0x{code & ~KNOWN_GO_BITS:02X}")
        if code & GoBits.TEST:
            raise Refused(NackReason.NOT_SUPPORTED, "the self-test sequence (GO bit 0x10) is not emulated")
        if self.booting:
            raise Refused(NackReason.BUSY, "the functional processor is booting from NAND")
        if not code & GoBits.COMMAND:
            self._terminate(code)
        if not self.mode.app:
            if not code & GoBits.LOAD_NAND:
                raise Refused(NackReason.WRONG_MODE, "GO without LOAD_NAND (0x02) needs application mode")
            self._boot()
        if code & GoBits.COMMAND:
            if self.busy:
                raise Refused(NackReason.BUSY, f"sequence {self.sequence} still running")
            self._start(code)

    def _terminate(self, code: int) -> None:
        """A GO without COMMAND: a running sequence ends now, its result TERMINATED (sequence
        number and epoch of that GO, no attitude); nothing when none runs."""
        if not self._busy:
            return
        self._epoch += 1  # its worker's result is dropped
        fields = {
            **self.settings.housekeeping.result_fields(),
            "epoch": self._running_epoch,
            "ext.utc_epoch": self._running_utc,
            "return_code": result.make_return_code(result.Status.TERMINATED),
            "ext.reason": f"sequence {self.sequence} terminated by GO 0x{code:02X}".encode(),
        }
        self.result = result.build(finish(fields, self.settings.quaternion_order), self.sequence)
        self.settings.faults.written("result")
        self._finish(SequenceState.TERMINATED)

    def _boot(self) -> None:
        """GO with LOAD_NAND in bootloader mode: the functional processor loads its bootloader and
        the application image from NAND (``Timing.boot_s``; at once with fast timing), leaves its
        boot message in EDAC, then runs the application."""
        delay = self.timing.boot_s if self.timing is not None else 0.0
        if delay <= 0:
            self._booted()
            return
        self.booting = True
        epoch = self._epoch
        threading.Thread(target=self._boot_after, args=(delay, epoch), name="boot", daemon=True).start()

    def _boot_after(self, delay: float, epoch: int) -> None:
        time.sleep(delay)
        with self._lock:
            if epoch == self._epoch:
                self._booted()
            self.done.notify_all()

    def _booted(self) -> None:
        self.booting = False
        self.boot_message = BOOT_MESSAGE
        self._table_cached = False
        self.mode.app = True

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
        if data[0] == RectangularPoke.SUBCOMMAND:
            return self._poke(RectangularPoke.unpack(data))
        if data[0] != DarkWindow.SUBCOMMAND:
            raise Refused(NackReason.BAD_PARAMETER, f"IMAGE subcommand {data[0]} is reserved")
        win = DarkWindow.unpack(data)
        if win.buffer not in self.dark:
            raise Refused(NackReason.BAD_PARAMETER, f"image buffer {win.buffer} not 0 or 1")
        self._inside("window", win.row, win.col, win.rows, win.cols)
        if len(self.dark[win.buffer]) >= MAX_DARK_WINDOWS:
            raise Refused(NackReason.TOO_LARGE, f"buffer {win.buffer} already has {MAX_DARK_WINDOWS} dark windows")
        self.dark[win.buffer].append(win)
        return data

    def _inside(self, what: str, row: int, col: int, rows: int, cols: int) -> None:
        height, width = self.settings.sensor_shape
        if rows < 1 or cols < 1 or row + rows > height or col + cols > width:
            raise Refused(
                NackReason.OUT_OF_RANGE,
                f"{what} {rows}x{cols} at row {row}, column {col} outside the {height}x{width} sensor",
            )

    def _poke(self, poke: RectangularPoke) -> bytes:
        """IMAGE Rectangular Poke: the pixel values into a rectangle of an image buffer; a bad
        rectangle is refused with the buffer unchanged."""
        if poke.buffer not in (0, 1):
            raise Refused(NackReason.BAD_PARAMETER, f"image buffer {poke.buffer} not 0 or 1")
        self._inside("rectangle", poke.row, poke.col, poke.rows, poke.cols)
        if len(poke.pixels) != 2 * poke.rows * poke.cols:
            raise Refused(
                NackReason.BAD_LENGTH,
                f"rectangle {poke.rows}x{poke.cols} needs {2 * poke.rows * poke.cols} pixel bytes, got {len(poke.pixels)}",
            )
        buf = self.buffers.get(poke.buffer)
        if buf is None:
            buf = self.buffers[poke.buffer] = np.zeros(self.settings.sensor_shape, np.uint16)
        values = np.frombuffer(poke.pixels, "<u2").reshape(poke.rows, poke.cols)
        buf[poke.row : poke.row + poke.rows, poke.col : poke.col + poke.cols] = values
        return poke.head()

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
        if deadline is not None and self.state == SequenceState.TERMINATED:
            raise Refused(NackReason.BUSY, f"sequence {self.sequence} terminated before its data")
        return self._counted_parts(sorted(section for bit, section in result.SECTIONS.items() if mask & bit))

    def _counted_parts(self, sections: list[tuple[int, int]]) -> list[bytes]:
        """COMBINATION's success reply (ICD page 1-35918): the ``sections`` (address, length; in
        increasing address order) as one stream, in messages of at most RESULT_PART result bytes,
        each ``u16 bytes already transmitted`` (by the earlier messages of the reply) + its bytes;
        no section: one message of just ``u16 0``."""
        stream = bytearray()
        for address, length in sections:
            self.settings.faults.read("result", address, length)
            stream += self.result[address : address + length]
        return [
            sent.to_bytes(2, "little") + bytes(stream[sent : sent + RESULT_PART])
            for sent in range(0, max(len(stream), 1), RESULT_PART)
        ]

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
        self.state = SequenceState.RUNNING
        st.housekeeping.set_busy(True)
        params = tr.objects.get(Slot.PARAMS)
        now = st.arrival()  # the exposure starts when the GO has arrived
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
            device_time=st.device_clock.seconds(now),
        )
        self._running_epoch, self._running_utc = ctx.device_time, ctx.started
        hold = 0.0 if self.timing is None else self.timing.hold(self._table(code, params))
        uploaded, tr.frame_pending = tr.frame_pending, False
        self._busy = True
        inbox = self._free.pop() if self._free else self._worker()
        inbox.put((ctx, uploaded, self._epoch, now + hold, inbox))

    def _worker(self) -> queue.SimpleQueue[tuple[Any, ...]]:
        """A new worker thread; the inbox it takes sequences from. A worker is kept for the next
        sequence once its own publishes or is abandoned, so sequences run on one thread while none
        is abandoned: a thread per sequence took whatever malloc arena the thread that ended last
        left (after a COMBINATION, its reply thread's), and the capture's arrays page-faulted into
        new memory, a GO after a COMBINATION computing slower than one after a GO."""
        inbox: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        self.workers += 1
        threading.Thread(target=self._serve, args=(inbox,), name=f"sequence-worker-{self.workers}", daemon=True).start()
        return inbox

    def _serve(self, inbox: queue.SimpleQueue[tuple[Any, ...]]) -> None:
        """A worker thread: the sequences put in ``inbox``, one after another, for ever."""
        while True:
            job = inbox.get()
            try:
                self._run(*job)
            except Exception:  # logged as a command's bug is; the thread lives on
                log.exception("device: bug while handling a command or sequence")

    def _table(self, code: int, params: Any) -> str:
        """How this GO's triangle table comes (:meth:`Timing.hold`): ``built`` without the cache
        (the parameter ``cache_triangle_table`` off, or GO bits 2 and 5 not both set), else
        ``cached`` the first time and ``reused`` after."""
        if not getattr(params, "cache_triangle_table", False) or code & CACHED_TABLE_BITS != CACHED_TABLE_BITS:
            return "built"
        if self._table_cached:
            return "reused"
        self._table_cached = True
        return "cached"

    def _capture(self, ctx: SolveContext, uploaded: bool) -> Callable[[SolveContext], Any] | None:
        """The capture of this sequence: image buffer 0 (GO bit INJECTED), the emulated detector,
        or None (the frame uploaded to slot 1)."""
        if ctx.go_code & GoBits.INJECTED:
            buf = self.buffers.get(0)
            pixels = buf.copy() if buf is not None else np.zeros(ctx.sensor_shape, np.uint16)
            return lambda _ctx: self.settings.injected(pixels)
        return None if uploaded else self.settings.frame_source

    def _fields(self, ctx: SolveContext, uploaded: bool) -> Mapping[str, Any]:
        base: dict[str, Any] = {
            "epoch": ctx.device_time,
            "ext.utc_epoch": ctx.started,
            "ext.catalog_crc32": ctx.catalog_crc32,
        }

        def status(st: result.Status, reason: str) -> dict[str, Any]:
            return {
                **base,
                "return_code": result.make_return_code(st),
                "ext.reason": reason.encode()[: result.EXT_REASON_BYTES],
            }

        capture = self._capture(ctx, uploaded)
        injected = bool(ctx.go_code & GoBits.INJECTED)
        if ctx.catalog is None:
            return status(result.Status.NO_CATALOG, "no catalog: upload one to slot 0")
        if capture is not None:
            frame = self.last_capture
            if injected or frame is None or not self.settings.faults.frozen():
                try:
                    frame = capture(ctx)
                except FrameUnavailable as exc:
                    return status(result.Status.BAD_FRAME, str(exc))
                if frame is None:
                    return status(result.Status.NO_FRAME, "the capture source has no more frames")
                if not injected:
                    self.last_capture = frame
            ctx = replace(ctx, frame=frame, frame_crc32=0)
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
        if capture is not None and not injected:
            fields["return_code"] = int(fields["return_code"]) | result.ReturnBits.DETECTOR_IMAGE
        fields["epoch"] = self._device_epoch(ctx, float(fields.get("ext.utc_epoch", ctx.started)))
        return {**base, **fields}

    def _device_epoch(self, ctx: SolveContext, utc_mid: float) -> float:
        """The device clock at the exposure's mid-time ``utc_mid`` (POSIX s, the solver's): the
        GO's reading plus the time since GO at the clock's rate, when the frame was exposed after
        this GO (a live capture); else (an uploaded or replayed frame with an older timestamp of its
        own) the GO's reading."""
        since = utc_mid - ctx.started
        if not 0.0 <= since <= MAX_EXPOSURE_S:
            return ctx.device_time
        return ctx.device_time + since * (1.0 + self.settings.device_clock.model.drift_ppm * 1e-6)

    def _run(
        self, ctx: SolveContext, uploaded: bool, epoch: int, ready_at: float, inbox: queue.SimpleQueue[tuple[Any, ...]]
    ) -> None:
        """Sequence ``ctx`` on the worker whose ``inbox`` it came from: compute its result, hold it
        until ``ready_at`` (the clock source's s), publish it unless ``epoch`` has passed; the
        worker is free for the next sequence from then (under the lock, before a waiting
        COMBINATION can answer and its host send the next GO)."""
        started = time.perf_counter()
        try:
            fields = {**self.settings.housekeeping.result_fields(), **self._fields(ctx, uploaded)}
            data = result.build(finish(fields, ctx.quaternion_order), ctx.sequence)
        except Exception as exc:
            log.exception("device: bug while handling a command or sequence")
            failed = {
                **self.settings.housekeeping.result_fields(),
                "epoch": ctx.device_time,
                "ext.utc_epoch": ctx.started,
                "return_code": result.make_return_code(result.Status.SOLVER_ERROR),
                "ext.reason": f"{type(exc).__name__}: {exc}".encode()[: result.EXT_REASON_BYTES],
            }
            data = result.build(finish(failed, ctx.quaternion_order), ctx.sequence)
        computed = time.perf_counter() - started
        held = ready_at - self.settings.device_clock.source()
        if held > 0:
            time.sleep(held)
        with self._lock:
            self._free.append(inbox)
            if epoch != self._epoch:  # a reset or a terminate came first: the sequence never ends
                return
            self.result = data
            self.settings.faults.written("result")
            self._finish(SequenceState.DONE)
            late = self.settings.device_clock.source() - ready_at
        log.debug(
            "device: sequence %d computed in %.1f ms, published %.1f ms after its hold",
            ctx.sequence,
            computed * 1e3,
            late * 1e3,
        )
        if log.isEnabledFor(logging.INFO):
            status = result.status_of(int(result.parse(data)["return_code"]))
            name = status.name if isinstance(status, result.Status) else f"status {status}"
            log.info("device: sequence %d done: %s", ctx.sequence, name)

    def _finish(self, state: SequenceState) -> None:
        """The running sequence ends in ``state`` (lock held): its result is ready."""
        self.result_ready = True
        self._busy = False
        self.state = state
        self.settings.housekeeping.set_busy(False)
        self.done.notify_all()

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until no sequence runs; False on timeout."""
        with self._lock:
            return self.done.wait_for(lambda: not self.busy, timeout)
