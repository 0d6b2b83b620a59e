"""Short fuzz of the device's NSP link (fixed seeds): random and damaged frames of every kind,
a PING answered after every burst, no crash, hang or traceback (long run: bench/bench_fuzz.py)."""

import random

from ground.testing import nsp_fuzz, traffic
from protocol import nsp, slip


def test_every_fault_kind_is_damaged_and_every_command_is_valid():
    rng = random.Random(3)
    for _ in range(20):
        for kind in sorted(set(traffic.FAULTS) - {"garbage"}):  # random garbage may hold anything
            for event in slip.Decoder(nsp.MAX_MESSAGE).feed(traffic.fault_frame(rng, kind) + b"\xc0"):
                try:
                    msg = nsp.decode(event.data) if isinstance(event, slip.Frame) else None
                except nsp.MessageError:
                    msg = None
                assert msg is None or msg.dst != nsp.DEVICE_ADDRESS, kind  # never a valid command for us
    frames = traffic.sweep(rng)[:64]
    codes = set()
    for frame in frames:
        (event,) = slip.Decoder(nsp.MAX_MESSAGE).feed(frame)
        msg = nsp.decode(event.data)
        codes.add((msg.code, msg.poll))
    assert codes == {(c, p) for c in range(32) for p in (True, False)}


def test_fuzzed_device_answers_a_ping_after_every_burst():
    tally, seen = nsp_fuzz.run(seed=1, bursts=25)
    assert tally.failures == 0, tally.notes
    assert tally.messages > 300 and tally.faults > 100
    assert all(seen[name] > 0 for name in nsp_fuzz.ERROR_COUNTERS), seen  # each fault class reached it


def test_every_code_is_answered_when_polled_and_silent_when_not():
    from firmware_model.device.device import Device

    dev, rng = Device(), random.Random(4)
    for _ in range(10):
        for code in range(32):
            for poll in (True, False):
                frame = traffic.command_frame(rng, code, poll=poll)
                cmd = nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(frame)[0].data)
                out = dev.receive(frame)
                dev.wait_idle(5)
                assert bool(out) == poll, (code, poll)
                replies = [nsp.decode(e.data) for f in out for e in slip.Decoder(nsp.MAX_MESSAGE).feed(f)]
                assert all((r.code, r.b, r.dst) == (code, cmd.b, nsp.HOST_ADDRESS) for r in replies)
                assert [r.final for r in replies] == ([False] * (len(replies) - 1) + [True] if poll else [])
