"""The device shell in process: every command, NACK rules, counters, GO/busy, slots and persistence."""

import struct
import threading

import pytest

from firmware_model.device.device import Device, SlotHandler
from firmware_model.device.slots import SlotStore
from protocol import nsp, result, slip
from protocol.commands import (
    UNASSIGNED,
    Code,
    Combination,
    DarkWindow,
    Diagnostics,
    NackInfo,
    NackReason,
    ReadRange,
    SequenceState,
    SlotImage,
    SlotRejected,
    XferBegin,
    XferData,
    XferState,
    XferStatus,
)
from protocol.crc import crc32

HOST = 0x11


def send(dev, code, data=b"", poll=True, b=False, dst=0x0E):
    """Frame a command, feed it byte-level, decode the replies."""
    frames = dev.receive(nsp.command(dst, HOST, code, data, poll=poll, b=b).frame())
    out = []
    for f in frames:
        (event,) = slip.Decoder(nsp.MAX_MESSAGE).feed(f)
        out.append(nsp.decode(event.data))
    return out


def ok(dev, code, data=b"", **kw) -> bytes:
    (rep,) = send(dev, code, data, **kw)
    assert rep.ack and rep.final and rep.code == code, NackInfo.unpack(rep.data)
    return rep.data


def nack(dev, code, data=b"", **kw) -> NackInfo:
    (rep,) = send(dev, code, data, **kw)
    assert not rep.ack and rep.final and rep.code == code
    return NackInfo.unpack(rep.data)


def app_device(**kw) -> Device:
    dev = Device(**kw)
    ok(dev, Code.INIT, struct.pack("<I", 0x2000))
    return dev


def test_ping_banner_changes_after_init_and_init_rules():
    dev = Device()
    boot = ok(dev, Code.PING).decode()
    assert nack(dev, Code.INIT, struct.pack("<I", 0x1000)).reason == NackReason.BAD_ADDRESS
    assert nack(dev, Code.READ_RESULT, ReadRange(0, 4).pack()).reason == NackReason.WRONG_MODE
    assert ok(dev, Code.INIT, struct.pack("<I", 0x2000)) == b""
    app = ok(dev, Code.PING).decode()
    assert "BOOTLOADER" in boot and "APPLICATION" in app and boot != app
    assert nack(dev, Code.INIT, struct.pack("<I", 0x2000)).reason == NackReason.WRONG_MODE
    assert nack(dev, Code.PING, b"x").reason == NackReason.BAD_LENGTH


def test_reply_copies_b_bit_and_swaps_addresses():
    dev = Device()
    (rep,) = send(dev, Code.PING, b=True)
    assert (rep.dst, rep.src, rep.b) == (HOST, 0x0E, True)
    (rep,) = send(dev, Code.PING, b=False)
    assert not rep.b


def test_edac_read_write_and_file_access():
    dev = Device()
    assert ok(dev, Code.WRITE_EDAC, struct.pack("<H", 0x100) + b"scratch!") == struct.pack("<HH", 0x100, 8)
    assert ok(dev, Code.READ_EDAC, ReadRange(0x100, 8, long=False).pack()) == struct.pack("<H", 0x100) + b"scratch!"
    long_read = ok(dev, Code.READ_EDAC, ReadRange(0, 512, long=True).pack())
    assert len(long_read) == 514 and long_read[2 + 0x100 : 2 + 0x108] == b"scratch!"
    # file access (ICD page 1-35916): both forms take the EDAC address / 4; index 0x41 = EDAC 0x104
    assert ok(dev, Code.WRITE_FILE, b"\x41WXYZ") == b"\x41WXYZ"
    assert ok(dev, Code.READ_FILE, b"\x41\x00") == b"\x41\x00WXYZ"
    assert ok(dev, Code.READ_FILE, b"\x40") == b"\x40scra"
    assert ok(dev, Code.READ_FILE, b"\x13\x00")[2:] == b"\x00\x00\x00\x00"  # EDAC 0x4C, no result yet
    assert ok(dev, Code.WRITE_FILE, b"\x41\x00abcd") == b"\x41\x00abcd"
    assert ok(dev, Code.READ_FILE, b"\x41")[1:] == b"abcd"
    assert nack(dev, Code.WRITE_FILE, b"\x10abcd").reason == NackReason.READ_ONLY
    assert nack(dev, Code.READ_FILE, b"\x80\x00").reason == NackReason.BAD_ADDRESS  # EDAC 0x200: past the end
    assert nack(dev, Code.WRITE_EDAC, struct.pack("<H", 0x4C) + b"\0").reason == NackReason.READ_ONLY
    assert nack(dev, Code.WRITE_EDAC, struct.pack("<H", 0x1FF) + b"ab").reason == NackReason.BAD_ADDRESS
    assert nack(dev, Code.READ_EDAC, ReadRange(0x1F0, 32).pack()).reason == NackReason.BAD_ADDRESS
    assert nack(dev, Code.READ_EDAC, b"\x00").reason == NackReason.BAD_LENGTH


def test_peek_poke_memory_map():
    dev = Device()
    assert ok(dev, Code.POKE, struct.pack("<I", 0x20000010) + b"abc") == struct.pack("<IH", 0x20000010, 3)
    assert ok(dev, Code.PEEK, struct.pack("<IH", 0x2000000F, 5)) == struct.pack("<I", 0x2000000F) + b"\0abc\0"
    assert ok(dev, Code.PEEK, struct.pack("<IH", 0, 8))[4:] == b"ST16-EMU"
    assert nack(dev, Code.POKE, struct.pack("<I", 0) + b"x").reason == NackReason.READ_ONLY
    assert nack(dev, Code.PEEK, struct.pack("<IH", 0x2000FFFF, 2)).reason == NackReason.BAD_ADDRESS
    assert nack(dev, Code.PEEK, struct.pack("<IH", 0x12345678, 1)).reason == NackReason.BAD_ADDRESS
    assert nack(dev, Code.PEEK, struct.pack("<IH", 0x20000000, 0)).reason == NackReason.BAD_LENGTH


def test_crc_command():
    dev = Device()
    ok(dev, Code.WRITE_EDAC, struct.pack("<H", 0x100) + b"123456789")
    reply = ok(dev, Code.CRC, struct.pack("<BII", 0, 0x100, 9))
    assert struct.unpack("<BIIH", reply)[3] == 0x6F91
    assert nack(dev, Code.CRC, struct.pack("<BII", 7, 0, 9)).reason == NackReason.BAD_PARAMETER
    assert nack(dev, Code.CRC, struct.pack("<BII", 0, 0x1F0, 32)).reason == NackReason.BAD_ADDRESS


@pytest.mark.parametrize("code", UNASSIGNED)
def test_unassigned_codes_nacked(code):
    assert nack(Device(), code).reason == NackReason.UNKNOWN_COMMAND


def test_counters_for_injected_faults():
    dev = Device()
    body = nsp.command(0x0E, HOST, Code.PING).encode()
    bad_crc = body[:-1] + bytes([body[-1] ^ 1])
    assert dev.receive(slip.encode(bad_crc)) == []
    assert dev.receive(slip.encode(b"\x0e\x11")) == []  # runt addressed to us
    assert dev.receive(slip.encode(b"\x20\x11")) == []  # runt for someone else: not counted
    assert dev.receive(slip.encode(b"\x20" + bad_crc[1:])) == []  # bad CRC for someone else: not counted
    assert dev.receive(b"\xc0\x0e\x11\xdb\x00\x80\xc0") == []  # bad escape
    assert dev.receive(b"\xc0" + b"\x0e" * (nsp.MAX_MESSAGE + 1) + b"\xc0") == []  # oversize
    assert dev.receive(nsp.command(0x20, HOST, Code.PING).frame()) == []  # another address: ignored
    d = Diagnostics.unpack(ok(dev, Code.DIAGNOSTIC))
    assert (d.bad_crc, d.runt, d.framing, d.oversize, d.other_address, d.fifo_overflow) == (1, 1, 1, 1, 1, 0)
    assert d.accepted == 1 and d.per_code[Code.DIAGNOSTIC] == 1
    edac = ok(dev, Code.READ_EDAC, ReadRange(0x24, 16).pack())[2:]
    assert struct.unpack("<4I", edac) == (1, 1, 1, 1)
    ok(dev, Code.DIAGNOSTIC, b"\x01")  # read and clear
    assert Diagnostics.unpack(ok(dev, Code.DIAGNOSTIC)).bad_crc == 0


def test_poll_zero_executes_silently():
    dev = Device()
    assert send(dev, Code.WRITE_EDAC, struct.pack("<H", 0x180) + b"quiet", poll=False) == []
    assert send(dev, Code.PEEK, b"bad", poll=False) == []  # even a NACK stays silent
    assert ok(dev, Code.READ_EDAC, ReadRange(0x180, 5).pack())[2:] == b"quiet"
    d = Diagnostics.unpack(ok(dev, Code.DIAGNOSTIC))
    assert d.silent == 2 and d.nacked == 1


def test_go_without_catalog_never_fakes_an_attitude():
    dev = Device()
    assert nack(dev, Code.GO, b"\x08").reason == NackReason.WRONG_MODE  # boot mode, no LOAD_NAND
    assert ok(dev, Code.GO, b"\x0b") == b"\x0b"  # LOAD_NAND boots the application
    assert dev.wait_idle(5)
    rec = result.parse(_read_result(dev))
    assert result.status_of(int(rec["return_code"])) == result.Status.NO_CATALOG
    assert int(rec["return_code"]) & 0xFF == result.ReturnBits.STATUS_NOT_OK and not rec["quaternion"].any()
    assert rec["sequence"] == 1
    assert nack(dev, Code.GO, b"\x37").reason == NackReason.NOT_SUPPORTED  # self-test
    assert nack(dev, Code.GO, b"\x8b").reason == NackReason.BAD_PARAMETER  # bit 7 unassigned


def _read_result(dev, address=0, count=result.TOTAL_LENGTH):
    parts = send(dev, Code.READ_RESULT, ReadRange(address, count).pack())
    assert all(p.ack for p in parts) and [p.final for p in parts] == [False] * (len(parts) - 1) + [True]
    buf = bytearray(count)
    for p in parts:
        addr = struct.unpack_from("<H", p.data)[0]
        buf[addr - address : addr - address + len(p.data) - 2] = p.data[2:]
    return bytes(buf)


def test_read_result_long_form_splits_into_parts():
    dev = app_device()
    rec = result.parse(_read_result(dev))
    assert result.status_of(int(rec["return_code"])) == result.Status.NO_RESULT  # nothing run yet
    parts = send(dev, Code.READ_RESULT, ReadRange(0, result.TOTAL_LENGTH).pack())
    addrs = [struct.unpack_from("<H", p.data)[0] for p in parts]
    assert addrs == list(range(0, result.TOTAL_LENGTH, 1024)) and len(parts) == -(-result.TOTAL_LENGTH // 1024)
    short = send(dev, Code.READ_RESULT, bytes.fromhex("480038"))  # COSMOS hardware block
    assert len(short) == 1 and len(short[0].data) == 2 + 0x38
    assert nack(dev, Code.READ_RESULT, ReadRange(result.TOTAL_LENGTH - 20, 100).pack()).reason == NackReason.BAD_ADDRESS


class _GatedSolver:
    def __init__(self):
        self.gate = threading.Event()
        self.contexts = []

    def __call__(self, ctx):
        self.contexts.append(ctx)
        assert self.gate.wait(5)
        return {
            "return_code": result.make_return_code(result.Status.OK, 0x5C),
            "quaternion": [1, 0, 0, 0],
            "ext.n_detected": 12,
        }


def _upload(dev, slot, data):
    ok(dev, Code.XFER_BEGIN, XferBegin(slot, len(data), crc32(data)).pack())
    for off in range(0, len(data), 1000):
        ok(dev, Code.XFER_DATA, XferData(slot, off, data[off : off + 1000]).pack())
    return send(dev, Code.XFER_COMMIT, bytes([slot]))[0]


def test_go_busy_result_length_and_solver_fields():
    solver = _GatedSolver()
    dev = app_device(solver=solver)
    assert _upload(dev, 0, b"catalog").ack and _upload(dev, 1, b"frame").ack
    assert ok(dev, Code.GO, b"\x0b") == b"\x0b"
    assert ok(dev, Code.READ_EDAC, ReadRange(0x4C, 4).pack())[2:] == bytes(4)  # busy: length 0
    assert nack(dev, Code.GO, b"\x0b").reason == NackReason.BUSY
    assert "BUSY" in ok(dev, Code.PING).decode()  # responsive while solving
    solver.gate.set()
    assert dev.wait_idle(5)
    assert struct.unpack("<II", ok(dev, Code.READ_EDAC, ReadRange(0x4C, 8).pack())[2:]) == (2616, result.TOTAL_LENGTH)
    rec = result.parse(_read_result(dev))
    assert result.status_of(int(rec["return_code"])) == result.Status.OK
    assert list(rec["quaternion"]) == [1, 0, 0, 0] and rec["ext"]["n_detected"] == 12
    assert rec["ext"]["catalog_crc32"] == crc32(b"catalog")
    ctx = solver.contexts[0]
    assert (ctx.catalog, ctx.frame, ctx.params, ctx.sequence) == (b"catalog", b"frame", None, 1)


def test_go_no_frame_and_solver_error():
    def broken(ctx):
        raise RuntimeError("boom")

    dev = app_device(solver=broken)
    _upload(dev, 0, b"catalog")
    ok(dev, Code.GO, b"\x0b")
    dev.wait_idle(5)
    assert result.status_of(int(result.parse(_read_result(dev))["return_code"])) == result.Status.NO_FRAME
    _upload(dev, 1, b"frame")
    ok(dev, Code.GO, b"\x0b")
    dev.wait_idle(5)
    rec = result.parse(_read_result(dev))
    assert result.status_of(int(rec["return_code"])) == result.Status.SOLVER_ERROR and rec["sequence"] == 2


def test_combination_multipart_reply():
    """ICD page 1-35918: the sections as one stream, each message u16 bytes already transmitted
    + at most 1 024 result bytes; ACK on each, Final on the last; a zero mask: one message, u16 0."""
    dev = app_device()
    parts = send(dev, Code.COMBINATION, Combination(0x0B, 0x0207, 3).pack())
    counts = [struct.unpack_from("<H", p.data)[0] for p in parts]
    assert counts == [0] and parts[0].final and parts[0].ack
    assert len(parts[0].data) == 2 + 4 + 4 + 32 + 832
    rc = struct.unpack_from("<I", parts[0].data, 2 + 4)[0]
    assert result.status_of(rc) == result.Status.NO_CATALOG
    (empty,) = send(dev, Code.COMBINATION, Combination(0x00, 0, 3).pack())
    assert empty.ack and empty.final and empty.data == b"\x00\x00"
    # refusals are the ICD's failure reply (page 1-35918): ACK 0, Final, sequence state + text
    for mask, text in ((0x0800, "self-test result section"), (0x8000, "unknown section bits")):
        (rep,) = send(dev, Code.COMBINATION, Combination(0x0B, mask, 3).pack())
        assert not rep.ack and rep.final and rep.data[0] == SequenceState.DONE and text in rep.data[1:].decode()


def test_combination_reply_counts_bytes_already_transmitted_and_reassembles_to_the_sections():
    """Mask 0x1000 | 0x0400 | 0x0001 (4 + 352 + 1 504 = 1 860 bytes): two messages counting 0 and
    1 024, Final on the second; joined, they are the sections' bytes in address order; the client
    splits them back by section."""
    from ground.link.client import Client, MalformedReply
    from protocol.nsp import Message

    dev = app_device()
    mask = 0x1000 | 0x0400 | 0x0001
    parts = send(dev, Code.COMBINATION, Combination(0x00, mask, 3).pack())
    assert [struct.unpack_from("<H", p.data)[0] for p in parts] == [0, 1024]
    assert [p.final for p in parts] == [False, True] and all(p.ack for p in parts)
    assert [len(p.data) - 2 for p in parts] == [1024, 4 + 352 + 1504 - 1024]
    raw = _read_result(dev)
    sections = [(0x000, 4), (0x7E8, 352), (0xA38, 1504)]
    assert b"".join(p.data[2:] for p in parts) == b"".join(raw[a : a + n] for a, n in sections)

    class Canned(Client):  # the client's reassembly, on the device's messages
        def __init__(self, replies):
            self.replies = replies

        def _request(self, code, request, **kw):
            return self.replies

    assert Canned(parts).combination(0x00, mask) == {a: raw[a : a + n] for a, n in sections}
    assert Canned(send(dev, Code.COMBINATION, Combination(0x00, 0, 3).pack())).combination(0x00, 0) == {}
    bad_count = [parts[0], Message(parts[1].dst, parts[1].src, parts[1].mcf, b"\x00\x05" + parts[1].data[2:])]
    with pytest.raises(MalformedReply, match="already transmitted"):
        Canned(bad_count).combination(0x00, mask)
    with pytest.raises(MalformedReply, match="its sections hold"):
        Canned(parts[:1]).combination(0x00, mask)


def test_image_dark_window():
    dev = Device()
    win = DarkWindow(0, 10, 20, 30, 40, tuple(range(8))).pack()
    assert nack(dev, Code.IMAGE, win).reason == NackReason.WRONG_MODE
    ok(dev, Code.INIT, struct.pack("<I", 0x2000))
    assert ok(dev, Code.IMAGE, win) == win
    assert nack(dev, Code.IMAGE, DarkWindow(2, 0, 0, 1, 1).pack()).reason == NackReason.BAD_PARAMETER
    assert nack(dev, Code.IMAGE, DarkWindow(0, 2460, 0, 10, 1).pack()).reason == NackReason.OUT_OF_RANGE
    assert nack(dev, Code.IMAGE, win[:25]).reason == NackReason.BAD_LENGTH
    assert nack(dev, Code.IMAGE, b"\x02" + bytes(10)).reason == NackReason.BAD_PARAMETER  # reserved subcommand


def test_transfer_commit_crc_and_validator():
    def validate(data):
        if not data.startswith(b"CAT"):
            raise SlotRejected(0x0103, "bad catalog magic")

    dev = Device(slots={0: SlotHandler(validate, bytes, lambda d, o: b'{"ok": 1}')})
    good = b"CAT" + bytes(5000)
    assert _upload(dev, 0, good).ack
    info = SlotImage.unpack(ok(dev, Code.SLOT_INFO, b"\x00"))
    assert (info.active, info.length, info.crc32, info.info) == (True, 5003, crc32(good), b'{"ok": 1}')
    rep = _upload(dev, 0, b"XYZ" + bytes(10))
    assert not rep.ack and NackInfo.unpack(rep.data) == NackInfo(0x0103, "bad catalog magic")
    assert SlotImage.unpack(ok(dev, Code.SLOT_INFO, b"\x00")).crc32 == crc32(good)  # previous stays active
    # announced CRC wrong: refused, transfer discarded
    ok(dev, Code.XFER_BEGIN, XferBegin(0, 4, 1234).pack())
    ok(dev, Code.XFER_DATA, XferData(0, 0, b"CATx").pack())
    assert nack(dev, Code.XFER_COMMIT, b"\x00").reason == NackReason.CRC_MISMATCH
    assert XferStatus.unpack(ok(dev, Code.XFER_STATUS, b"\x00")).state == XferState.NONE
    # bad requests
    assert nack(dev, Code.XFER_BEGIN, XferBegin(9, 4, 0).pack()).reason == NackReason.BAD_SLOT
    assert nack(dev, Code.XFER_DATA, XferData(0, 0, b"x").pack()).reason == NackReason.NO_TRANSFER
    ok(dev, Code.XFER_BEGIN, XferBegin(0, 10, 0).pack())
    assert nack(dev, Code.XFER_DATA, XferData(0, 8, b"xyz").pack()).reason == NackReason.OUT_OF_RANGE
    assert nack(dev, Code.XFER_COMMIT, b"\x00").reason == NackReason.INCOMPLETE
    assert nack(dev, Code.XFER_BEGIN, XferBegin(0, 0, 0).pack()).reason == NackReason.TOO_LARGE


def test_transfer_status_ranges_and_resume_after_restart(tmp_path):
    data = bytes(range(256)) * 40
    dev = Device(store=SlotStore(tmp_path))
    ok(dev, Code.XFER_BEGIN, XferBegin(2, len(data), crc32(data)).pack())
    ok(dev, Code.XFER_DATA, XferData(2, 0, data[:1000]).pack())
    ok(dev, Code.XFER_DATA, XferData(2, 3000, data[3000:4000]).pack())
    st = XferStatus.unpack(ok(dev, Code.XFER_STATUS, b"\x02"))
    assert (st.state, st.contiguous, st.received) == (XferState.RECEIVING, 1000, 2000)
    assert st.missing == ((1000, 2000), (4000, len(data) - 4000))
    # "restart": a new device on the same state directory resumes the transfer
    dev2 = Device(store=SlotStore(tmp_path))
    st2 = XferStatus.unpack(ok(dev2, Code.XFER_BEGIN, XferBegin(2, len(data), crc32(data)).pack()))
    assert st2.missing == st.missing
    for off, n in st2.missing:
        for start in range(off, off + n, 4096):
            ok(dev2, Code.XFER_DATA, XferData(2, start, data[start : min(start + 4096, off + n)]).pack())
    rep = send(dev2, Code.XFER_COMMIT, b"\x02")[0]
    assert not rep.ack and NackInfo.unpack(rep.data).reason == 0x0101  # not JSON: params validator
    params = b'{"max_stars": 20}'
    assert _upload(dev2, 2, params).ack
    dev3 = Device(store=SlotStore(tmp_path))
    info = SlotImage.unpack(ok(dev3, Code.SLOT_INFO, b"\x02"))
    assert info.active and info.crc32 == crc32(params) and b"max_stars" in info.info
