"""The emulated tracker's link shell: bytes in, framed replies out (docs/ICD.md).

:class:`Device` owns the supervisor state (boot/application mode, 512-byte EDAC memory, error and
command counters), a bounded PEEK/POKE memory map, the result structure, the transfer slots and
the GO sequence. It does no I/O of its own: a transport (``firmware_model.device.link``) feeds received
bytes to :meth:`Device.receive` and writes back the frames it returns. A GO sequence runs the
pluggable ``solver`` in a worker thread; the device keeps answering meanwhile. A COMBINATION that
waits for its sequence answers through :attr:`Device.late_reply` when the transport sets it (the
link keeps being served meanwhile), else the call returns only when the sequence is done.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

import protocol
from firmware_model.device.slots import SlotStore
from protocol import edac, nsp, result, slip
from protocol.commands import (
    APP_START_ADDRESS,
    MAX_SLOT_BYTES,
    MAX_STATUS_RANGES,
    UNASSIGNED,
    AddressedBytes,
    Code,
    Combination,
    CrcReply,
    CrcRequest,
    DarkWindow,
    Diagnostics,
    Go,
    GoBits,
    Init,
    MemorySpace,
    NackInfo,
    NackReason,
    PayloadError,
    Peek,
    Poke,
    ReadFile,
    ReadRange,
    Slot,
    SlotImage,
    SlotRejected,
    SlotRequest,
    WriteAck,
    WriteEdac,
    WriteFile,
    XferBegin,
    XferData,
    XferDataAck,
    XferState,
    XferStatus,
)
from protocol.crc import crc16_mcrf4xx, crc32

log = logging.getLogger(__name__)

VERSION = protocol.__version__  #: in the PING banner
EDAC_SIZE = edac.SIZE
EDAC_SCRATCH = edac.SCRATCH  #: writable user scratch [start, end)
RESULT_PART = 1024  #: result bytes per message of a multi-part reply (ours)
MAX_PEEK = 1024
MAX_CRC_SPAN = 1 << 20
MAX_DARK_WINDOWS = 32  #: per image buffer
COMBINATION_TIMEOUT = 60.0  #: seconds COMBINATION waits for its sequence


class FrameUnavailable(Exception):
    """Raised by a frame source for a frame it cannot deliver (unreadable file, wrong size)."""


#: Emulated "asynchronous analog frame" at EDAC 0x0004 (8 x f32): nominal constants, the emulator
#: models no electronics. Current (A), bus, Vdd core, Vdd MPU, Vdd IO (V), supervisor temperature
#: (deg C), Vdd supervisor, Vdd detector (V).
ANALOG_FRAME = (0.25, 5.0, 1.2, 1.8, 3.3, 20.0, 3.3, 2.8)

# Memory map for PEEK/POKE (ours): name -> (base, size, writable)
ROM_BASE, ROM_SIZE = 0x00000000, 0x2000
RAM_BASE, RAM_SIZE = 0x20000000, 0x10000
RESULT_BASE = 0x40000000


@dataclass
class SlotHandler:
    """How a slot checks and installs a committed image.

    ``validate(data)`` raises :class:`~protocol.commands.SlotRejected` (code >= 0x0100, message)
    for an unacceptable image; ``activate(data)`` returns the installed object the solver sees;
    ``info(data, obj)`` returns the SLOT INFO blob (bytes).
    """

    validate: Callable[[bytes], None]
    activate: Callable[[bytes], Any] = bytes
    info: Callable[[bytes, Any], bytes] = lambda data, obj: b""


def _reject_empty(data: bytes) -> None:
    if not data:
        raise SlotRejected(0x0100, "empty image")


def _params_validate(data: bytes) -> None:
    try:
        obj = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise SlotRejected(0x0101, f"parameter set is not UTF-8 JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise SlotRejected(0x0102, "parameter set must be a JSON object")


def default_slots() -> dict[int, SlotHandler]:
    """Handlers used until the real catalog/frame validators are plugged in: slots 0 and 1 accept
    any non-empty image (kept as bytes); slot 2 accepts a JSON object (activated as a dict)."""

    def blob(data, obj):
        return json.dumps({"length": len(data)}).encode()

    return {
        Slot.CATALOG: SlotHandler(_reject_empty, bytes, blob),
        Slot.FRAME: SlotHandler(_reject_empty, bytes, blob),
        Slot.PARAMS: SlotHandler(
            _params_validate,
            lambda d: json.loads(d.decode("utf-8")),
            lambda d, obj: json.dumps({"keys": sorted(obj)}).encode(),
        ),
    }


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


#: ``solver(ctx) -> {result field path: value}``; must set ``"return_code"``.
Solver = Callable[[SolveContext], Mapping[str, Any]]


@dataclass(frozen=True)
class _Pending:
    """A command's reply that is ready only later: ``wait()`` returns its payload parts (with the
    device lock held; it may wait on the sequence condition, which releases the lock)."""

    wait: Callable[[], list[bytes]]


class _Nack(Exception):
    def __init__(self, reason: int, text: str):
        super().__init__(text)
        self.reason = int(reason)
        self.text = text


@dataclass
class Counters:
    framing: int = 0
    runt: int = 0
    oversize: int = 0
    bad_crc: int = 0
    fifo_overflow: int = 0
    accepted: int = 0
    nacked: int = 0
    silent: int = 0
    other_address: int = 0
    replies: int = 0
    per_code: list[int] = field(default_factory=lambda: [0] * 32)

    def snapshot(self) -> Diagnostics:
        """The DIAGNOSTIC reply of these counters (fields matched by name)."""
        return Diagnostics(**{**asdict(self), "per_code": tuple(self.per_code)})


class Device:
    """The emulated tracker at NSP ``address``. ``store`` persists slots (``SlotStore``);
    ``slots`` maps slot numbers to :class:`SlotHandler`, replacing the :func:`default_slots`
    handler of each slot it names; ``solver`` runs GO sequences;
    ``frame_source(ctx)``, if given, captures the frame for each sequence (returning None when it
    has none, raising :class:`FrameUnavailable` for one it cannot read); a frame committed to slot 1
    since the last GO takes precedence, and without a source the last committed frame is reused."""

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
    ):
        if not 0 <= address <= 0xFF:
            raise ValueError("address must be 0..255")
        self.address = address
        self.store = store if store is not None else SlotStore(None)
        self.slots = {**default_slots(), **(slots or {})}
        self.solver = solver
        self.frame_source = frame_source
        self.sensor_shape = sensor_shape
        self.clock = clock
        self.counters = Counters()
        self.app_mode = False
        self._lock = threading.RLock()
        self._decoder = slip.Decoder(nsp.MAX_MESSAGE)
        self._scratch = bytearray(EDAC_SCRATCH[1] - EDAC_SCRATCH[0])
        self._ram = bytearray(RAM_SIZE)
        self._rom = bytearray(ROM_SIZE)
        self._rom[: len(self.boot_banner)] = self.boot_banner.encode()
        self._result = result.build({"return_code": result.make_return_code(result.Status.NO_RESULT)}, 0)
        self._result_ready = False
        self._sequence = 0
        self._busy: threading.Thread | None = None
        self._done = threading.Condition(self._lock)
        self._dark: dict[int, list[DarkWindow]] = {0: [], 1: []}
        self._objects: dict[int, Any] = {}
        self._frame_pending = False
        #: ``late_reply(frames)``: how a transport takes replies produced after :meth:`receive`
        #: returned (a COMBINATION's, once its sequence is done); None answers synchronously
        self.late_reply: Callable[[list[bytes]], None] | None = None
        for slot in self.store.active_slots():
            data = self.store.active(slot)
            if slot not in self.slots:
                log.warning("device: slot %d in the state directory is not a slot of this device; ignored", slot)
                continue
            try:
                self._install(slot, data)
            except Exception as exc:  # a persisted image the current validator refuses
                log.warning("device: slot %d image not activated at start: %s", slot, " ".join(str(exc).split()))

    # ------------------------------------------------------------------ identity

    @property
    def boot_banner(self) -> str:
        return f"ST16-EMU BOOTLOADER {VERSION} addr=0x{self.address:02X}"

    def app_banner(self) -> str:
        state = "BUSY" if self.busy else "IDLE"
        return f"ST16-EMU APPLICATION {VERSION} {state}"

    @property
    def busy(self) -> bool:
        return self._busy is not None

    # ------------------------------------------------------------------ byte level

    def receive(self, chunk: bytes) -> list[bytes]:
        """Feed received bytes; return the SLIP frames to transmit, in order."""
        out: list[bytes] = []
        for event in self._decoder.feed(chunk):
            if isinstance(event, slip.FramingError):
                self.counters.framing += 1
            elif isinstance(event, slip.Oversize):
                self.counters.oversize += 1
            else:
                out.extend(m.frame() for m in self.receive_frame(event.data))
        return out

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

    # ------------------------------------------------------------------ message level

    def handle(self, msg: nsp.Message) -> list[nsp.Message]:
        """Execute a command addressed to us; return its reply messages ([] when Poll = 0)."""
        with self._lock:
            self.counters.accepted += 1
            self.counters.per_code[msg.code] += 1
            replies = self._replies(msg, lambda: self._dispatch(msg))
            if isinstance(replies, _Pending):
                if self.late_reply is None:  # no transport to answer later: wait here
                    replies = self._replies(msg, replies.wait)
                else:
                    threading.Thread(
                        target=self._answer_late, args=(msg, replies), daemon=True, name=f"reply-{msg.code:02X}"
                    ).start()
                    return []
            return self._count_replies(msg, replies)

    def _replies(self, msg: nsp.Message, run: Callable[[], Any]):
        """Reply messages to ``msg`` from ``run()`` (its payload parts), a NACK for an expected
        refusal or a bug, or the :class:`_Pending` that ``run`` returned."""
        try:
            parts = run()
            if isinstance(parts, _Pending):
                return parts
            return [nsp.reply_to(msg, data, ack=True, final=(i == len(parts) - 1)) for i, data in enumerate(parts)]
        except (_Nack, PayloadError) as exc:
            self.counters.nacked += 1
            reason = exc.reason
            text = exc.text if isinstance(exc, _Nack) else exc.message
            return [nsp.reply_to(msg, NackInfo(reason, text).pack(), ack=False)]
        except Exception as exc:  # never crash the link on a bug: NACK and report
            log.exception("device: bug while handling a command or sequence")
            self.counters.nacked += 1
            return [nsp.reply_to(msg, NackInfo(NackReason.INTERNAL, repr(exc)).pack(), ack=False)]

    def _count_replies(self, msg: nsp.Message, replies: list[nsp.Message]) -> list[nsp.Message]:
        if not msg.poll:
            self.counters.silent += 1
            return []
        self.counters.replies += len(replies)
        return replies

    def _answer_late(self, msg: nsp.Message, pending: _Pending) -> None:
        """Wait for ``pending`` (the lock is released while waiting) and hand its replies to
        :attr:`late_reply`."""
        with self._lock:
            replies = self._count_replies(msg, self._replies(msg, pending.wait))
        if replies and self.late_reply is not None:
            self.late_reply([m.frame() for m in replies])

    def _dispatch(self, msg: nsp.Message) -> list[bytes] | _Pending:
        code = msg.code
        if code in UNASSIGNED:
            raise _Nack(NackReason.UNKNOWN_COMMAND, f"command code 0x{code:02X} is not assigned")
        handler = getattr(self, f"_cmd_{Code(code).name.lower()}")
        parts = handler(msg.data)
        return parts if isinstance(parts, (list, _Pending)) else [parts]

    def _require_app(self, what: str) -> None:
        if not self.app_mode:
            raise _Nack(NackReason.WRONG_MODE, f"{what} needs application mode (send INIT 0x{APP_START_ADDRESS:08X})")

    # ------------------------------------------------------------------ ST-16 commands

    def _cmd_ping(self, data: bytes) -> bytes:
        if data:
            raise _Nack(NackReason.BAD_LENGTH, "PING takes no data")
        return (self.app_banner() if self.app_mode else self.boot_banner).encode()

    def _cmd_init(self, data: bytes) -> bytes:
        req = Init.unpack(data)
        if self.app_mode:
            raise _Nack(NackReason.WRONG_MODE, "INIT is a bootloader command; the application is running")
        if req.address != APP_START_ADDRESS:
            raise _Nack(NackReason.BAD_ADDRESS, f"no application image at 0x{req.address:08X}")
        self.app_mode = True
        return b""

    def _region(self, address: int, count: int, write: bool) -> tuple[bytearray | bytes, int]:
        regions = ((ROM_BASE, self._rom, False), (RAM_BASE, self._ram, True), (RESULT_BASE, self._result, False))
        for base, buf, writable in regions:
            if base <= address and address + count <= base + len(buf):
                if write and not writable:
                    raise _Nack(NackReason.READ_ONLY, f"0x{address:08X} is read-only")
                return buf, address - base
        raise _Nack(NackReason.BAD_ADDRESS, f"0x{address:08X}+{count} is outside the memory map")

    def _cmd_peek(self, data: bytes) -> bytes:
        req = Peek.unpack(data)
        if not 1 <= req.count <= MAX_PEEK:
            raise _Nack(NackReason.BAD_LENGTH, f"PEEK count {req.count} outside 1..{MAX_PEEK}")
        buf, off = self._region(req.address, req.count, write=False)
        return AddressedBytes(req.address, bytes(buf[off : off + req.count]), 4).pack()

    def _cmd_poke(self, data: bytes) -> bytes:
        req = Poke.unpack(data)
        buf, off = self._region(req.address, len(req.data), write=True)
        buf[off : off + len(req.data)] = req.data
        return WriteAck(req.address, len(req.data), 4).pack()

    def _cmd_diagnostic(self, data: bytes) -> bytes:
        if len(data) > 1:
            raise _Nack(NackReason.BAD_LENGTH, "DIAGNOSTIC takes 0 or 1 data byte")
        flags = data[0] if data else 0
        if flags & ~0x01:
            raise _Nack(NackReason.BAD_PARAMETER, f"unknown DIAGNOSTIC flags 0x{flags:02X}")
        out = self.counters.snapshot().pack()
        if flags & 0x01:
            self.counters = Counters()
        return out

    def _space(self, space: int) -> bytes:
        if space == MemorySpace.EDAC:
            return self.edac_image()
        if space == MemorySpace.RESULT:
            return self._result
        raise _Nack(NackReason.BAD_PARAMETER, f"unknown address space {space}")

    def _cmd_crc(self, data: bytes) -> bytes:
        req = CrcRequest.unpack(data)
        if not 1 <= req.length <= MAX_CRC_SPAN:
            raise _Nack(NackReason.BAD_LENGTH, f"CRC length {req.length} outside 1..{MAX_CRC_SPAN}")
        if req.space == MemorySpace.MEMORY:
            buf, off = self._region(req.address, req.length, write=False)
            span = bytes(buf[off : off + req.length])
        else:
            whole = self._space(req.space)
            if req.address + req.length > len(whole):
                raise _Nack(NackReason.BAD_ADDRESS, f"0x{req.address:X}+{req.length} beyond {len(whole)} bytes")
            span = whole[req.address : req.address + req.length]
        return CrcReply(req.space, req.address, req.length, crc16_mcrf4xx(span)).pack()

    def edac_image(self) -> bytes:
        """The 512 EDAC bytes as READ EDAC sees them now (:data:`protocol.edac.EDAC_DTYPE`)."""
        rec = np.zeros((), edac.EDAC_DTYPE)
        ready = self._result_ready
        rec["status"] = (
            (edac.STATUS_APP_MODE if self.app_mode else 0)
            | (edac.STATUS_BUSY if self.busy else 0)
            | (edac.STATUS_RESULT_READY if ready else 0)
        )
        rec["analog"] = ANALOG_FRAME
        for name in edac.COUNTERS:
            rec[name] = getattr(self.counters, name)
        rec["result_length"] = result.STANDARD_LENGTH if ready else 0
        rec["total_length"] = result.TOTAL_LENGTH if ready else 0
        rec["sequence"], rec["address"] = self._sequence, self.address
        rec["app_mode"], rec["busy"] = int(self.app_mode), int(self.busy)
        rec["banner"] = self.boot_banner.encode()[:64]
        rec["scratch"] = np.frombuffer(bytes(self._scratch), np.uint8)
        return rec.tobytes()

    def _edac_read(self, address: int, count: int) -> bytes:
        if count < 1 or address + count > EDAC_SIZE:
            raise _Nack(NackReason.BAD_ADDRESS, f"EDAC 0x{address:04X}+{count} outside 0x0000-0x01FF")
        return self.edac_image()[address : address + count]

    def _edac_write(self, address: int, value: bytes) -> None:
        lo, hi = EDAC_SCRATCH
        if address + len(value) > EDAC_SIZE:
            raise _Nack(NackReason.BAD_ADDRESS, f"EDAC 0x{address:04X}+{len(value)} outside 0x0000-0x01FF")
        if address < lo:
            raise _Nack(NackReason.READ_ONLY, f"EDAC 0x{address:04X} is read-only (scratch is 0x0100-0x01FF)")
        self._scratch[address - lo : address - lo + len(value)] = value

    def _cmd_read_edac(self, data: bytes) -> bytes:
        req = ReadRange.unpack(data)
        return AddressedBytes(req.address, self._edac_read(req.address, req.count)).pack()

    def _cmd_write_edac(self, data: bytes) -> bytes:
        req = WriteEdac.unpack(data)
        self._edac_write(req.address, req.data)
        return WriteAck(req.address, len(req.data)).pack()

    def _file_address(self, address: int) -> None:
        if address % 4 or address + 4 > EDAC_SIZE:
            raise _Nack(NackReason.BAD_ADDRESS, f"file address 0x{address:04X} is not a 4-byte EDAC word")

    def _cmd_read_file(self, data: bytes) -> bytes:
        req = ReadFile.unpack(data)
        self._file_address(req.address)
        return data + self._edac_read(req.address, 4)

    def _cmd_write_file(self, data: bytes) -> bytes:
        req = WriteFile.unpack(data)
        self._file_address(req.address)
        self._edac_write(req.address, req.value)
        return data

    def _cmd_go(self, data: bytes) -> bytes:
        req = Go.unpack(data)
        self._go(req.code)
        return bytes([req.code])

    def _go(self, code: int) -> None:
        if code & ~0x3F:
            raise _Nack(NackReason.BAD_PARAMETER, f"unknown GO bits 0x{code & ~0x3F:02X}")
        if code & GoBits.TEST:
            raise _Nack(NackReason.NOT_SUPPORTED, "the self-test sequence (GO bit 0x10) is not emulated")
        if not self.app_mode:
            if not code & GoBits.LOAD_NAND:
                raise _Nack(NackReason.WRONG_MODE, "GO without LOAD_NAND (0x02) needs application mode")
            self.app_mode = True
        if code & GoBits.COMMAND:
            if self.busy:
                raise _Nack(NackReason.BUSY, f"sequence {self._sequence + 1} still running")
            self._start_sequence(code)

    def _cmd_read_result(self, data: bytes) -> list[bytes]:
        req = ReadRange.unpack(data)
        self._require_app("READ RESULT")
        if req.count < 1 or req.address + req.count > result.TOTAL_LENGTH:
            raise _Nack(
                NackReason.BAD_ADDRESS, f"result 0x{req.address:04X}+{req.count} outside 0..{result.TOTAL_LENGTH}"
            )
        return self._result_parts(req.address, req.count)

    def _result_parts(self, address: int, count: int) -> list[bytes]:
        parts = []
        for start in range(address, address + count, RESULT_PART):
            n = min(RESULT_PART, address + count - start)
            parts.append(AddressedBytes(start, self._result[start : start + n]).pack())
        return parts

    def _cmd_image(self, data: bytes) -> bytes:
        self._require_app("IMAGE")
        if not data:
            raise _Nack(NackReason.BAD_LENGTH, "IMAGE needs a subcommand byte")
        if data[0] == 1:
            raise _Nack(NackReason.NOT_SUPPORTED, "Rectangular Poke (IMAGE subcommand 1) is not emulated")
        if data[0] != DarkWindow.SUBCOMMAND:
            raise _Nack(NackReason.BAD_PARAMETER, f"IMAGE subcommand {data[0]} is reserved")
        win = DarkWindow.unpack(data)
        rows, cols = self.sensor_shape
        if win.buffer not in self._dark:
            raise _Nack(NackReason.BAD_PARAMETER, f"image buffer {win.buffer} not 0 or 1")
        if win.rows < 1 or win.cols < 1 or win.row + win.rows > rows or win.col + win.cols > cols:
            raise _Nack(NackReason.OUT_OF_RANGE, f"window outside the {rows}x{cols} sensor")
        if len(self._dark[win.buffer]) >= MAX_DARK_WINDOWS:
            raise _Nack(NackReason.TOO_LARGE, f"buffer {win.buffer} already has {MAX_DARK_WINDOWS} dark windows")
        self._dark[win.buffer].append(win)
        return data

    def _cmd_combination(self, data: bytes) -> list[bytes] | _Pending:
        req = Combination.unpack(data)
        if req.mask & result.SELF_TEST_SECTION:
            raise _Nack(NackReason.NOT_SUPPORTED, "the self-test result section (0x0800) is not emulated")
        unknown = req.mask & ~sum(result.SECTIONS)
        if unknown:
            raise _Nack(NackReason.BAD_PARAMETER, f"unknown section bits 0x{unknown:X}")
        self._go(req.go_code)
        if req.go_code & GoBits.COMMAND:
            return _Pending(lambda: self._combination_parts(req.mask, time.monotonic() + COMBINATION_TIMEOUT))
        return self._combination_parts(req.mask, None)

    def _combination_parts(self, mask: int, deadline: float | None) -> list[bytes]:
        """The result sections of ``mask``, once the running sequence is done (by ``deadline``,
        monotonic s; None: at once). Call with the lock held."""
        while deadline is not None and self.busy:
            if not self._done.wait(timeout=max(0.0, deadline - time.monotonic())):
                raise _Nack(NackReason.BUSY, "sequence did not complete in time")
        parts: list[bytes] = []
        for bit, (address, length) in sorted(result.SECTIONS.items()):
            if mask & bit:
                parts.extend(self._result_parts(address, length))
        return parts or [b""]

    # ------------------------------------------------------------------ GO sequence

    def _start_sequence(self, code: int) -> None:
        self._sequence += 1
        self._result_ready = False
        ctx = SolveContext(
            go_code=code,
            sequence=self._sequence,
            started=self.clock(),
            catalog=self._objects.get(Slot.CATALOG),
            frame=self._objects.get(Slot.FRAME),
            params=self._objects.get(Slot.PARAMS),
            catalog_crc32=crc32(self.store.active(0) or b""),
            frame_crc32=crc32(self.store.active(1) or b""),
            dark_windows=tuple(self._dark[0] + self._dark[1]),
            sensor_shape=self.sensor_shape,
        )
        uploaded, self._frame_pending = self._frame_pending, False
        self._busy = threading.Thread(
            target=self._run_sequence, args=(ctx, uploaded), name=f"sequence-{ctx.sequence}", daemon=True
        )
        self._busy.start()

    def _sequence_fields(self, ctx: SolveContext, uploaded: bool) -> Mapping[str, Any]:
        base = {"epoch": ctx.started, "ext.catalog_crc32": ctx.catalog_crc32}

        def status(st: result.Status, reason: str) -> dict:
            return {
                **base,
                "return_code": result.make_return_code(st),
                "ext.reason": reason.encode()[: result.EXT_REASON_BYTES],
            }

        if ctx.catalog is None:
            return status(result.Status.NO_CATALOG, "no catalog: upload one to slot 0")
        if self.frame_source is not None and not uploaded:
            try:
                frame = self.frame_source(ctx)
            except FrameUnavailable as exc:
                return status(result.Status.BAD_FRAME, str(exc))
            if frame is None:
                return status(result.Status.NO_FRAME, "the capture source has no more frames")
            ctx = SolveContext(**{**ctx.__dict__, "frame": frame, "frame_crc32": 0})
        if ctx.frame is None:
            return status(result.Status.NO_FRAME, "no frame: no capture source and none uploaded to slot 1")
        base["ext.frame_crc32"] = ctx.frame_crc32
        if self.solver is None:
            return {**base, "return_code": result.make_return_code(result.Status.NO_SOLVER)}
        t0 = time.perf_counter()
        fields = dict(self.solver(ctx))
        if "ext.reason" in fields and isinstance(fields["ext.reason"], str):
            fields["ext.reason"] = fields["ext.reason"].encode()[: result.EXT_REASON_BYTES]
        if "return_code" not in fields:
            raise ValueError("solver returned no return_code")
        fields.setdefault("ext.solve_time", time.perf_counter() - t0)
        return {**base, **fields}

    def _run_sequence(self, ctx: SolveContext, uploaded: bool) -> None:
        try:
            data = result.build(self._sequence_fields(ctx, uploaded), ctx.sequence)
        except Exception as exc:
            log.exception("device: bug while handling a command or sequence")
            data = result.build(
                {
                    "epoch": ctx.started,
                    "return_code": result.make_return_code(result.Status.SOLVER_ERROR),
                    "ext.reason": f"{type(exc).__name__}: {exc}".encode()[: result.EXT_REASON_BYTES],
                },
                ctx.sequence,
            )
        with self._lock:
            self._result = data
            self._result_ready = True
            self._busy = None
            self._done.notify_all()
        if log.isEnabledFor(logging.INFO):
            rc = int(result.parse(data)["return_code"])
            log.info("device: sequence %d done: %s", ctx.sequence, result.status_of(rc).name)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until no sequence runs; False on timeout."""
        with self._lock:
            return self._done.wait_for(lambda: not self.busy, timeout)

    # ------------------------------------------------------------------ slots and transfers (ours)

    def _handler(self, slot: int) -> SlotHandler:
        if slot not in self.slots:
            raise _Nack(NackReason.BAD_SLOT, f"no slot {slot} (slots: {sorted(self.slots)})")
        return self.slots[slot]

    def _install(self, slot: int, data: bytes) -> None:
        handler = self.slots[slot]
        handler.validate(data)
        self._objects[slot] = handler.activate(data)
        log.info("device: slot %d: image of %d bytes activated", slot, len(data))

    def _status(self, slot: int) -> XferStatus:
        tr = self.store.transfer(slot)
        if tr is None:
            return XferStatus(slot, XferState.NONE)
        missing = tr.missing()
        state = XferState.COMPLETE if tr.complete else XferState.RECEIVING
        return XferStatus(
            slot,
            state,
            tr.length,
            tr.crc32,
            tr.contiguous,
            tr.received,
            len(missing),
            tuple(missing[:MAX_STATUS_RANGES]),
        )

    def _cmd_xfer_begin(self, data: bytes) -> bytes:
        req = XferBegin.unpack(data)
        self._handler(req.slot)
        if not 1 <= req.length <= MAX_SLOT_BYTES:
            raise _Nack(NackReason.TOO_LARGE, f"length {req.length} outside 1..{MAX_SLOT_BYTES}")
        try:
            self.store.begin(req.slot, req.length, req.crc32)
        except OSError as exc:
            raise _Nack(NackReason.STORAGE_ERROR, str(exc)) from None
        return self._status(req.slot).pack()

    def _cmd_xfer_data(self, data: bytes) -> bytes:
        req = XferData.unpack(data)
        self._handler(req.slot)
        tr = self.store.transfer(req.slot)
        if tr is None:
            raise _Nack(NackReason.NO_TRANSFER, f"no transfer in progress for slot {req.slot} (send BEGIN)")
        if req.offset + len(req.data) > tr.length:
            raise _Nack(NackReason.OUT_OF_RANGE, f"bytes {req.offset}+{len(req.data)} beyond length {tr.length}")
        try:
            tr = self.store.write(req.slot, req.offset, req.data)
        except OSError as exc:
            raise _Nack(NackReason.STORAGE_ERROR, str(exc)) from None
        return XferDataAck(req.slot, tr.contiguous).pack()

    def _cmd_xfer_status(self, data: bytes) -> bytes:
        req = SlotRequest.unpack(data)
        self._handler(req.slot)
        return self._status(req.slot).pack()

    def _cmd_xfer_abort(self, data: bytes) -> bytes:
        req = SlotRequest.unpack(data)
        self._handler(req.slot)
        self.store.drop_transfer(req.slot)
        return self._status(req.slot).pack()

    def _cmd_xfer_commit(self, data: bytes) -> bytes:
        req = SlotRequest.unpack(data)
        handler = self._handler(req.slot)
        tr = self.store.transfer(req.slot)
        if tr is None:
            raise _Nack(NackReason.NO_TRANSFER, f"no transfer in progress for slot {req.slot}")
        if not tr.complete:
            raise _Nack(NackReason.INCOMPLETE, f"{tr.length - tr.received} of {tr.length} bytes missing")
        try:
            image = self.store.transfer_bytes(req.slot)
        except OSError as exc:
            raise _Nack(NackReason.STORAGE_ERROR, str(exc)) from None
        if len(image) != tr.length or crc32(image) != tr.crc32:
            self.store.drop_transfer(req.slot)
            raise _Nack(
                NackReason.CRC_MISMATCH,
                f"image CRC-32 0x{crc32(image):08X} != announced 0x{tr.crc32:08X}; transfer discarded",
            )
        try:
            handler.validate(image)
            obj = handler.activate(image)
        except SlotRejected as exc:
            self.store.drop_transfer(req.slot)
            raise _Nack(exc.code, exc.message) from None
        except Exception as exc:
            self.store.drop_transfer(req.slot)
            raise _Nack(NackReason.BAD_PARAMETER, f"slot {req.slot} image refused: {exc}") from None
        try:
            self.store.set_active(req.slot, image)
        except OSError as exc:
            raise _Nack(NackReason.STORAGE_ERROR, str(exc)) from None
        self._objects[req.slot] = obj
        if req.slot == Slot.FRAME:  # consumed by the next GO before the capture source
            self._frame_pending = True
        self.store.drop_transfer(req.slot)
        return SlotImage(req.slot, True, len(image), crc32(image)).pack()

    def _cmd_slot_info(self, data: bytes) -> bytes:
        req = SlotRequest.unpack(data)
        handler = self._handler(req.slot)
        image = self.store.active(req.slot)
        if image is None or req.slot not in self._objects:
            return SlotImage(req.slot, False, 0, 0).pack()
        blob = bytes(handler.info(image, self._objects[req.slot]))[: nsp.MAX_DATA - 10]
        return SlotImage(req.slot, True, len(image), crc32(image), blob).pack()
