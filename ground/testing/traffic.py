"""Valid and mutated NSP traffic for fuzzing the device (bytes on the wire, SLIP framed).

:func:`command_frame` makes a well-formed command of any code 0x00-0x1F, with or without Poll,
with a plausible or a random data field; :func:`fault_frame` makes one damaged frame of a named
kind (:data:`FAULTS`); :func:`burst` mixes both, with garbage between frames.

FAULT (0x19) is generated like any code; it arms nothing on the devices the campaigns start,
which run without ``--fault-injection`` and NACK it NOT_SUPPORTED (``tests/test_faults.py``).
"""

from __future__ import annotations

import random
from collections.abc import Callable

from protocol import nsp, slip
from protocol.command_table import COMMANDS
from protocol.commands import (
    Code,
    Combination,
    CrcRequest,
    DarkWindow,
    DiagnosticRequest,
    FaultRequest,
    Go,
    Init,
    Peek,
    Poke,
    ReadFile,
    ReadRange,
    RectangularPoke,
    SlotRequest,
    WriteEdac,
    WriteFile,
    XferBegin,
    XferData,
)
from protocol.crc import crc16_mcrf4xx

HOST = nsp.HOST_ADDRESS

#: Kinds of damaged frame :func:`fault_frame` makes.
FAULTS = (
    "bad_crc",
    "runt",
    "bad_escape",
    "oversize",
    "wrong_address",
    "truncated",
    "bit_flip",
    "garbage",
    "no_end",
    "huge_data",
)


def _poke(rng: random.Random, buffer: int, row: int, col: int, rows: int, cols: int) -> RectangularPoke:
    """A Rectangular Poke of random pixel values, of the right length nine times in ten."""
    n = rows * cols if rng.random() < 0.9 else rng.randrange(rows * cols + 2)
    return RectangularPoke(buffer, row, col, rows, cols, rng.randbytes(2 * n))


def _plausible_data(rng: random.Random, code: int) -> bytes:
    """A data field of the right shape for ``code`` with random values (often out of range): of
    the request type the command table gives ``code`` (``tests/test_nsp_payloads.py`` checks that
    every type is made)."""
    r = rng.randrange
    addr = rng.choice([0x20000000 + r(0x10000), r(0x2000), 0x40000000 + r(3000), r(1 << 32)])
    makers: dict[int, Callable[[], bytes]] = {
        Code.INIT: lambda: Init(rng.choice([0x2000, r(1 << 32)])).pack(),
        Code.PEEK: lambda: Peek(addr, r(0, 1100)).pack(),
        Code.POKE: lambda: Poke(addr, rng.randbytes(r(1, 64))).pack(),
        Code.DIAGNOSTIC: lambda: (
            DiagnosticRequest(rng.choice([0, 1, r(256)]), True) if r(2) else DiagnosticRequest()
        ).pack(),
        Code.CRC: lambda: CrcRequest(r(4), addr, rng.choice([r(1, 4096), r(1 << 32)])).pack(),
        Code.READ_FILE: lambda: ReadFile(r(0, 600) & ~3, long=bool(r(2))).pack(),
        Code.WRITE_FILE: lambda: WriteFile(r(0, 600) & ~3, rng.randbytes(4), long=bool(r(2))).pack(),
        Code.READ_EDAC: lambda: ReadRange(r(0, 600), r(1, 257), long=bool(r(2))).pack(),
        Code.WRITE_EDAC: lambda: WriteEdac(r(0, 600), rng.randbytes(r(1, 40))).pack(),
        Code.GO: lambda: Go(rng.choice([0x02, 0x03, 0x0B, 0x12, r(256)])).pack(),
        Code.READ_RESULT: lambda: ReadRange(r(0, 3000), r(0, 3000), long=True).pack(),
        Code.IMAGE: lambda: (
            DarkWindow(r(3), r(3000), r(3000), r(1, 3000), r(1, 3000))
            if r(2)
            else _poke(rng, r(3), r(3000), r(3000), r(1, 24), r(1, 24))
        ).pack(),
        Code.COMBINATION: lambda: Combination(rng.choice([0x02, 0x03, 0x0B, r(256)]), r(1 << 24)).pack(),
        Code.XFER_BEGIN: lambda: XferBegin(r(5), rng.choice([r(1, 5000), r(1 << 32)]), r(1 << 32)).pack(),
        Code.XFER_DATA: lambda: XferData(r(5), r(6000), rng.randbytes(r(1, 300))).pack(),
        Code.FAULT: lambda: FaultRequest(r(4), rng.randbytes(r(0, 40))).pack(),
    }
    if code in makers:
        return makers[code]()
    spec = COMMANDS.get(code)
    if spec is not None and spec.request is SlotRequest:
        return SlotRequest(r(5)).pack()
    return b""


def command_frame(
    rng: random.Random, code: int | None = None, *, poll: bool | None = None, dst: int = nsp.DEVICE_ADDRESS
) -> bytes:
    """A well-formed command of ``code`` (random if None): Poll as given (random if None), B
    random, a plausible data field three times in four, else 0-64 random bytes."""
    code = rng.randrange(32) if code is None else code
    poll = rng.random() < 0.7 if poll is None else poll
    data = _plausible_data(rng, code) if rng.random() < 0.75 else rng.randbytes(rng.randrange(65))
    return nsp.command(dst, HOST, code, data, poll=poll, b=rng.random() < 0.5).frame()


def _damaged_cut(rng: random.Random, raw: bytes, shortest: int) -> bytes:
    """``raw`` cut to a random shorter length whose last two bytes are not by chance a valid CRC."""
    cut = raw[: rng.randrange(shortest, len(raw))]
    if len(cut) >= nsp.MIN_MESSAGE and crc16_mcrf4xx(cut) == 0:  # 1 in 65 536: damage its last byte
        cut = cut[:-1] + bytes([cut[-1] ^ 0x01])
    return cut


def fault_frame(rng: random.Random, kind: str, *, dst: int = nsp.DEVICE_ADDRESS) -> bytes:
    """One damaged frame of ``kind`` (see :data:`FAULTS`); its trailing FEND ends it on the wire
    except for ``no_end``, which the next frame's leading FEND ends."""
    raw = nsp.command(dst, HOST, rng.randrange(32), rng.randbytes(rng.randrange(1, 40)), poll=True).encode()
    if kind == "bad_crc":
        return slip.encode(raw[:-2] + bytes([raw[-2] ^ (1 + rng.randrange(255)), raw[-1]]))
    if kind == "runt":
        return slip.encode(raw[: rng.randrange(1, nsp.MIN_MESSAGE)])
    if kind == "bad_escape":
        body = slip.escape(raw)
        cut = rng.randrange(len(body) + 1)
        bad = bytes([slip.FESC, rng.choice([b for b in range(256) if b not in (slip.TFEND, slip.TFESC, slip.FEND)])])
        return bytes([slip.FEND]) + body[:cut] + bad + body[cut:] + bytes([slip.FEND])
    if kind == "oversize":
        return bytes([slip.FEND]) + bytes([dst]) * (nsp.MAX_MESSAGE + 1 + rng.randrange(4096)) + bytes([slip.FEND])
    if kind == "huge_data":  # a valid CRC around a data field one byte past the limit
        return nsp.command(dst, HOST, rng.randrange(32), rng.randbytes(nsp.MAX_DATA + 1)).frame()
    if kind == "wrong_address":
        other = rng.choice([a for a in range(256) if a != dst])
        return nsp.command(other, HOST, rng.randrange(32), b"", poll=True).frame()
    if kind == "truncated":
        return slip.encode(_damaged_cut(rng, raw, nsp.MIN_MESSAGE))
    if kind == "bit_flip":
        buf = bytearray(raw)
        buf[rng.randrange(len(buf))] ^= 1 << rng.randrange(8)
        return slip.encode(bytes(buf))
    if kind == "garbage":
        return rng.randbytes(rng.randrange(1, 200))
    if kind == "no_end":
        return bytes([slip.FEND]) + slip.escape(_damaged_cut(rng, raw, 1))
    raise ValueError(f"unknown fault kind {kind!r}")


def sweep(rng: random.Random) -> list[bytes]:
    """Every command code with and without Poll, then every fault kind: one frame each."""
    frames = [command_frame(rng, code, poll=poll) for code in range(32) for poll in (True, False)]
    return frames + [fault_frame(rng, kind) for kind in FAULTS]


def burst(rng: random.Random, n: int, fault_share: float = 0.5) -> tuple[bytes, int, int]:
    """``n`` frames, about ``fault_share`` of them damaged, with garbage between some of them.
    Returns (bytes, commands sent, faults injected)."""
    out, commands, faults = bytearray(), 0, 0
    for _ in range(n):
        if rng.random() < fault_share:
            out += fault_frame(rng, rng.choice(FAULTS))
            faults += 1
        else:
            out += command_frame(rng)
            commands += 1
        if rng.random() < 0.1:  # interleaved garbage, ended by the next frame's FEND
            out += rng.randbytes(rng.randrange(1, 32))
            faults += 1
    return bytes(out), commands, faults
