"""The device's memories: the 512-byte EDAC memory (a view of the supervisor state plus the user
scratch) and the PEEK/POKE memory map (boot ROM, RAM, the result structure), with the commands
that read and write them: PEEK, POKE, READ/WRITE EDAC, READ/WRITE FILE and CRC."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from firmware_model.device.dispatch import Counters, Refused
from firmware_model.device.faults import FaultInjector
from protocol import edac, result
from protocol.commands import (
    AddressedBytes,
    CrcReply,
    CrcRequest,
    MemorySpace,
    NackReason,
    Peek,
    Poke,
    ReadFile,
    ReadRange,
    WriteAck,
    WriteEdac,
    WriteFile,
)
from protocol.crc import crc16_mcrf4xx

EDAC_SIZE = edac.SIZE
EDAC_SCRATCH = edac.SCRATCH  #: writable user scratch [start, end)
MAX_PEEK = 1024
MAX_CRC_SPAN = 1 << 20


# Memory map for PEEK/POKE (ours): name -> (base, size, writable)
ROM_BASE, ROM_SIZE = 0x00000000, 0x2000
RAM_BASE, RAM_SIZE = 0x20000000, 0x10000
RESULT_BASE = 0x40000000


@dataclass(frozen=True)
class Supervisor:
    """What the EDAC memory shows of the rest of the device, read when it is read."""

    address: int
    banner: str
    app_mode: Callable[[], bool]
    busy: Callable[[], bool]
    result_ready: Callable[[], bool]
    sequence: Callable[[], int]
    counters: Callable[[], Counters]
    result: Callable[[], bytes]  #: the result structure now
    analog: Callable[[], tuple[float, ...]]  #: the analog frame now (``housekeeping``)
    fault_counters: Callable[[], Mapping[str, int]] = dict  #: the scripted faults' counters now
    boot_message: Callable[[], str] = str  #: the functional processor's last boot message (ASCII)


#: 4-byte words of each region an ``edac_upset`` may strike, but the catalog (its image's)
WORDS = {"scratch": (EDAC_SCRATCH[1] - EDAC_SCRATCH[0]) // 4, "ram": RAM_SIZE // 4, "result": result.TOTAL_LENGTH // 4}


class Memory:
    """EDAC memory and the memory map of one device; ``faults`` is told of every read and write
    of the scratch, the RAM and the result (its EDAC upsets: corrected, or a NACK)."""

    def __init__(self, state: Supervisor, faults: FaultInjector | None = None):
        self.state = state
        self.faults = faults if faults is not None else FaultInjector()
        self._scratch = bytearray(EDAC_SCRATCH[1] - EDAC_SCRATCH[0])
        self._ram = bytearray(RAM_SIZE)
        self._rom = bytearray(ROM_SIZE)
        self._rom[: len(state.banner)] = state.banner.encode()

    def reset(self) -> None:
        """Scratch and RAM zeroed, as at start (a scripted reset)."""
        self._scratch[:] = bytes(len(self._scratch))
        self._ram[:] = bytes(len(self._ram))
        self.faults.written("scratch")
        self.faults.written("ram")

    # ------------------------------------------------------------------ EDAC

    def edac_image(self) -> bytes:
        """The 512 EDAC bytes as READ EDAC sees them now (:data:`protocol.edac.EDAC_DTYPE`)."""
        st = self.state
        rec = np.zeros((), edac.EDAC_DTYPE)
        ready, busy, app_mode, counters = st.result_ready(), st.busy(), st.app_mode(), st.counters()
        rec["status"] = (
            (edac.STATUS_APP_MODE if app_mode else 0)
            | (edac.STATUS_BUSY if busy else 0)
            | (edac.STATUS_RESULT_READY if ready else 0)
        )
        rec["analog"] = st.analog()
        for name in edac.COUNTERS:
            rec[name] = getattr(counters, name)
        rec["result_length"] = result.STANDARD_LENGTH if ready else 0
        rec["total_length"] = result.TOTAL_LENGTH if ready else 0
        rec["sequence"], rec["address"] = st.sequence(), st.address
        rec["app_mode"], rec["busy"] = int(app_mode), int(busy)
        rec["banner"] = st.banner.encode()[:64]
        for name, value in st.fault_counters().items():
            rec[name] = value
        rec["boot_message"] = st.boot_message().encode("ascii", "replace")[:64]
        rec["scratch"] = np.frombuffer(bytes(self._scratch), np.uint8)
        return rec.tobytes()

    def _scratch_read(self, address: int, count: int) -> None:
        """Tell the faults of a read of EDAC [address, address + count) where it covers scratch."""
        lo, hi = EDAC_SCRATCH
        start, end = max(address, lo), min(address + count, hi)
        if start < end:
            self.faults.read("scratch", start - lo, end - start)

    def _edac_read(self, address: int, count: int) -> bytes:
        if count < 1 or address + count > EDAC_SIZE:
            raise Refused(NackReason.BAD_ADDRESS, f"EDAC 0x{address:04X}+{count} outside 0x0000-0x01FF")
        self._scratch_read(address, count)
        return self.edac_image()[address : address + count]

    def _edac_write(self, address: int, value: bytes) -> None:
        lo, hi = EDAC_SCRATCH
        if address + len(value) > EDAC_SIZE:
            raise Refused(NackReason.BAD_ADDRESS, f"EDAC 0x{address:04X}+{len(value)} outside 0x0000-0x01FF")
        if address < lo:
            raise Refused(NackReason.READ_ONLY, f"EDAC 0x{address:04X} is read-only (scratch is 0x0100-0x01FF)")
        self._scratch[address - lo : address - lo + len(value)] = value
        self.faults.written("scratch", address - lo, len(value))

    def read_edac(self, req: ReadRange) -> bytes:
        return AddressedBytes(req.address, self._edac_read(req.address, req.count)).pack()

    def write_edac(self, req: WriteEdac) -> bytes:
        self._edac_write(req.address, req.data)
        return WriteAck(req.address, len(req.data)).pack()

    @staticmethod
    def _file_address(address: int) -> None:
        if address % 4 or address + 4 > EDAC_SIZE:
            raise Refused(
                NackReason.BAD_ADDRESS,
                f"file index 0x{address // 4:X} (EDAC 0x{address:04X}) outside the {EDAC_SIZE // 4} words of EDAC",
            )

    def read_file(self, req: ReadFile) -> bytes:
        self._file_address(req.address)
        return WriteFile(req.address, self._edac_read(req.address, 4), req.long).pack()

    def write_file(self, req: WriteFile) -> bytes:
        self._file_address(req.address)
        self._edac_write(req.address, req.value)
        return req.pack()

    # ------------------------------------------------------------------ memory map

    def _region(self, address: int, count: int, write: bool) -> tuple[bytearray | bytes, int]:
        regions = (
            (ROM_BASE, self._rom, False, None),
            (RAM_BASE, self._ram, True, "ram"),
            (RESULT_BASE, self.state.result(), False, "result"),
        )
        for base, buf, writable, protected in regions:
            if base <= address and address + count <= base + len(buf):
                if write and not writable:
                    raise Refused(NackReason.READ_ONLY, f"0x{address:08X} is read-only")
                if protected is not None:
                    (self.faults.written if write else self.faults.read)(protected, address - base, count)
                return buf, address - base
        raise Refused(NackReason.BAD_ADDRESS, f"0x{address:08X}+{count} is outside the memory map")

    def peek(self, req: Peek) -> bytes:
        if not 1 <= req.count <= MAX_PEEK:
            raise Refused(NackReason.BAD_LENGTH, f"PEEK count {req.count} outside 1..{MAX_PEEK}")
        buf, off = self._region(req.address, req.count, write=False)
        return AddressedBytes(req.address, bytes(buf[off : off + req.count]), 4).pack()

    def poke(self, req: Poke) -> bytes:
        buf, off = self._region(req.address, len(req.data), write=True)
        assert isinstance(buf, bytearray)  # the writable regions
        buf[off : off + len(req.data)] = req.data
        return WriteAck(req.address, len(req.data), 4).pack()

    def _space(self, space: int) -> bytes:
        if space == MemorySpace.EDAC:
            return self.edac_image()
        if space == MemorySpace.RESULT:
            return self.state.result()
        raise Refused(NackReason.BAD_PARAMETER, f"unknown address space {space}")

    def crc(self, req: CrcRequest) -> bytes:
        if not 1 <= req.length <= MAX_CRC_SPAN:
            raise Refused(NackReason.BAD_LENGTH, f"CRC length {req.length} outside 1..{MAX_CRC_SPAN}")
        if req.space == MemorySpace.MEMORY:
            buf, off = self._region(req.address, req.length, write=False)
            span = bytes(buf[off : off + req.length])
        else:
            whole = self._space(req.space)
            if req.address + req.length > len(whole):
                raise Refused(NackReason.BAD_ADDRESS, f"0x{req.address:X}+{req.length} beyond {len(whole)} bytes")
            if req.space == MemorySpace.EDAC:
                self._scratch_read(req.address, req.length)
            else:
                self.faults.read("result", req.address, req.length)
            span = whole[req.address : req.address + req.length]
        return CrcReply(req.space, req.address, req.length, crc16_mcrf4xx(span)).pack()
