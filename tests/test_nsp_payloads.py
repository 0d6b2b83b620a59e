"""Typed command/reply data fields and the result structure layout."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol import result
from protocol.commands import (
    Combination,
    DarkWindow,
    Diagnostics,
    NackInfo,
    NackReason,
    PayloadError,
    ReadFile,
    ReadRange,
    SlotImage,
    SlotRejected,
    WriteFile,
    XferBegin,
    XferData,
    XferStatus,
)


def test_read_range_forms():
    assert ReadRange.unpack(bytes.fromhex("4C0004")) == ReadRange(0x4C, 4, False)
    assert ReadRange.unpack(bytes.fromhex("4C0000")).count == 256  # 0 means 256 in short form
    assert ReadRange.unpack(bytes.fromhex("00004800")) == ReadRange(0, 0x48, True)
    with pytest.raises(PayloadError) as exc:
        ReadRange.unpack(b"\x00\x01")
    assert exc.value.reason == NackReason.BAD_LENGTH


def test_file_forms_distinguished_by_length_and_both_carry_the_edac_address_over_4():
    """ICD page 1-35916: short and long forms both give the EDAC address divided by 4."""
    assert ReadFile.unpack(b"\x41") == ReadFile(0x104, False)
    assert ReadFile.unpack(b"\x41\x00") == ReadFile(0x104, True)
    assert ReadFile(0x4C, True).pack() == b"\x13\x00"  # index 0x13: the result length
    assert WriteFile.unpack(b"\x41abcd") == WriteFile(0x104, b"abcd", False)
    assert WriteFile.unpack(b"\x41\x00abcd") == WriteFile(0x104, b"abcd", True)


def test_time_reply_is_48_bits_little_endian_and_the_new_layouts_round_trip():
    from protocol.commands import CombinationFailure, RectangularPoke, TimeReply

    assert TimeReply(0x0000_1234_5678_9ABC).pack() == bytes.fromhex("bc9a78563412")
    assert TimeReply.unpack(bytes.fromhex("020000000080")).micros == (1 << 47) + 2
    with pytest.raises(PayloadError):
        TimeReply.unpack(b"\x00" * 8)
    poke = RectangularPoke(1, 2, 3, 1, 2, b"\x01\x00\x02\x00")
    assert RectangularPoke.unpack(poke.pack()) == poke and poke.head() == poke.pack()[:10]
    assert CombinationFailure.unpack(b"\x03terminated") == CombinationFailure(3, "terminated")


def test_combination_accepts_cosmos_4_byte_and_5_byte_forms():
    assert Combination.unpack(bytes.fromhex("0B7E0000")) == Combination(0x0B, 0x7E, 3)
    assert Combination.unpack(bytes.fromhex("1B00080000")) == Combination(0x1B, 0x0800, 4)


def test_dark_window_is_26_bytes():
    win = DarkWindow(1, 10, 20, 30, 40, tuple(range(8)))
    assert len(win.pack()) == 26 and DarkWindow.unpack(win.pack()) == win


@given(st.integers(0, 255), st.integers(0, 2**32 - 1), st.binary(min_size=1, max_size=100))
def test_xfer_roundtrips(slot, offset, data):
    assert XferData.unpack(XferData(slot, offset, data).pack()) == XferData(slot, offset, data)
    assert XferBegin.unpack(XferBegin(slot, offset, offset ^ 0xFFFF).pack()).length == offset


def test_status_and_slot_image_roundtrip():
    st_ = XferStatus(2, 1, 1000, 0xDEADBEEF, 100, 300, 2, ((100, 100), (400, 600)))
    assert XferStatus.unpack(st_.pack()) == st_
    img = SlotImage(0, True, 5, 7, b'{"a": 1}')
    assert SlotImage.unpack(img.pack()) == img


def test_diagnostics_and_nack_roundtrip():
    d = Diagnostics(1, 2, 3, 4, 5, 6, 7, 8, 9, 10, tuple(range(32)))
    assert Diagnostics.unpack(d.pack()) == d
    info = NackInfo.unpack(NackInfo(0x0103, "bad header").pack())
    assert (info.reason, info.text, info.reason_name) == (0x0103, "bad header", "VALIDATOR")
    with pytest.raises(ValueError):
        SlotRejected(0x0001, "validators use codes >= 0x0100")


def test_result_layout_matches_cosmos_offsets():
    off = {name: result.RESULT.fields[name][1] for name in result.RESULT.names}
    assert off["quaternion"] == 0x008 and off["omega"] == 0x028 and off["epoch"] == 0x040
    assert off["hardware"] == 0x048 and off["statistics"] == 0x080 and off["image"] == 0x130
    assert off["ers"] == 0x440 and off["centroid"] == 0x4A8 and off["matching"] == 0x7E8
    assert off["reserved_948"] == 0x948 and off["ext"] == 2616 == result.STANDARD_LENGTH
    assert result.RESULT.itemsize == result.TOTAL_LENGTH
    hw = result.HARDWARE.fields
    assert hw["detector_temp_raw"][1] == 0x0C and hw["dark_offsets"][1] == 0x18
    for addr, length in result.SECTIONS.values():
        assert addr + length <= result.TOTAL_LENGTH


def test_result_build_parse_paths():
    q = [0.5, 0.5, 0.5, 0.5]
    data = result.build(
        {
            "return_code": result.make_return_code(result.Status.OK, 0x5C),
            "quaternion": q,
            "centroid.1.good_stars": 7,
            "ext.n_reported": 1,
            "ext.stars.0.rg": 0.8,
        },
        sequence=3,
    )
    assert len(data) == result.TOTAL_LENGTH
    assert data[0x008:0x010] == np.float64(0.5).tobytes()
    rec = result.parse(data)
    assert rec["sequence"] == 3 and result.status_of(int(rec["return_code"])) is result.Status.OK
    assert int(rec["return_code"]) & result.ReturnBits.CONSISTENT_SOLUTION
    assert rec["centroid"][1]["good_stars"] == 7
    assert rec["ext"]["stars"][0]["rg"] == pytest.approx(0.8)
    assert result.parse(data[:2616])["ext"]["magic"] == 0
    with pytest.raises(KeyError):
        result.build({"no_such_field": 1})
    with pytest.raises(ValueError):
        result.parse(b"\0" * 100)


def test_every_payload_type_of_the_command_table_round_trips():
    from protocol.command_table import TABLE
    from protocol.commands import (
        AddressedBytes,
        CrcReply,
        CrcRequest,
        DiagnosticRequest,
        FaultRequest,
        FaultStatus,
        Go,
        Init,
        Peek,
        Poke,
        SlotRequest,
        TimeReply,
        WriteAck,
        WriteEdac,
        XferDataAck,
    )

    samples = {
        Init: Init(0x2000),
        Peek: Peek(0x20000000, 16),
        Poke: Poke(0x20000000, b"\x01\x02"),
        AddressedBytes: AddressedBytes(0x4C, b"\x00\x0a"),
        WriteAck: WriteAck(0x100, 2),
        DiagnosticRequest: DiagnosticRequest(1, True),
        Diagnostics: Diagnostics(framing=3, replies=9, per_code=tuple(range(32))),
        CrcRequest: CrcRequest(1, 0x20000000, 64),
        CrcReply: CrcReply(1, 0x20000000, 64, 0xBEEF),
        ReadFile: ReadFile(0x104, True),
        WriteFile: WriteFile(0x104, b"abcd"),
        ReadRange: ReadRange(0x4C, 4, False),
        WriteEdac: WriteEdac(0x100, b"xy"),
        Go: Go(0x0B),
        DarkWindow: DarkWindow(1, 10, 20, 30, 40, tuple(range(8))),
        Combination: Combination(0x0B, 0x7E, 3),
        XferBegin: XferBegin(0, 1000, 0xDEADBEEF),
        XferData: XferData(1, 4096, b"data"),
        XferDataAck: XferDataAck(1, 4100),
        SlotRequest: SlotRequest(2),
        XferStatus: XferStatus(2, 1, 1000, 0xDEADBEEF, 100, 300, 1, ((100, 700),)),
        SlotImage: SlotImage(2, True, 10, 0x1234, b'{"keys": []}'),
        FaultRequest: FaultRequest(0, b"drop_reply count=1\n"),
        FaultStatus: FaultStatus(2, 3, tuple(range(9))),
        TimeReply: TimeReply(0x123456789ABC),
    }
    types = {t for c in TABLE for t in (c.request, c.reply) if t is not None}
    assert types <= set(samples)
    for kind in types:
        assert kind.unpack(samples[kind].pack()) == samples[kind], kind


def test_diagnostic_request_forms_and_length_text():
    from protocol.commands import DiagnosticRequest

    assert DiagnosticRequest.clearing(True).pack() == b"\x01" and DiagnosticRequest.clearing(False).pack() == b""
    assert DiagnosticRequest.unpack(b"") == DiagnosticRequest() and DiagnosticRequest.unpack(b"\x03").flags == 3
    with pytest.raises(PayloadError) as exc:
        DiagnosticRequest.unpack(b"\x00\x00")
    assert exc.value.reason == NackReason.BAD_LENGTH and exc.value.message == "DIAGNOSTIC takes 0 or 1 data byte"


def test_the_fuzz_generator_makes_every_request_type_of_the_command_table():
    import random

    from ground.testing.traffic import _plausible_data
    from protocol.command_table import TABLE

    rng = random.Random(3)
    for command in TABLE:
        for _ in range(20):
            data = _plausible_data(rng, command.code)
            if command.request is None:
                assert data == b"", command.name
            elif command.also and data[:1] != b"\x00":  # IMAGE: a Dark Window, or the poke after it
                command.also[0].unpack(data)
            else:
                command.request.unpack(data)  # the right shape, whatever the values
