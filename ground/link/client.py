"""Ground-side NSP client over any pyserial URL (pty path, /dev/tty*, socket://host:port, loop://).

Every transaction toggles the B bit and only accepts a reply that carries the same B bit, the
device as source, us as destination and the command's code, so a late reply to an earlier
command is never taken for the current one. Before its first command a client drains the line
until it has been quiet for :data:`SYNC_QUIET` s (a reply still on its way to a previous,
killed client is dropped there), and before every command it drops what is waiting; both drains
are bounded (:data:`SYNC_BOUND`, :data:`READ_SLICE`), whatever the peer sends. Line noise, damaged frames and replies to
other commands are read past: the exchange goes on until its own reply or its deadline, and
only then reports the damage seen (:class:`MalformedReply`) or the silence (:class:`ReplyTimeout`).
Idempotent reads are retried on timeouts and malformed replies. NACKs raise :class:`Nack`. Each
error carries the raw bytes received (the first :data:`MAX_RAW` of them).
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import serial
from tqdm import tqdm

from ground.link.exchange_log import ExchangeLog, code_name
from protocol import edac, nsp, result, slip
from protocol.command_table import COMMANDS
from protocol.commands import (
    APP_START_ADDRESS,
    GO_OPERATIONAL,
    MAX_FAULT_SCRIPT,
    MAX_POKE_PIXELS,
    UPLOAD_CHUNK,
    AddressedBytes,
    Code,
    Combination,
    CombinationFailure,
    CrcReply,
    CrcRequest,
    DarkWindow,
    DiagnosticRequest,
    Diagnostics,
    FaultAction,
    FaultRequest,
    FaultStatus,
    Go,
    Init,
    NackInfo,
    PayloadError,
    Peek,
    Poke,
    ReadFile,
    ReadRange,
    RectangularPoke,
    SlotImage,
    SlotRequest,
    TimeReply,
    WriteAck,
    WriteEdac,
    WriteFile,
    XferBegin,
    XferData,
    XferDataAck,
    XferState,
    XferStatus,
)
from protocol.crc import crc32
from protocol.layout import Layout

_TermiosError: type[Exception]
try:
    import termios

    _TermiosError = termios.error
except ImportError:  # pragma: no cover - not POSIX
    _TermiosError = OSError

_PORT_ERRORS = (serial.SerialException, OSError, _TermiosError)
READ_SLICE = 0.02  #: seconds one port read may block
SYNC_QUIET = 0.05  #: seconds of silence that end the drain before a client's first command
SYNC_BOUND = 0.25  #: seconds that drain may last at most (a peer that never stops sending)
MAX_RAW = 65536  #: received bytes kept per exchange for error reports

_T = TypeVar("_T")


class LinkError(Exception):
    """Base of the client's errors; ``raw`` is every byte received during the failed exchange."""

    def __init__(self, message: str, raw: bytes = b""):
        super().__init__(message)
        self.raw = bytes(raw)


class Nack(LinkError):
    """The device answered with ACK clear; ``reason`` (u16) and ``text`` come from its data."""

    def __init__(self, code: int, info: NackInfo, raw: bytes):
        super().__init__(f"{code_name(code)} NACKed: {info.reason_name} (0x{info.reason:04X}) {info.text}", raw)
        self.code = code
        self.reason = info.reason
        self.text = info.text


class SequenceFailed(Nack):
    """COMBINATION's failure reply (docs/ICD.md section 7): ``state`` the sequence state
    (:class:`~protocol.commands.SequenceState`) and ``text``; it carries no reason code (``reason`` 0)."""

    def __init__(self, failure: CombinationFailure, raw: bytes):
        LinkError.__init__(self, f"COMBINATION failed: sequence {failure.state_name}: {failure.text}", raw)
        self.code = Code.COMBINATION
        self.reason = 0
        self.text = failure.text
        self.state = failure.state


def refusal(code: int, data: bytes, raw: bytes) -> Nack:
    """The error of a reply with ACK clear: the command's own failure layout when the command table
    gives it one (COMBINATION), else our NACK."""
    spec = COMMANDS.get(code)
    if spec is not None and spec.failure is not None:
        return SequenceFailed(spec.failure.unpack(data), raw)
    return Nack(code, NackInfo.unpack(data), raw)


class ReplyTimeout(LinkError):
    """No complete reply in time."""


class MalformedReply(LinkError):
    """A reply that is garbled (bad CRC, runt, bad escape) or inconsistent with the command."""


class LinkDown(LinkError):
    """The port itself failed (device process gone, cable unplugged): pyserial's error text."""


@dataclass(frozen=True)
class UploadReport:
    slot: int
    length: int
    crc32: int
    resumed_from: int  #: bytes already on the device when the upload started
    sent: int  #: payload bytes sent by this call
    seconds: float


class Client:
    """NSP client; use as a context manager. ``log`` is a JSONL path or an :class:`ExchangeLog`."""

    def __init__(
        self,
        url: str,
        device_address: int = nsp.DEVICE_ADDRESS,
        host_address: int = nsp.HOST_ADDRESS,
        timeout: float = 1.0,
        log: str | Path | ExchangeLog | None = None,
        retries: int = 2,
        baudrate: int = 115200,
    ):
        self.url = url
        self.device_address = device_address
        self.host_address = host_address
        self.timeout = timeout
        self.retries = retries
        self._own_log = isinstance(log, (str, Path))
        self.log = (
            ExchangeLog(log) if isinstance(log, (str, Path)) else log
        )  # first: a log that fails leaves no port open
        # Reads wait at most READ_SLICE so the reply deadline is checked without reconfiguring the port.
        try:
            self._ser = serial.serial_for_url(
                url, baudrate=baudrate, timeout=READ_SLICE, write_timeout=max(timeout, 5.0)
            )
        except BaseException:
            if self._own_log and self.log is not None:
                self.log.close()
            raise
        self._b = False
        self._synced = False  #: the line has been drained once (before the first command)
        self.stale_replies = 0  #: replies discarded because their B bit belonged to an earlier command
        self.discarded = 0  #: bytes dropped by the drains before commands
        self.bad_crcs = 0  #: frames addressed to us whose CRC did not check (read past, never accepted)
        self.last_exchange: tuple[bytes, bytes] = (b"", b"")  #: (sent frame, bytes received) of the last command

    def close(self) -> None:
        self._ser.close()
        if self._own_log and self.log is not None:
            self.log.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ transactions

    def transact(
        self, code: int, data: bytes = b"", *, poll: bool = True, timeout: float | None = None, idempotent: bool = False
    ) -> list[nsp.Message]:
        """Send a command; return its reply messages (all ACKed, last one Final); [] if not polled."""
        attempts = 1 + (self.retries if idempotent else 0)
        for attempt in range(attempts):
            try:
                return self._exchange(code, data, poll, self.timeout if timeout is None else timeout)
            except (ReplyTimeout, MalformedReply):
                if attempt == attempts - 1:
                    raise
        raise AssertionError("unreachable")

    def write_raw(self, data: bytes) -> None:
        """Put bytes on the line unchanged (fault injection, console ``raw``); logged as ``tx``."""
        self._ser.write(bytes(data))
        if self.log:
            self.log.record("tx", bytes(data), "raw")

    def read_raw(self, duration: float) -> bytes:
        """Everything that arrives within ``duration`` seconds."""
        out = bytearray()
        deadline = time.monotonic() + duration
        while time.monotonic() < deadline:
            out += self._ser.read(max(1, self._ser.in_waiting))
        return bytes(out)

    def send_silent(self, code: int, data: bytes = b"") -> None:
        """Send with Poll = 0: the device executes without replying."""
        self._exchange(code, data, False, 0.0)

    def _exchange(self, code: int, data: bytes, poll: bool, timeout: float) -> list[nsp.Message]:
        if not self._ser.is_open:  # pyserial would fail with a TypeError on the closed descriptor
            raise LinkDown(f"{code_name(code)}: port {self.url} is closed")
        try:
            return self._exchange_once(code, data, poll, timeout)
        except _PORT_ERRORS as exc:
            raise LinkDown(f"{code_name(code)}: port {self.url} failed: {exc}", self.last_exchange[1]) from exc

    def _discard(self, quiet: float, bound: float) -> None:
        """Drop input until none has arrived for ``quiet`` s (0: just what is waiting now), for
        at most ``bound`` s. Bounded, unlike pyserial's ``socket://`` flush, which reads as long
        as the peer sends."""
        start = last = time.monotonic()
        while True:
            now = time.monotonic()
            if now - start >= bound or (now - last >= quiet and not self._ser.in_waiting):
                return
            chunk = (
                self._ser.read(self._ser.in_waiting)
                if self._ser.in_waiting
                else (self._ser.read(1) if quiet > 0 else b"")
            )
            if chunk:
                self.discarded += len(chunk)
                last = time.monotonic()

    def _exchange_once(self, code: int, data: bytes, poll: bool, timeout: float) -> list[nsp.Message]:
        if not self._synced:
            self._discard(SYNC_QUIET, min(max(timeout, SYNC_QUIET), SYNC_BOUND))
            self._synced = True
        else:
            self._discard(0.0, READ_SLICE)
        self._b = not self._b
        msg = nsp.command(self.device_address, self.host_address, code, data, poll=poll, b=self._b)
        self._ser.write(msg.frame())
        self.last_exchange = (msg.frame(), b"")
        if self.log:
            self.log.record("tx", msg.encode())
        if not poll:
            return []
        decoder = slip.Decoder(nsp.MAX_MESSAGE)
        received = bytearray()
        parts: list[nsp.Message] = []
        damage: list[str] = []  # what was read past: noise, damaged frames, replies to other commands
        damage_before = 0  # len(damage) when the first part arrived
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                got = f"; {len(parts)} part(s) received before the Final one" if parts else ""
                if damage:
                    raise MalformedReply(
                        f"{code_name(code)}: no valid reply within {timeout:.3f} s{got}; "
                        f"read past {len(damage)} bad frame(s), first: {damage[0]}",
                        bytes(received),
                    )
                raise ReplyTimeout(f"{code_name(code)}: no reply within {timeout:.3f} s{got}", bytes(received))
            chunk = self._ser.read(max(1, self._ser.in_waiting))
            if not chunk:
                continue
            if len(received) < MAX_RAW:
                received += chunk[: MAX_RAW - len(received)]
            self.last_exchange = (self.last_exchange[0], bytes(received))
            for event in decoder.feed(chunk):
                reply = self._accept(event, code, damage)
                if reply is None:
                    continue
                if not reply.ack:
                    raise refusal(code, reply.data, bytes(received))
                if parts and len(damage) > damage_before:  # a part of this reply may be among them
                    raise MalformedReply(
                        f"{code_name(code)}: a frame was damaged inside the multi-part reply: {damage[-1]}",
                        bytes(received),
                    )
                if not parts:
                    damage_before = len(damage)  # noise before the first part is harmless
                parts.append(reply)
                if reply.final:
                    return parts

    def _accept(self, event, code: int, damage: list[str]) -> nsp.Message | None:
        """The reply ``event`` holds if it is this command's; else None, noting damage in ``damage``."""
        if isinstance(event, (slip.FramingError, slip.Oversize)):
            damage.append(event.reason if isinstance(event, slip.FramingError) else "oversize frame")
            return None
        try:
            reply = nsp.decode(event.data)
        except nsp.MessageError as exc:
            if event.data[:1] == bytes([self.host_address]):
                self.bad_crcs += isinstance(exc, nsp.BadCrc)
                if self.log:
                    self.log.record("rx", event.data)
            damage.append(str(exc))
            return None
        if reply.dst != self.host_address or reply.src != self.device_address:
            return None  # another node's traffic (or our own echo on loop://)
        stale = reply.b != self._b
        other = not stale and reply.code != code
        if self.log:
            note = (
                "stale: B bit of an earlier command"
                if stale
                else f"ignored: a reply to code 0x{reply.code:02X}"
                if other
                else None
            )
            self.log.record("rx", event.data, note)
        if stale:
            self.stale_replies += 1
            return None
        if other:
            damage.append(f"reply carries code 0x{reply.code:02X}")
            return None
        return reply

    def _parse(self, code: int, data: bytes, parser: Callable[..., _T], *args: Any) -> _T:
        try:
            return parser(data, *args)
        except PayloadError as exc:
            raise MalformedReply(f"{code_name(code)}: {exc}", data) from None

    def _request(self, code: Code, request: Layout | None, **kw: Any) -> list[nsp.Message]:
        """The reply messages to ``request``, a payload of the command table's request type of
        ``code`` (None: no data field); retried when the table says it may be (``idempotent``
        given overrides)."""
        spec = COMMANDS[code]
        if not (request is None if spec.request is None else type(request) in spec.requests):
            raise TypeError(f"{code_name(code)} takes {spec.request}, not {type(request)}")
        kw.setdefault("idempotent", spec.idempotent)
        return self.transact(code, request.pack() if request is not None else b"", **kw)

    def _send(self, code: Code, request: Layout | None, **kw: Any) -> bytes:
        """The data of the single reply message to ``request`` (see :meth:`_request`)."""
        parts = self._request(code, request, **kw)
        if len(parts) != 1:
            raise MalformedReply(
                f"{code_name(code)}: {len(parts)} reply messages, expected 1", b"".join(p.encode() for p in parts)
            )
        return parts[0].data

    def _reply(self, code: Code, data: bytes, *args: Any) -> Any:
        """``data`` parsed as the command table's reply type of ``code``."""
        reply = COMMANDS[code].reply
        assert reply is not None
        return self._parse(code, data, reply.unpack, *args)

    def _call(self, code: Code, request: Layout | None, *args: Any, **kw: Any) -> Any:
        """Send ``request`` and parse the reply (``args`` go to the reply parser)."""
        return self._reply(code, self._send(code, request, **kw), *args)

    # ------------------------------------------------------------------ ST-16 commands

    def ping(self) -> str:
        """Identification banner (differs between bootloader and application)."""
        return self._send(Code.PING, None).decode("ascii", "replace")

    def init(self, addr: int = APP_START_ADDRESS) -> None:
        """Start the application at ``addr`` (0x00002000)."""
        self._send(Code.INIT, Init(addr), timeout=max(self.timeout, 3.0))

    def peek(self, address: int, count: int) -> bytes:
        data = self._send(Code.PEEK, Peek(address, count))
        reply: AddressedBytes = self._reply(Code.PEEK, data, 4)
        self._check_echo(Code.PEEK, reply.address, address, len(reply.data), count, data)
        return reply.data

    def poke(self, address: int, data: bytes) -> int:
        raw = self._send(Code.POKE, Poke(address, data))
        ack: WriteAck = self._reply(Code.POKE, raw, 4)
        self._check_echo(Code.POKE, ack.address, address, ack.count, len(data), raw)
        return ack.count

    def diagnostic(self, clear: bool = False) -> Diagnostics:
        """Error counters and command counts; ``clear`` resets them after reading."""
        request = DiagnosticRequest.clearing(clear)
        return self._call(Code.DIAGNOSTIC, request, idempotent=not clear)  # a clearing read is not repeated

    def crc(self, space: int, address: int, length: int) -> int:
        """CRC-16/MCRF4XX of a device memory span (space: 0 EDAC, 1 memory map, 2 result)."""
        reply: CrcReply = self._call(Code.CRC, CrcRequest(space, address, length))
        return reply.crc

    def read_file(self, address: int, long: bool = False) -> bytes:
        """Four EDAC bytes at ``address`` (short form sends the file index ``address // 4``)."""
        req = ReadFile(address, long)
        data = self._send(Code.READ_FILE, req)
        head = req.pack()
        try:
            reply: WriteFile | None = self._reply(Code.READ_FILE, data)
        except MalformedReply:
            reply = None
        if reply is None or ReadFile(reply.address, reply.long).pack() != head:
            raise MalformedReply(f"READ_FILE: reply {data.hex()} does not echo {head.hex()} + 4 bytes", data)
        return reply.value

    def write_file(self, address: int, value: bytes, long: bool = False) -> None:
        if len(value) != 4:
            raise ValueError("WRITE FILE writes exactly 4 bytes")
        req = WriteFile(address, value, long)
        data = self._send(Code.WRITE_FILE, req)
        if data != req.pack():
            raise MalformedReply(f"WRITE_FILE: reply {data.hex()} does not echo the command", data)

    def read_edac(self, address: int, count: int) -> bytes:
        """EDAC bytes; the short form is used for up to 256 bytes, the long form beyond."""
        data = self._send(Code.READ_EDAC, ReadRange(address, count, long=count > 256))
        reply: AddressedBytes = self._reply(Code.READ_EDAC, data)
        self._check_echo(Code.READ_EDAC, reply.address, address, len(reply.data), count, data)
        return reply.data

    def write_edac(self, address: int, data: bytes) -> int:
        raw = self._send(Code.WRITE_EDAC, WriteEdac(address, data))
        ack: WriteAck = self._reply(Code.WRITE_EDAC, raw)
        self._check_echo(Code.WRITE_EDAC, ack.address, address, ack.count, len(data), raw)
        return ack.count

    def go(self, code: int = GO_OPERATIONAL) -> int:
        data = self._send(Code.GO, Go(code))
        if data[:1] != bytes([code]):
            raise MalformedReply(f"GO: reply {data.hex()} does not echo the go code", data)
        return data[0]

    def result_length(self) -> int:
        """EDAC 0x004C: 2616 when a result is ready, 0 while a sequence runs."""
        return struct.unpack("<I", self.read_edac(edac.RESULT_LENGTH, 4))[0]

    def read_result(self, address: int = 0, count: int = result.TOTAL_LENGTH) -> bytes:
        """Result bytes [address, address+count), assembled from the Final-flagged parts."""
        parts = self._request(Code.READ_RESULT, ReadRange(address, count, long=True))
        return self._assemble(Code.READ_RESULT, parts, address, count)

    def read_result_record(self) -> np.ndarray:
        """The whole result structure, parsed (``protocol.result.RESULT`` record)."""
        return result.parse(self.read_result(0, result.TOTAL_LENGTH))

    def go_and_wait(self, code: int = GO_OPERATIONAL, timeout: float = 30.0, interval: float = 0.02) -> np.ndarray:
        """GO, poll the result length until the sequence has finished, return the parsed result."""
        self.go(code)
        deadline = time.monotonic() + timeout
        while self.result_length() == 0:
            if time.monotonic() > deadline:
                raise ReplyTimeout(f"result not ready within {timeout} s after GO 0x{code:02X}")
            time.sleep(interval)
        return self.read_result_record()

    def combination(self, go_code: int, mask: int, timeout: float = 30.0, mask_bytes: int = 4) -> dict[int, bytes]:
        """COMBINATION: returns {result address: bytes} of every requested section. The reply
        (ICD page 1-35918) is the sections in increasing address order as one stream, each message
        ``u16 bytes already transmitted`` + its bytes: joined by that count, then split by ``mask``."""
        parts = self._request(Code.COMBINATION, Combination(go_code, mask, mask_bytes), timeout=timeout)
        stream = b""
        for part in parts:
            if len(part.data) < 2:
                raise MalformedReply("COMBINATION: a reply message without its u16 byte count", part.data)
            sent = int.from_bytes(part.data[:2], "little")
            if sent != len(stream):
                raise MalformedReply(
                    f"COMBINATION: a message says {sent} bytes already transmitted, {len(stream)} were", part.data
                )
            stream += part.data[2:]
        sections = sorted(section for bit, section in result.SECTIONS.items() if mask & bit)
        if len(stream) != sum(length for _, length in sections):
            raise MalformedReply(
                f"COMBINATION: {len(stream)} result bytes for mask 0x{mask:X}, "
                f"its sections hold {sum(length for _, length in sections)}",
                stream[:64],
            )
        out: dict[int, bytes] = {}
        for address, length in sections:
            out[address], stream = stream[:length], stream[length:]
        return out

    def time(self) -> int:
        """TIME: the device clock, microseconds (latched when the command's last FEND arrived)."""
        reply: TimeReply = self._call(Code.TIME, None)
        return reply.micros

    def poke_image(self, buffer: int, row: int, col: int, pixels: np.ndarray) -> None:
        """IMAGE Rectangular Poke of a 2-D array of pixel values (u16) at (row, col) of ``buffer``,
        split into as many pokes as the data field needs (rows of at most MAX_POKE_PIXELS)."""
        values = np.asarray(pixels)
        if values.ndim != 2 or values.size == 0 or values.min() < 0 or values.max() > 0xFFFF:
            raise ValueError("poke pixels must be a non-empty 2-D array of values 0..65535")
        rows_per = max(1, MAX_POKE_PIXELS // values.shape[1])
        for start in range(0, values.shape[0], rows_per):
            block = values[start : start + rows_per]
            for c0 in range(0, block.shape[1], MAX_POKE_PIXELS):
                piece = np.ascontiguousarray(block[:, c0 : c0 + MAX_POKE_PIXELS], "<u2")
                poke = RectangularPoke(buffer, row + start, col + c0, piece.shape[0], piece.shape[1], piece.tobytes())
                data = self._send(Code.IMAGE, poke)
                if data != poke.head():
                    raise MalformedReply("IMAGE: reply does not echo the rectangular poke's head", data)

    def dark_window(self, window: DarkWindow) -> None:
        data = self._send(Code.IMAGE, window)
        if data != window.pack():
            raise MalformedReply("IMAGE: reply does not echo the dark-window command", data)

    # ------------------------------------------------------------------ transfers (extension)

    def xfer_begin(self, slot: int, length: int, crc: int) -> XferStatus:
        return self._call(Code.XFER_BEGIN, XferBegin(slot, length, crc))

    def xfer_data(self, slot: int, offset: int, chunk: bytes, poll: bool = True) -> int | None:
        """Send bytes at ``offset``; returns the contiguous byte count (None when not polled)."""
        request = XferData(slot, offset, chunk)
        if not poll:
            self.send_silent(Code.XFER_DATA, request.pack())
            return None
        ack: XferDataAck = self._call(Code.XFER_DATA, request)
        return ack.contiguous

    def xfer_status(self, slot: int) -> XferStatus:
        return self._call(Code.XFER_STATUS, SlotRequest(slot))

    def xfer_commit(self, slot: int, timeout: float = 30.0) -> SlotImage:
        return self._call(Code.XFER_COMMIT, SlotRequest(slot), timeout=timeout)

    def xfer_abort(self, slot: int) -> XferStatus:
        return self._call(Code.XFER_ABORT, SlotRequest(slot))

    def slot_info(self, slot: int) -> SlotImage:
        return self._call(Code.SLOT_INFO, SlotRequest(slot))

    def upload(
        self, slot: int, data: bytes, progress: bool = True, chunk: int = UPLOAD_CHUNK, commit: bool = True
    ) -> UploadReport:
        """Upload ``data`` into ``slot``, resuming whatever the device already holds of the same
        image (same length and CRC-32), then COMMIT (raises :class:`Nack` if the device refuses)."""
        t0 = time.monotonic()
        data = bytes(data)
        crc = crc32(data)
        status = self.xfer_begin(slot, len(data), crc)
        resumed, sent = status.received, 0
        with tqdm(
            total=len(data), initial=resumed, unit="B", unit_scale=True, disable=not progress, desc=f"slot {slot}"
        ) as bar:
            while status.state != XferState.COMPLETE:
                if not status.missing:
                    raise MalformedReply(f"slot {slot}: transfer incomplete but no missing range reported")
                for offset, length in status.missing:
                    for start in range(offset, offset + length, chunk):
                        piece = data[start : min(start + chunk, offset + length)]
                        self.xfer_data(slot, start, piece)
                        sent += len(piece)
                        bar.update(len(piece))
                status = self.xfer_status(slot)
                if status.length != len(data) or status.crc32 != crc:
                    raise MalformedReply(f"slot {slot}: device now holds a different transfer")
        if commit:
            self.xfer_commit(slot)
        return UploadReport(slot, len(data), crc, resumed, sent, time.monotonic() - t0)

    # ------------------------------------------------------------------ scripted faults (extension)

    def fault(self, action: FaultAction, script: str = "") -> FaultStatus:
        """FAULT (docs/ICD.md section 13): ``load`` the fault ``script`` text (replacing the armed
        one), ``clear`` or ``status``; the reply holds the faults armed and the fault counters.
        The device NACKs it NOT_SUPPORTED unless started with ``--fault-injection``."""
        data = script.encode("utf-8")
        if len(data) > MAX_FAULT_SCRIPT:
            raise ValueError(f"fault script of {len(data)} bytes: one FAULT load carries at most {MAX_FAULT_SCRIPT}")
        idempotent = action == FaultAction.STATUS
        return self._call(Code.FAULT, FaultRequest(action, data), idempotent=idempotent)

    # ------------------------------------------------------------------ helpers

    def _check_echo(self, code, got_addr, want_addr, got_n, want_n, raw) -> None:
        if got_addr != want_addr or got_n != want_n:
            raise MalformedReply(
                f"{code_name(code)}: reply for 0x{got_addr:X}+{got_n}, asked 0x{want_addr:X}+{want_n}", raw
            )

    def _assemble(self, code: int, parts: list[nsp.Message], address: int, count: int) -> bytes:
        buf = bytearray(count)
        covered = 0
        for part in parts:
            piece = self._parse(code, part.data, AddressedBytes.unpack)
            lo = piece.address - address
            if lo < 0 or lo + len(piece.data) > count:
                raise MalformedReply(f"{code_name(code)}: part at 0x{piece.address:X} outside the request", part.data)
            buf[lo : lo + len(piece.data)] = piece.data
            covered += len(piece.data)
        if covered != count:
            raise MalformedReply(
                f"{code_name(code)}: parts cover {covered} of {count} bytes", b"".join(p.encode() for p in parts)
            )
        return bytes(buf)
