"""NSP message layer: MCF bits, encode/decode, and the research notes' worked byte examples."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol import nsp, slip
from protocol.commands import Code, Go, Init, ReadRange

WORKED = [  # research notes section 2.5: (message, wire bytes)
    (nsp.command(0x0E, 0x11, Code.PING), "C00E11806921C0"),
    (nsp.command(0x0E, 0x11, Code.INIT, Init(0x2000).pack()), "C00E1181002000001F31C0"),
    (nsp.command(0x0E, 0x11, Code.READ_EDAC, ReadRange(0x4C, 4, long=False).pack()), "C00E11894C00042ABFC0"),
    (nsp.command(0x0E, 0x11, Code.READ_RESULT, ReadRange(0, 0x48, long=True).pack()), "C00E118D00004800B2CDC0"),
    (nsp.command(0x0E, 0x11, Code.READ_RESULT, ReadRange(0xC0, 16, long=False).pack()), "C00E118DDBDC00102C32C0"),
    (nsp.command(0x0E, 0x11, Code.GO, Go(0x0B).pack()), "C00E118B0B9DA4C0"),
    (nsp.Message(0x11, 0x0E, 0xA0), "C0110EA060D9C0"),
]


@pytest.mark.parametrize("msg,wire", WORKED)
def test_worked_examples(msg, wire):
    assert msg.frame() == bytes.fromhex(wire)
    (frame,) = slip.Decoder().feed(bytes.fromhex(wire))
    assert nsp.decode(frame.data) == msg


def test_mcf_bits():
    cmd = nsp.command(0x0E, 0x11, 0x0B, b"\x0b", b=True)
    assert cmd.mcf == 0xCB and cmd.poll and cmd.b and not cmd.ack and cmd.code == 0x0B
    rep = nsp.reply_to(cmd, b"\x0b")
    assert (rep.dst, rep.src, rep.mcf) == (0x11, 0x0E, 0xEB)
    assert rep.final and rep.ack and rep.b
    nack = nsp.reply_to(cmd, ack=False, final=False)
    assert nack.mcf == 0x4B and not nack.final and not nack.ack
    assert nsp.command(0x0E, 0x11, 0x00, poll=False).mcf == 0x00
    with pytest.raises(ValueError):
        nsp.make_mcf(0x20)


def test_runt_and_bad_crc():
    with pytest.raises(nsp.Runt) as exc:
        nsp.decode(b"\x0e\x11\x80\x69")
    assert exc.value.raw == b"\x0e\x11\x80\x69"
    with pytest.raises(nsp.BadCrc):
        nsp.decode(bytes.fromhex("0E11806922"))


@given(st.integers(0, 255), st.integers(0, 255), st.integers(0, 255), st.binary(max_size=500))
def test_roundtrip(dst, src, mcf, data):
    msg = nsp.Message(dst, src, mcf, data)
    assert nsp.decode(msg.encode()) == msg
    (frame,) = slip.Decoder(nsp.MAX_MESSAGE).feed(msg.frame())
    assert frame.data == msg.encode()


@given(st.binary(min_size=5, max_size=50), st.integers(0, 49), st.integers(1, 255))
def test_any_single_byte_corruption_is_caught(data, pos, flip):
    raw = nsp.Message(data[0], data[1], data[2], data[3:]).encode()
    bad = bytearray(raw)
    bad[pos % len(raw)] ^= flip
    with pytest.raises(nsp.BadCrc):
        nsp.decode(bytes(bad))
