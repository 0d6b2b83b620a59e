"""The emulated tracker's link shell: bytes in, framed replies out (docs/ICD.md).

:class:`Device` ties the parts of the shell together; each part is a module with one job:

* :mod:`~firmware_model.device.dispatch`: the command table's handlers, counters, NACKs and
  late replies;
* :mod:`~firmware_model.device.memory`: the 512-byte EDAC memory and the PEEK/POKE memory map;
* :mod:`~firmware_model.device.transfers`: the slots and resumable transfers (XFER_*, SLOT INFO);
* :mod:`~firmware_model.device.sequence`: GO, COMBINATION, READ RESULT and IMAGE, the worker
  thread that runs the pluggable ``solver``, BUSY and result ready;
* :mod:`~firmware_model.device.faults`: scripted faults (FAULT, ``st16-device --faults``) and
  their counters;
* :mod:`~firmware_model.device.clock`: the device clock TIME reads and every reported time is on.

The device does no I/O of its own: a transport (``firmware_model.device.link``) feeds received
bytes to :meth:`Device.receive` and writes back the frames it returns. A GO sequence runs in a
worker thread; the device keeps answering meanwhile. A COMBINATION that waits for its sequence
answers through :attr:`Device.late_reply` when the transport sets it (the link keeps being served
meanwhile), else the call returns only when the sequence is done.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import protocol
from firmware_model.device.clock import ClockModel, DeviceClock
from firmware_model.device.dispatch import Counters, Dispatcher, Handler, Mode, Refused
from firmware_model.device.faults import Fault, FaultInjector, FaultScriptError, parse_script
from firmware_model.device.housekeeping import Housekeeping
from firmware_model.device.memory import WORDS, Memory, Supervisor
from firmware_model.device.nand import MAINTENANCE_ADDRESS, Maintenance, Nand
from firmware_model.device.sequence import (
    COMBINATION_TIMEOUT,
    MAX_DARK_WINDOWS,
    RESULT_PART,
    FrameUnavailable,
    InjectedFormat,
    SequenceRunner,
    SolveContext,
    Solver,
)
from firmware_model.device.slots import SlotStore
from firmware_model.device.transfers import SlotHandler, Transfers, default_slots
from firmware_model.pipeline.raw_frame import Frame
from protocol import edac, nsp, result, slip
from protocol.commands import (
    APP_START_ADDRESS,
    Code,
    Combination,
    DiagnosticRequest,
    FaultAction,
    FaultRequest,
    FaultStatus,
    Go,
    GoBits,
    Init,
    NackReason,
    Slot,
    TimeReply,
)

log = logging.getLogger(__name__)

VERSION = protocol.__version__  #: in the PING banner

__all__ = [
    "COMBINATION_TIMEOUT",
    "MAX_DARK_WINDOWS",
    "RESULT_PART",
    "Device",
    "FrameUnavailable",
    "SlotHandler",
    "SolveContext",
    "Solver",
    "default_slots",
]


class Device:
    """The emulated tracker at NSP ``address``. ``store`` persists slots (``SlotStore``);
    ``slots`` maps slot numbers to :class:`SlotHandler`, replacing the :func:`default_slots`
    handler of each slot it names; ``solver`` runs GO sequences;
    ``frame_source(ctx)``, if given, captures the frame for each sequence (returning None when it
    has none, raising :class:`FrameUnavailable` for one it cannot read); a frame committed to slot 1
    since the last GO takes precedence, and without a source the last committed frame is reused.
    ``quaternion_order`` orders the standard result structure's quaternions unless the slot-2
    parameter set names an order (docs/ICD.md section 10.2). ``fault_injection`` lets FAULT arm
    scripted faults (docs/ICD.md section 13; off: FAULT is NACKed NOT_SUPPORTED); ``faults``
    holds the armed ones and their counters. ``clock_model`` says how the device clock (TIME) is
    wrong; ``clock_source`` is what it counts (monotonic s); ``clock`` gives POSIX UTC seconds
    (the sky's time, ``ext.utc_epoch``). ``injected`` reads the image buffers (GO bit INJECTED)."""

    def __init__(
        self,
        address: int = nsp.DEVICE_ADDRESS,
        *,
        store: SlotStore | None = None,
        slots: Mapping[int, SlotHandler] | None = None,
        solver: Solver | None = None,
        frame_source: Callable[[SolveContext], Any] | None = None,
        sensor_shape: tuple[int, int] = (2464, 3280),
        clock: Callable[[], float] = time.time,
        quaternion_order: result.QuaternionOrder = result.QuaternionOrder.SCALAR_FIRST,
        fault_injection: bool = False,
        clock_model: ClockModel = ClockModel(),
        clock_source: Callable[[], float] = time.monotonic,
        injected: InjectedFormat = InjectedFormat(),
    ):
        if not 0 <= address <= 0xFF:
            raise ValueError("address must be 0..255")
        self.address = address
        self.solver = solver
        self.frame_source = frame_source
        self.sensor_shape = sensor_shape
        self.clock = clock
        self.quaternion_order = quaternion_order
        self.fault_injection = fault_injection
        self.device_clock = DeviceClock(clock_model, clock_source)
        self.injected_format = injected
        self._rx_at: float | None = None  #: clock-source time the frame being handled ended (its last FEND)
        self.faults = FaultInjector(self._words)
        self.sleep: Callable[[float], None] = time.sleep  #: how a delayed reply waits (s)
        self._reset_now = False  #: a loaded ``reset now``: reset once the FAULT reply is built
        self.counters = Counters()
        self._mode = Mode()
        self._lock = threading.RLock()
        self._decoder = slip.Decoder(nsp.MAX_MESSAGE)
        #: ``late_reply(frames)``: how a transport takes replies produced after :meth:`receive`
        #: returned (a COMBINATION's, once its sequence is done); None answers synchronously
        self.late_reply: Callable[[list[bytes]], None] | None = None
        self.transfers = Transfers(store, slots)
        self.housekeeping = Housekeeping(self.device_clock.seconds)
        self.runner = SequenceRunner(self._lock, self._mode, self.transfers, self)
        self.memory = Memory(
            Supervisor(
                address=address,
                banner=self.boot_banner,
                app_mode=lambda: self._mode.app,
                busy=lambda: self.runner.busy,
                result_ready=lambda: self.runner.result_ready,
                sequence=lambda: self.runner.sequence,
                counters=lambda: self.counters,
                result=lambda: self.runner.result,
                analog=self.housekeeping.analog_frame,
                fault_counters=lambda: self.faults.counters,
                boot_message=lambda: self.runner.boot_message,
            ),
            self.faults,
        )
        root = self.transfers.store.root
        #: maintenance mode and the FLASH command on the NAND (docs/ICD.md section 15)
        self.maintenance = Maintenance(
            Nand(None if root is None else root / "nand"),
            self._lock,
            self.memory.crc,
            lambda offset, length: bytes(self.memory._ram[offset : offset + length]),  # SRAM: the RAM region
            self._fp_message,
        )
        self.housekeeping.flash_errors = self.maintenance.nand.error_counts
        self.faults.flash = self.maintenance.apply_fault
        self.dispatcher = Dispatcher(
            self._handlers(),
            self._lock,
            lambda: self.counters,
            lambda: self.late_reply,
            self._frames,
            failure_state=lambda: int(self.runner.state),
        )
        self.transfers.activate_stored()
        self.maintenance.store_catalog(self.store.active(Slot.CATALOG))

    def _handlers(self) -> dict[int, Handler]:
        """The handler of every command-table code."""
        mem, tr, seq = self.memory, self.transfers, self.runner
        return {
            Code.PING: self._ping,
            Code.INIT: self._init,
            Code.PEEK: mem.peek,
            Code.POKE: mem.poke,
            Code.DIAGNOSTIC: self._diagnostic,
            Code.CRC: lambda data: self.maintenance.crc_or_flash(self.in_maintenance, data),
            Code.READ_FILE: mem.read_file,
            Code.WRITE_FILE: mem.write_file,
            Code.READ_EDAC: mem.read_edac,
            Code.WRITE_EDAC: mem.write_edac,
            Code.GO: self._go,
            Code.READ_RESULT: seq.read_result,
            Code.IMAGE: seq.image,
            Code.COMBINATION: self._combination,
            Code.TIME: self._time,
            Code.XFER_BEGIN: tr.xfer_begin,
            Code.XFER_DATA: tr.xfer_data,
            Code.XFER_STATUS: tr.xfer_status,
            Code.XFER_COMMIT: tr.xfer_commit,
            Code.SLOT_INFO: tr.slot_info,
            Code.XFER_ABORT: tr.xfer_abort,
            Code.FAULT: self._fault,
        }

    # ------------------------------------------------------------------ state

    @property
    def store(self) -> SlotStore:
        return self.transfers.store

    @property
    def slots(self) -> dict[int, SlotHandler]:
        return self.transfers.slots

    @property
    def _objects(self) -> dict[int, Any]:
        """The activated object of each slot."""
        return self.transfers.objects

    @property
    def app_mode(self) -> bool:
        return self._mode.app

    @app_mode.setter
    def app_mode(self, value: bool) -> None:
        self._mode.app = value

    @property
    def in_maintenance(self) -> bool:
        """Maintenance mode: entered by INIT MAINTENANCE_ADDRESS in bootloader mode, left when the
        application starts (INIT 0x2000, a GO that boots) or on a reset (docs/ICD.md section 15)."""
        return self.maintenance.entered and not self._mode.app

    def _from_nand(self, go_code: int) -> None:
        """A GO or COMBINATION that boots the functional processor reads the NAND first: its boot
        block and application image (docs/ICD.md section 15); Refused when they cannot be read."""
        if not self._mode.app and go_code & GoBits.LOAD_NAND and not self.runner.booting:
            self.maintenance.boot_check()

    def _go(self, req: Go) -> Any:
        self._from_nand(req.code)
        self._catalog_reads(req.code)
        return self.runner.go(req)

    def _combination(self, req: Combination) -> Any:
        self._from_nand(req.go_code)
        self._catalog_reads(req.go_code)
        return self.runner.combination(req)

    def _catalog_reads(self, go_code: int) -> None:
        """A sequence reads the catalog's tables from the NAND (docs/ICD.md section 15)."""
        if go_code & GoBits.COMMAND and not self.runner.busy:
            self.maintenance.read_catalog()

    def _fp_message(self, text: str) -> None:
        """A functional processor message into EDAC (0x00C0), where the boot message goes."""
        self.runner.boot_message = text

    @property
    def boot_banner(self) -> str:
        return f"ST16-EMU BOOTLOADER {VERSION} addr=0x{self.address:02X}"

    def app_banner(self) -> str:
        state = "BUSY" if self.busy else "IDLE"
        return f"ST16-EMU APPLICATION {VERSION} {state}"

    @property
    def busy(self) -> bool:
        return self.runner.busy

    def edac_image(self) -> bytes:
        """The 512 EDAC bytes as READ EDAC sees them now (:data:`protocol.edac.EDAC_DTYPE`)."""
        return self.memory.edac_image()

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until no sequence runs; False on timeout."""
        return self.runner.wait_idle(timeout)

    def drop_delayed(self) -> None:
        """Drop the delayed replies still waiting (serving stops): they are never sent."""
        self.faults.delayed.drop()

    def close(self) -> None:
        """Close the solver's index-building process, if it has one."""
        close = getattr(self.solver, "close", None)
        if close is not None:
            close()

    # ------------------------------------------------------------------ byte level

    def receive(self, chunk: bytes, arrived: float | None = None) -> list[bytes]:
        """Feed received bytes; return the SLIP frames to transmit, in order. ``arrived`` is when
        the chunk's last byte arrived on the line (the clock source's time: a paced link's UART
        time); None: now."""
        out: list[bytes] = []
        for event in self._decoder.feed(chunk):
            if isinstance(event, slip.FramingError):
                self.counters.framing += 1
            elif isinstance(event, slip.Oversize):
                self.counters.oversize += 1
            else:
                self._rx_at = self.device_clock.source() if arrived is None else arrived
                out.extend(self._frames(self.receive_frame(event.data)))
        return out

    def _frames(self, replies: list[nsp.Message], late: Callable[[list[bytes]], None] | None = None) -> list[bytes]:
        """The frames of one command's ``replies`` as the scripted reply faults leave them:
        dropped, the last one's CRC corrupted, or held back. A delayed reply is queued
        (``faults.delayed``) and handed later to ``late`` (the callback of the session that sent
        the command; None: the transport's now, :attr:`late_reply`), the link serving on
        meanwhile, unless FAULT clear, a reset or the device stopping drops it first; without a
        transport the call waits (:attr:`sleep`) and returns them."""
        if not replies:
            return []
        fault = self.faults.reply(replies[0].code)
        if fault.drop:
            self._unsent(self.counters, len(replies))
            return []
        frames = [m.frame() for m in replies]
        if fault.corrupt:
            raw = replies[-1].encode()
            frames[-1] = slip.encode(raw[:-2] + bytes([raw[-2] ^ 0xFF, raw[-1] ^ 0xFF]))
        if fault.delay_s > 0:
            send = late or self.late_reply
            if send is None:
                self.sleep(fault.delay_s)
                return frames
            counted, n = self.counters, len(replies)
            if not self.faults.delayed.add(fault.delay_s, lambda: send(frames), lambda: self._unsent(counted, n)):
                self.faults.count("dropped_replies")  # the queue is full: dropped, as drop_reply would
                self._unsent(counted, n)
            return []
        return frames

    def _unsent(self, counted: Counters, n: int) -> None:
        """``n`` reply messages counted in ``counted`` were not sent after all: the link counter
        counts what was sent. Counters a reset or DIAGNOSTIC has replaced since hold nothing of
        them (and a counter never goes below zero)."""
        with self._lock:
            if counted is self.counters:
                counted.replies = max(0, counted.replies - n)

    def receive_frame(self, raw: bytes) -> list[nsp.Message]:
        """Handle one unescaped frame: count runts / bad CRCs addressed to us, ignore others."""
        try:
            msg = nsp.decode(raw)
        except nsp.Runt:
            if raw and raw[0] == self.address:
                self.counters.runt += 1
            return []
        except nsp.BadCrc:
            if raw[0] == self.address:
                self.counters.bad_crc += 1
            return []
        if msg.dst != self.address:
            self.counters.other_address += 1
            return []
        return self.handle(msg)

    def handle(self, msg: nsp.Message) -> list[nsp.Message]:
        """Execute a command addressed to us; return its reply messages ([] when Poll = 0, or
        when a scripted reset takes the device first)."""
        if self.faults.reset_before(msg.code):
            self.reset()
            return []
        catalog = self.store.active(Slot.CATALOG)
        replies = self.dispatcher.handle(msg)
        if self.store.active(Slot.CATALOG) is not catalog:  # a new image rewrote every catalog word
            self.faults.written("catalog")
            self.maintenance.store_catalog(self.store.active(Slot.CATALOG))  # and the NAND's copy
        if self.faults.reset_after(msg.code) or self._reset_now:
            self._reset_now = False
            self.reset()
        return replies

    # ------------------------------------------------------------------ scripted faults

    def reset(self) -> None:
        """A scripted reset: back to bootloader mode, the result cleared to NO_RESULT, the link
        counters, scratch and RAM as after a restart; slots and the fault counters kept. What was
        in flight is lost: no reply is sent to a command received before it (a COMBINATION
        waiting for its sequence, a delayed reply)."""
        with self._lock:
            self.dispatcher.generation += 1
            self.faults.delayed.drop()
            self._mode.app = False
            self.counters = Counters()
            self.runner.reset()
            self.memory.reset()
            self.maintenance.reset()
            self.device_clock.power_on()
            self.faults.count("resets")
        log.info("device: scripted reset")

    def _words(self, region: str) -> int:
        """4-byte words of ``region`` (an ``edac_upset`` picks among them)."""
        if region == "catalog":
            return len(self.store.active(Slot.CATALOG) or b"") // 4
        return WORDS[region]

    def arm(self, faults: tuple[Fault, ...]) -> int:
        """Arm ``faults`` (``faults.parse_script``) in place of the armed ones; the number armed.
        A ``reset now`` among them resets the device at once."""
        if self.faults.load(faults):
            self.reset()
        return self.faults.armed

    def _fault(self, data: bytes) -> bytes:
        if not self.fault_injection:
            raise Refused(NackReason.NOT_SUPPORTED, "fault injection is off; start st16-device with --fault-injection")
        req = FaultRequest.unpack(data)
        if req.action == FaultAction.LOAD:
            try:
                faults = parse_script(req.script.decode("utf-8"), "fault script")
            except UnicodeDecodeError as exc:
                raise Refused(NackReason.BAD_PARAMETER, f"fault script is not UTF-8: {exc}") from None
            except FaultScriptError as exc:
                raise Refused(NackReason.BAD_PARAMETER, str(exc)) from None
            self._reset_now = self.faults.load(faults)
        elif req.action not in (FaultAction.CLEAR, FaultAction.STATUS):
            raise Refused(NackReason.BAD_PARAMETER, f"unknown FAULT subcommand {req.action}: 0 load, 1 clear, 2 status")
        elif req.script:
            raise Refused(NackReason.BAD_LENGTH, f"FAULT {FaultAction(req.action).name.lower()} takes no script")
        elif req.action == FaultAction.CLEAR:
            self.faults.clear()
        counters = tuple(self.faults.counters[name] for name in edac.FAULT_COUNTERS)
        return FaultStatus(req.action, self.faults.armed, counters).pack()

    # ------------------------------------------------------------------ identity and counters

    def arrival(self) -> float:
        """When the command being handled arrived: its final FEND (the clock source's time)."""
        return self.device_clock.source() if self._rx_at is None else self._rx_at

    def injected(self, pixels: Any) -> Frame:
        """The frame of an image buffer (GO bit INJECTED), in :attr:`injected_format`."""
        f = self.injected_format
        return Frame(pixels, pattern=f.pattern, black_level=f.black_level, white_level=f.white_level)

    def _time(self, data: bytes) -> bytes:
        """TIME: the device clock latched when this command's final FEND arrived."""
        if data:
            raise Refused(
                NackReason.BAD_LENGTH,
                f"TIME takes no data field, got {len(data)} bytes (XFER BEGIN, once 0x13, is 0x{Code.XFER_BEGIN:02X})",
            )
        return TimeReply(self.device_clock.latch(self._rx_at)).pack()

    def _ping(self, data: bytes) -> bytes:
        if data:
            raise Refused(NackReason.BAD_LENGTH, "PING takes no data")
        if self.in_maintenance:
            return f"ST16-EMU MAINTENANCE {VERSION} addr=0x{self.address:02X}".encode()
        return (self.app_banner() if self.app_mode else self.boot_banner).encode()

    def _init(self, req: Init) -> bytes:
        if self.app_mode:
            raise Refused(NackReason.WRONG_MODE, "INIT is a bootloader command; the application is running")
        if req.address == MAINTENANCE_ADDRESS:  # ours: the functional processor's maintenance program
            self.maintenance.entered = True
            return b""
        if req.address != APP_START_ADDRESS:
            raise Refused(NackReason.BAD_ADDRESS, f"no application image at 0x{req.address:08X}")
        self.app_mode = True
        return b""

    def _diagnostic(self, req: DiagnosticRequest) -> bytes:
        if req.flags & ~0x01:
            raise Refused(NackReason.BAD_PARAMETER, f"unknown DIAGNOSTIC flags 0x{req.flags:02X}")
        out = self.counters.snapshot().pack()
        if req.flags & 0x01:
            self.counters = Counters()
        return out
