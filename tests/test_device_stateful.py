"""Property-based tests of the device: a stateful model of scratch memory and error counters under
injected faults, and random byte streams interleaved with good commands."""

import struct

from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from firmware_model.device.device import Device
from protocol import nsp, slip
from protocol.commands import UNASSIGNED, Code, NackInfo, NackReason, ReadRange

HOST = 0x11


def replies(dev, raw_stream):
    out = []
    for frame in dev.receive(raw_stream):
        (event,) = slip.Decoder(nsp.MAX_MESSAGE).feed(frame)
        out.append(nsp.decode(event.data))
    return out


class DeviceModel(RuleBasedStateMachine):
    def __init__(self):
        super().__init__()
        self.dev = Device()
        self.scratch = bytearray(256)
        self.expect = dict(framing=0, runt=0, oversize=0, bad_crc=0, other_address=0, accepted=0, nacked=0, silent=0)
        self.b = False

    def command(self, code, data, poll=True):
        self.b = not self.b
        msg = nsp.command(0x0E, HOST, code, data, poll=poll, b=self.b)
        reps = replies(self.dev, msg.frame())
        self.expect["accepted"] += 1
        if not poll:
            self.expect["silent"] += 1
            assert reps == []
            return None
        assert len(reps) == 1 and reps[0].final and reps[0].b == self.b and reps[0].code == code
        if not reps[0].ack:
            self.expect["nacked"] += 1
        return reps[0]

    @rule(addr=st.integers(0, 0x220), data=st.binary(min_size=1, max_size=40), poll=st.booleans())
    def write_edac(self, addr, data, poll):
        rep = self.command(Code.WRITE_EDAC, struct.pack("<H", addr) + data, poll)
        valid = addr >= 0x100 and addr + len(data) <= 0x200
        if not poll:
            if valid:
                self.scratch[addr - 0x100 : addr - 0x100 + len(data)] = data
            else:
                self.expect["nacked"] += 1
            return
        assert rep.ack == valid
        if valid:
            self.scratch[addr - 0x100 : addr - 0x100 + len(data)] = data

    @rule(addr=st.integers(0x100, 0x1FF), count=st.integers(1, 256))
    def read_scratch(self, addr, count):
        rep = self.command(Code.READ_EDAC, ReadRange(addr, count, long=False).pack())
        if addr + count > 0x200:
            assert not rep.ack and NackInfo.unpack(rep.data).reason == NackReason.BAD_ADDRESS
        else:
            assert rep.ack and rep.data[2:] == self.scratch[addr - 0x100 : addr - 0x100 + count]

    @rule(data=st.binary(min_size=1, max_size=30), flip=st.integers(1, 255))
    def bad_crc(self, data, flip):
        raw = bytearray(nsp.command(0x0E, HOST, Code.PING, data).encode())
        raw[-1] ^= flip
        assert replies(self.dev, slip.encode(bytes(raw))) == []
        self.expect["bad_crc"] += 1

    @rule(n=st.integers(1, 4))
    def runt(self, n):
        assert replies(self.dev, slip.encode(bytes([0x0E]) + bytes(n - 1))) == []
        self.expect["runt"] += 1

    @rule(after=st.sampled_from([0x00, 0x41, 0xC1, 0xDB]))
    def bad_escape(self, after):
        assert replies(self.dev, b"\xc0\x0e\x11\x80\xdb" + bytes([after]) + b"\x11\x22\xc0") == []
        self.expect["framing"] += 1

    @rule(extra=st.integers(1, 3000))
    def oversize(self, extra):
        assert replies(self.dev, b"\xc0" + b"\x0e" * (nsp.MAX_MESSAGE + extra) + b"\xc0") == []
        self.expect["oversize"] += 1

    @rule(dst=st.integers(0, 255).filter(lambda a: a != 0x0E))
    def other_address(self, dst):
        assert replies(self.dev, nsp.command(dst, HOST, Code.PING).frame()) == []
        self.expect["other_address"] += 1

    @rule(code=st.sampled_from(UNASSIGNED), data=st.binary(max_size=8))
    def unknown_code(self, code, data):
        rep = self.command(code, data)
        assert not rep.ack and NackInfo.unpack(rep.data).reason == NackReason.UNKNOWN_COMMAND

    @rule(
        code=st.sampled_from([Code.INIT, Code.PEEK, Code.READ_EDAC, Code.GO, Code.XFER_STATUS]),
        data=st.binary(max_size=12),
    )
    def wrong_length(self, code, data):
        sizes = {Code.INIT: (4,), Code.PEEK: (6,), Code.READ_EDAC: (3, 4), Code.GO: (1,), Code.XFER_STATUS: (1,)}
        if len(data) in sizes[code]:
            return
        rep = self.command(code, data)
        assert not rep.ack and NackInfo.unpack(rep.data).reason == NackReason.BAD_LENGTH

    @invariant()
    def counters_match(self):
        d = self.dev.counters.snapshot()
        for name, value in self.expect.items():
            assert getattr(d, name) == value, name


DeviceModel.TestCase.settings = settings(max_examples=40, stateful_step_count=30, deadline=None)
TestDeviceModel = DeviceModel.TestCase


@settings(max_examples=60, deadline=None)
@given(st.lists(st.binary(max_size=300), min_size=1, max_size=6))
def test_random_streams_never_break_the_next_good_command(garbage):
    dev = Device()
    for i, junk in enumerate(garbage):
        replies(dev, junk)
        # a FEND resynchronises; the next good command gets exactly its reply
        b = bool(i % 2)
        reps = replies(dev, nsp.command(0x0E, HOST, Code.PING, b=b).frame())
        assert [(r.code, r.ack, r.final, r.b) for r in reps][-1:] == [(0, True, True, b)]
        assert all(r.dst == HOST and r.src == 0x0E for r in reps)
    d = dev.counters.snapshot()
    assert d.per_code[0] >= len(garbage)
