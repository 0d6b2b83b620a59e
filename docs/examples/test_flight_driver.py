"""A flight driver's tests against the emulated ST-16 star tracker on a pty (docs/testing.md).

Copy this file into your project and run ``pytest``: with ``colour-st16`` installed, the ``st16``
pytest plugin provides the ``st16_device`` fixture (a device started on a pty, its catalog
committed, stopped at teardown) and the ``@pytest.mark.st16(...)`` marker that configures it.

``St16Driver`` below stands for your flight software's driver: it is written from docs/ICD.md
alone (SLIP, NSP, CRC-16/MCRF4XX; the commands PING 0x00, INIT 0x01, READ EDAC 0x09, GO 0x0B and
READ RESULT 0x0D of section 6) and talks to the device through pyserial, as it would to the real
sensor on a UART. Replace it with yours (or call your C driver on ``st16_device.port``).
"""

from __future__ import annotations

import math
import struct
import time

import pytest
import serial

# ---------------------------------------------------------------------------------------------- the wire (docs/ICD.md)

FEND, FESC, TFEND, TFESC = 0xC0, 0xDB, 0xDC, 0xDD  # SLIP (section 2)
DEVICE, HOST = 0x0E, 0x11  # NSP addresses (section 3)
POLL = 0x80  # command MCF bit 7: reply wanted; in a reply, bit 7 is Final
B_BIT = 0x40  # copied from the command into its reply
ACK = 0x20  # reply MCF bit 5: 1 executed, 0 NACK
PING, INIT, READ_EDAC, GO, READ_RESULT = 0x00, 0x01, 0x09, 0x0B, 0x0D  # section 6
APP_START = 0x00002000  # INIT's start address (section 5)
GO_OPERATIONAL = 0x0B  # GO code: ON | NOT_OFF | COMMAND (section 7)
RESULT_LENGTH = 0x004C  # EDAC u32: 2616 once a result is ready, 0 while a sequence runs (section 8)
RESULT_HEAD = 0x48  # result bytes read: sequence, return code, quaternion, omega, epoch (section 10)


def crc16(data: bytes) -> int:
    """CRC-16/MCRF4XX: polynomial 0x1021 reflected, init 0xFFFF, no final XOR (section 3)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    return crc


def slip_encode(msg: bytes) -> bytes:
    body = msg.replace(bytes([FESC]), bytes([FESC, TFESC])).replace(bytes([FEND]), bytes([FESC, TFEND]))
    return bytes([FEND]) + body + bytes([FEND])


def slip_decode(body: bytes) -> bytes | None:
    """A frame's bytes between FENDs, unescaped; None for a bad escape."""
    out, k = bytearray(), 0
    while k < len(body):
        if body[k] == FESC:
            if k + 1 >= len(body) or body[k + 1] not in (TFEND, TFESC):
                return None
            out.append(FEND if body[k + 1] == TFEND else FESC)
            k += 2
        else:
            out.append(body[k])
            k += 1
    return bytes(out)


# ---------------------------------------------------------------------------------------------- the driver under test


class DriverError(Exception):
    pass


class Nacked(DriverError):
    def __init__(self, code: int, reason: int, text: str):
        super().__init__(f"command 0x{code:02X} NACKed 0x{reason:04X}: {text}")
        self.reason = reason


class StaleResult(DriverError):
    """The sensor said a result was ready, but its sequence number did not advance."""


class St16Driver:
    """A minimal ST-16 driver: one command at a time, the reply checked (CRC, addresses, code, B
    bit), read-only commands retried after a timeout or a bad CRC, every anomaly counted."""

    def __init__(self, port: str, timeout: float = 1.0, retries: int = 2):
        self.ser = serial.Serial(port, 115200, timeout=0.01)
        self.timeout, self.retries = timeout, retries
        self.b = 0
        self.crc_errors = self.timeouts = self.stale_results = 0
        self.last_sequence = 0
        self._rx = bytearray()

    def close(self) -> None:
        self.ser.close()

    # -- one command

    def command(self, code: int, data: bytes = b"", retry: bool = True) -> bytes:
        """Send ``code`` with ``data``; the reply's data (the parts of a multi-part reply joined,
        each part's own address field kept)."""
        for _ in range(1 + (self.retries if retry else 0)):
            self.b ^= 1
            mcf = POLL | (B_BIT if self.b else 0) | code
            msg = bytes([DEVICE, HOST, mcf]) + data
            self._rx.clear()
            self.ser.reset_input_buffer()
            self.ser.write(slip_encode(msg + struct.pack("<H", crc16(msg))))
            reply = self._reply(code)
            if reply is not None:
                return reply
        raise DriverError(f"command 0x{code:02X}: no valid reply after {1 + self.retries} tries")

    def _reply(self, code: int) -> bytes | None:
        parts: list[bytes] = []
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            frame = self._frame()
            if frame is None:
                continue
            if len(frame) < 5:
                continue
            msg, crc = frame[:-2], struct.unpack("<H", frame[-2:])[0]
            if crc16(msg) != crc:
                self.crc_errors += 1
                return None  # this reply is lost: try again
            dst, src, mcf = msg[0], msg[1], msg[2]
            if (dst, src) != (HOST, DEVICE) or mcf & 0x1F != code or bool(mcf & B_BIT) != bool(self.b):
                continue  # not the reply to this command (a stale one)
            if not mcf & ACK:
                reason = struct.unpack("<H", msg[3:5])[0] if len(msg) >= 5 else 0
                raise Nacked(code, reason, msg[5:].decode("utf-8", "replace"))
            parts.append(msg[3:])
            if mcf & POLL:  # Final
                return b"".join(parts)
        self.timeouts += 1
        return None

    def _frame(self) -> bytes | None:
        """The next whole frame received, unescaped (None if none came within a read slice)."""
        while True:
            start = self._rx.find(FEND)
            if start >= 0:
                end = self._rx.find(FEND, start + 1)
                if end >= 0:
                    body = bytes(self._rx[start + 1 : end])
                    del self._rx[:end]
                    if body:
                        return slip_decode(body)
                    continue
            chunk = self.ser.read(4096)
            if not chunk:
                return None
            self._rx += chunk

    # -- the sensor's functions

    def ping(self) -> str:
        return self.command(PING).decode("ascii", "replace")

    def init(self) -> None:
        self.command(INIT, struct.pack("<I", APP_START), retry=False)

    def result_length(self) -> int:
        data = self.command(READ_EDAC, struct.pack("<HB", RESULT_LENGTH, 4))  # short form
        return struct.unpack("<I", data[2:6])[0]  # after the echoed u16 address

    def go(self) -> None:
        if self.command(GO, bytes([GO_OPERATIONAL]), retry=False) != bytes([GO_OPERATIONAL]):
            raise DriverError("GO not echoed")

    def read_result(self) -> dict:
        data = self.command(READ_RESULT, struct.pack("<HH", 0, RESULT_HEAD))  # long form: one part
        head = data[2:]  # after the part's u16 address
        sequence, return_code = struct.unpack_from("<II", head, 0)
        return {
            "sequence": sequence,
            "status": (return_code >> 8) & 0xFF,  # 0 OK: a high-confidence attitude
            "q": struct.unpack_from("<4d", head, 0x08),  # scalar first, ICRS to sensor
            "epoch": struct.unpack_from("<d", head, 0x40)[0],
        }

    def solve(self, timeout: float = 10.0, poll_s: float = 0.05) -> dict:
        """GO, poll the result length until a result is ready, read it; StaleResult if its
        sequence number did not advance."""
        self.go()
        deadline = time.monotonic() + timeout
        while self.result_length() == 0:
            if time.monotonic() > deadline:
                raise DriverError(f"no result within {timeout} s of GO")
            time.sleep(poll_s)
        result = self.read_result()
        if result["sequence"] <= self.last_sequence:
            self.stale_results += 1
            raise StaleResult(f"result sequence {result['sequence']} after {self.last_sequence}")
        self.last_sequence = result["sequence"]
        return result


def arcsec_between(q1, q2) -> float:
    dot = min(1.0, abs(sum(a * b for a, b in zip(q1, q2))))
    return math.degrees(2.0 * math.acos(dot)) * 3600.0


@pytest.fixture
def driver(st16_device):
    d = St16Driver(st16_device.port)
    yield d
    d.close()


# ---------------------------------------------------------------------------------------------- the tests


@pytest.mark.st16(sky=3)  # three sky attitudes rendered in turn, one per GO; the truth is st16_device.truth
def test_the_driver_solves_each_attitude_of_the_schedule(st16_device, driver):
    assert driver.ping().startswith("ST16-EMU BOOTLOADER")
    driver.init()
    assert driver.ping().startswith("ST16-EMU APPLICATION")
    for k in range(3):
        result = driver.solve()
        assert result["status"] == 0, st16_device.log
        assert result["sequence"] == k + 1
        assert arcsec_between(result["q"], st16_device.expected(k)) < 60.0
    assert driver.crc_errors == driver.timeouts == 0


@pytest.mark.st16(sky=1, faults="corrupt_crc count=1")  # the next reply goes out with a bad CRC
def test_the_driver_notices_a_corrupted_reply_and_asks_again(st16_device, driver):
    assert driver.ping().startswith("ST16-EMU BOOTLOADER")  # the first reply is corrupted, the retry is not
    assert driver.crc_errors == 1
    assert st16_device.fault_counters()["corrupted_crcs"] == 1  # the device made one; the driver saw it


@pytest.mark.st16(sky=1, faults="stuck_result count=1")  # the next GO completes at once with the old result
def test_the_driver_refuses_a_stuck_result(st16_device, driver):
    driver.init()
    with pytest.raises(StaleResult):
        driver.solve()
    assert driver.stale_results == 1
    result = driver.solve()  # the next GO runs: the schedule's first exposure, solved
    assert result["status"] == 0 and arcsec_between(result["q"], st16_device.expected(0)) < 60.0
    assert st16_device.fault_counters()["stuck_results"] == 1
