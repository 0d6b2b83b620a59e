"""Scripted device faults in process (docs/ICD.md section 13): the script parser and its one-line
errors, the counted and seeded triggers, each fault's effect on a Device's replies and its
counter in EDAC memory, and fuzz traffic that never arms one."""

import random
import struct
import threading

import pytest

from firmware_model.device.device import Device, SlotHandler
from firmware_model.device.faults import (
    MAX_DELAYED,
    MAX_UPSET_WORDS,
    DelayedReplies,
    FaultInjector,
    FaultScriptError,
    draw_words,
    parse_script,
)
from firmware_model.device.memory import RAM_BASE, RESULT_BASE
from protocol import edac, nsp, result, slip
from protocol.commands import (
    Code,
    Combination,
    DiagnosticRequest,
    Diagnostics,
    FaultAction,
    FaultRequest,
    FaultStatus,
    Go,
    NackInfo,
    NackReason,
    Peek,
    Poke,
    ReadRange,
    Slot,
    SlotImage,
    SlotRequest,
    WriteEdac,
    XferBegin,
    XferData,
)
from protocol.crc import crc32
from tests import guards

HOST = 0x11


def frames(dev, code, data=b"", poll=True) -> list[bytes]:
    return dev.receive(nsp.command(0x0E, HOST, code, data, poll=poll).frame())


def decode(frame: bytes) -> nsp.Message:
    (event,) = slip.Decoder(nsp.MAX_MESSAGE).feed(frame)
    return nsp.decode(event.data)


def reply(dev, code, data=b"") -> nsp.Message:
    (msg,) = [decode(f) for f in frames(dev, code, data)]
    return msg


def ok(dev, code, data=b"") -> bytes:
    msg = reply(dev, code, data)
    assert msg.ack, NackInfo.unpack(msg.data)
    return msg.data


def nack(dev, code, data=b"") -> NackInfo:
    msg = reply(dev, code, data)
    assert not msg.ack
    return NackInfo.unpack(msg.data)


def fault(dev, action, script="") -> FaultStatus:
    return FaultStatus.unpack(ok(dev, Code.FAULT, FaultRequest(action, script.encode()).pack()))


def load(dev, script) -> FaultStatus:
    return fault(dev, FaultAction.LOAD, script)


def counter(dev, name: str) -> int:
    """A fault counter as flight software reads it: EDAC memory at its declared address."""
    return struct.unpack_from("<I", dev.edac_image(), edac.offset(name))[0]


def app(**kw) -> Device:
    dev = Device(fault_injection=True, **kw)
    ok(dev, Code.INIT, struct.pack("<I", 0x2000))
    return dev


def go(dev) -> None:
    ok(dev, Code.GO, Go(0x0B).pack())
    assert dev.wait_idle(30)


def sequence_of(dev) -> int:
    return int(result.parse(dev.runner.result)["sequence"])


# ------------------------------------------------------------------ the script


def test_a_script_parses_with_comments_and_defaults():
    faults = parse_script(
        "# header\n\ndrop_reply count=2   # the next two\ncorrupt_crc fraction=0.25 seed=7\n"
        "delay_reply ms=250 count=1\nreset at_go=3\nreset now\nedac_upset region=ram bits=2\n"
        "stuck_result count=1\nfrozen_detector count=0\n"
    )
    assert [f.name for f in faults] == [
        "drop_reply",
        "corrupt_crc",
        "delay_reply",
        "reset",
        "reset",
        "edac_upset",
        "stuck_result",
        "frozen_detector",
    ]
    assert [f.line for f in faults] == [3, 4, 5, 6, 7, 8, 9, 10]
    assert faults[1].keys == {"fraction": 0.25, "seed": 7} and faults[1].seed == 7 and faults[0].seed == 0
    assert faults[4].keys == {"now": True} and faults[2].keys["ms"] == 250.0


@pytest.mark.parametrize(
    ("line", "says"),
    [
        ("drop_replies count=1", "unknown fault 'drop_replies'; known: delay_reply, drop_reply"),
        ("drop_reply count=1 ms=3", "drop_reply: unknown key 'ms'"),
        ("drop_reply fraction=1.5", "fraction=1.5 outside 0..1"),
        ("drop_reply fraction=-0.1", "fraction=-0.1 outside 0..1"),
        ("drop_reply fraction=nan", "fraction=nan outside 0..1"),
        ("corrupt_crc count=-1", "count=-1 outside 0..1000000"),
        ("delay_reply ms=-5 count=1", "ms=-5 outside 0..60000"),
        ("delay_reply count=1", "delay_reply needs ms="),
        ("drop_reply", "drop_reply takes exactly one of count, fraction"),
        ("drop_reply count=1 fraction=0.5", "drop_reply takes exactly one of count, fraction"),
        ("drop_reply count=1 count=2", "count given twice"),
        ("drop_reply count", "count needs a value"),
        ("drop_reply count=two", "count='two' is not a whole number"),
        ("reset at_go=0", "at_go=0 outside 1..1000000"),
        ("reset now=1", "reset now takes no value"),
        ("reset", "reset takes exactly one of after, at_go, now"),
        ("edac_upset region=rom bits=1", "region='rom'; known: scratch, ram, result, catalog"),
        ("edac_upset region=ram bits=3", "bits='3': 1 (corrected) or 2 (uncorrectable)"),
        ("edac_upset bits=1", "edac_upset needs region= and bits="),
        ("stuck_result", "stuck_result needs count="),
    ],
)
def test_a_bad_line_is_one_error_naming_its_line(line, says):
    with pytest.raises(FaultScriptError) as exc:
        parse_script(f"# ok\ndrop_reply count=1\n{line}\n", "faults.txt")
    text = str(exc.value)
    assert text.startswith("faults.txt line 3: ") and says in text and "\n" not in text


def test_a_fraction_follows_its_seeded_stream_and_a_count_the_next_n():
    def hits(script: str, n: int) -> list[bool]:
        inj = FaultInjector()
        inj.load(parse_script(script))
        return [inj.reply(Code.PING).drop for _ in range(n)]

    drawn = random.Random(11)
    assert hits("drop_reply fraction=0.3 seed=11", 200) == [drawn.random() < 0.3 for _ in range(200)]
    assert hits("drop_reply fraction=0.3 seed=11", 200) != hits("drop_reply fraction=0.3 seed=12", 200)
    assert hits("drop_reply count=3", 6) == [True, True, True, False, False, False]
    assert hits("drop_reply fraction=0", 50) == [False] * 50 and hits("drop_reply fraction=1", 50) == [True] * 50


# ------------------------------------------------------------------ the command


def test_fault_injection_is_off_unless_asked_for():
    dev = Device()
    for data in (b"", FaultRequest(FaultAction.LOAD, b"drop_reply count=1").pack(), b"\x02"):
        info = nack(dev, Code.FAULT, data)
        assert info.reason == NackReason.NOT_SUPPORTED
        assert info.text == "fault injection is off; start st16-device with --fault-injection"
    assert dev.faults.armed == 0 and len(ok(dev, Code.PING)) > 0  # the PING reply was not dropped


def test_load_clear_status_and_their_refusals():
    dev = Device(fault_injection=True)
    st = load(dev, "drop_reply count=1\nedac_upset region=scratch bits=1 count=3\n")
    assert (st.action, st.armed, st.counters) == (FaultAction.LOAD, 4, (0,) * 9)
    bad = nack(dev, Code.FAULT, FaultRequest(FaultAction.LOAD, b"stuck_result count=1\nfrozen count=1").pack())
    assert bad.reason == NackReason.BAD_PARAMETER and bad.text.startswith("fault script line 2: unknown fault 'frozen'")
    assert nack(dev, Code.FAULT, b"\x00\xff\xfe").reason == NackReason.BAD_PARAMETER  # not UTF-8
    assert nack(dev, Code.FAULT, b"\x07").reason == NackReason.BAD_PARAMETER
    assert nack(dev, Code.FAULT, b"\x02x").reason == NackReason.BAD_LENGTH
    assert nack(dev, Code.FAULT, b"").reason == NackReason.BAD_LENGTH
    assert fault(dev, FaultAction.STATUS).armed == 4  # the refused loads armed nothing; FAULT replies are never dropped
    assert fault(dev, FaultAction.CLEAR).armed == 0
    assert len(frames(dev, Code.PING)) == 1 and counter(dev, "dropped_replies") == 0


# ------------------------------------------------------------------ reply faults


def test_drop_reply_sends_nothing_and_counts():
    dev = Device(fault_injection=True)
    load(dev, "drop_reply count=2")
    assert frames(dev, Code.PING) == [] and frames(dev, Code.PING, b"x") == []  # a NACK is a reply too
    assert len(frames(dev, Code.PING)) == 1
    assert dev.counters.per_code[Code.PING] == 3 and dev.counters.nacked == 1  # executed all the same
    assert dev.counters.replies == 1 + 1  # the messages sent: the FAULT reply and the last PING's
    assert counter(dev, "dropped_replies") == 2 == fault(dev, FaultAction.STATUS).counters[1]


def test_corrupt_crc_sends_a_frame_that_fails_its_crc():
    dev = Device(fault_injection=True)
    load(dev, "corrupt_crc count=1")
    (bad,) = frames(dev, Code.PING)
    (event,) = slip.Decoder(nsp.MAX_MESSAGE).feed(bad)
    with pytest.raises(nsp.BadCrc):
        nsp.decode(event.data)
    assert "BOOTLOADER" in ok(dev, Code.PING).decode()
    assert counter(dev, "corrupted_crcs") == 1


def test_delay_reply_waits_its_ms_before_the_reply():
    dev = Device(fault_injection=True)
    waits: list[float] = []
    dev.sleep = waits.append
    load(dev, "delay_reply ms=250 count=1")
    assert len(frames(dev, Code.PING)) == 1 and len(frames(dev, Code.PING)) == 1
    assert waits == [0.25] and counter(dev, "delayed_replies") == 1


# ------------------------------------------------------------------ sequences


def test_stuck_result_repeats_the_sequence_number_and_the_result():
    dev = app()
    go(dev)
    first = dev.runner.result
    load(dev, "stuck_result count=1")
    go(dev)
    assert sequence_of(dev) == 1 and dev.runner.result == first and dev.runner.result_ready
    assert struct.unpack_from("<I", dev.edac_image(), 0x54)[0] == 1  # the EDAC sequence number too
    go(dev)
    assert sequence_of(dev) == 2 and counter(dev, "stuck_results") == 1


def test_frozen_detector_hands_the_solver_the_previous_frame():
    seen = []
    shots = iter(range(100, 200))

    def solver(ctx):
        seen.append(ctx.frame)
        return {"return_code": result.make_return_code(result.Status.OK)}

    dev = app(solver=solver, frame_source=lambda ctx: next(shots))
    ok(dev, Code.XFER_BEGIN, XferBegin(Slot.CATALOG, 4, crc32(b"cat!")).pack())
    ok(dev, Code.XFER_DATA, XferData(Slot.CATALOG, 0, b"cat!").pack())
    ok(dev, Code.XFER_COMMIT, SlotRequest(Slot.CATALOG).pack())
    go(dev)
    load(dev, "frozen_detector count=2")
    go(dev)
    go(dev)
    go(dev)
    assert seen == [100, 100, 100, 101] and counter(dev, "frozen_frames") == 2


# ------------------------------------------------------------------ resets


def test_reset_after_n_commands_goes_back_to_the_bootloader_keeping_slots_and_fault_counters():
    dev = app()
    ok(dev, Code.XFER_BEGIN, XferBegin(Slot.PARAMS, 2, crc32(b"{}")).pack())
    ok(dev, Code.XFER_DATA, XferData(Slot.PARAMS, 0, b"{}").pack())
    ok(dev, Code.XFER_COMMIT, SlotRequest(Slot.PARAMS).pack())
    go(dev)
    load(dev, "drop_reply count=1\nreset after=3")
    assert frames(dev, Code.PING) == []  # command 1, its reply dropped
    ok(dev, Code.WRITE_EDAC, WriteEdac(0x100, b"\xaa\xbb").pack())  # command 2
    assert "APPLICATION" in ok(dev, Code.PING).decode()  # command 3: answered, then the reset
    assert "BOOTLOADER" in ok(dev, Code.PING).decode()
    image = dev.edac_image()
    assert image[0x100:0x102] == b"\0\0" and struct.unpack_from("<I", image, 0x54)[0] == 0  # scratch, sequence
    assert dev.counters.accepted == 1  # the PING since the reset, as after a restart
    assert result.status_of(int(result.parse(dev.runner.result)["return_code"])) == result.Status.NO_RESULT
    assert SlotImage.unpack(ok(dev, Code.SLOT_INFO, SlotRequest(Slot.PARAMS).pack())).active
    assert counter(dev, "resets") == 1 and counter(dev, "dropped_replies") == 1  # kept across the reset


def test_reset_at_the_nth_go_leaves_it_unanswered():
    dev = app()
    load(dev, "reset at_go=2")
    go(dev)
    assert frames(dev, Code.GO, Go(0x0B).pack()) == []
    assert "BOOTLOADER" in ok(dev, Code.PING).decode() and sequence_of(dev) == 0
    assert counter(dev, "resets") == 1


def test_reset_now_answers_the_fault_command_first():
    dev = app()
    assert load(dev, "reset now").action == FaultAction.LOAD
    assert "BOOTLOADER" in ok(dev, Code.PING).decode() and counter(dev, "resets") == 1


# ------------------------------------------------------------------ EDAC upsets


def test_single_bit_upsets_are_corrected_on_the_next_read():
    dev = Device(fault_injection=True)
    pattern = bytes(range(256))
    ok(dev, Code.WRITE_EDAC, WriteEdac(0x100, pattern).pack())
    assert load(dev, "edac_upset region=scratch bits=1 count=64").armed == 64  # every word
    assert ok(dev, Code.READ_EDAC, ReadRange(0x100, 256, long=True).pack())[2:] == pattern
    assert counter(dev, "edac_corrected") == 64 and dev.faults.armed == 0
    ok(dev, Code.READ_EDAC, ReadRange(0x100, 256, long=True).pack())
    assert counter(dev, "edac_corrected") == 64  # scrubbed: counted once


def test_a_double_bit_upset_nacks_every_read_until_the_word_is_written():
    dev = Device(fault_injection=True)
    load(dev, "edac_upset region=ram bits=2 seed=5")
    ((word, bits),) = dev.faults.upset_words("ram").items()
    assert bits == 2 and [word] == draw_words(5, 0x10000 // 4, 1).tolist()
    address = RAM_BASE + 4 * word
    for _ in range(2):
        info = nack(dev, Code.PEEK, Peek(address - 2, 4).pack())
        assert info.reason == NackReason.EDAC_UNCORRECTABLE and f"0x{4 * word:X}" in info.text
    assert ok(dev, Code.PEEK, Peek(address + 4, 4).pack())  # the next word reads
    ok(dev, Code.POKE, Poke(address, b"\1\2\3\4").pack())
    assert ok(dev, Code.PEEK, Peek(address, 4).pack())[4:] == b"\1\2\3\4"
    assert counter(dev, "edac_uncorrectable") == 2


def test_a_double_bit_upset_in_the_result_lasts_until_the_next_sequence():
    dev = app()
    load(dev, "edac_upset region=result bits=2 count=1030")  # every word
    assert nack(dev, Code.READ_RESULT, ReadRange(0, 8).pack()).reason == NackReason.EDAC_UNCORRECTABLE
    assert nack(dev, Code.PEEK, Peek(RESULT_BASE, 4).pack()).reason == NackReason.EDAC_UNCORRECTABLE
    go(dev)
    assert ok(dev, Code.READ_RESULT, ReadRange(0, 8).pack())
    assert counter(dev, "edac_uncorrectable") == 2 + 1  # one per bad word read: READ RESULT 2, PEEK 1


def test_a_double_bit_catalog_upset_reloads_the_catalog_before_the_solve():
    loads = []

    def activate(data: bytes) -> bytes:
        loads.append(data)
        return data

    dev = app(slots={Slot.CATALOG: SlotHandler(lambda d: None, activate)})
    image = b"catalog image"
    ok(dev, Code.XFER_BEGIN, XferBegin(Slot.CATALOG, len(image), crc32(image)).pack())
    ok(dev, Code.XFER_DATA, XferData(Slot.CATALOG, 0, image).pack())
    ok(dev, Code.XFER_COMMIT, SlotRequest(Slot.CATALOG).pack())
    load(dev, "edac_upset region=catalog bits=1\nedac_upset region=catalog bits=2 seed=1")
    go(dev)
    assert loads == [image, image]  # the commit, then the reload
    assert [counter(dev, n) for n in ("edac_corrected", "edac_uncorrectable", "catalog_reloads")] == [1, 1, 1]
    go(dev)
    assert len(loads) == 2


# ------------------------------------------------------------------ fuzz traffic


def test_fuzz_traffic_never_arms_a_fault_on_a_default_device():
    from ground.testing.traffic import burst, command_frame, sweep

    rng = random.Random(33)
    dev = Device()
    answers = []
    for frame in sweep(rng) + [command_frame(rng, Code.FAULT, poll=True) for _ in range(200)]:
        answers += [decode(f) for f in dev.receive(frame)]
    for _ in range(20):
        dev.receive(burst(rng, 200)[0])
    faults = [m for m in answers if m.code == Code.FAULT]
    assert len(faults) > 100 and all(NackInfo.unpack(m.data).reason == NackReason.NOT_SUPPORTED for m in faults)
    assert dev.faults.armed == 0 and set(dev.faults.counters.values()) == {0}
    assert dev.edac_image()[edac.FAULT_COUNTERS_AT : edac.FAULT_COUNTERS_AT + 36] == bytes(36)


def test_st16_ground_refuses_a_script_too_long_for_one_fault_load(tmp_path, capsys):
    from ground.cli.main import main

    long = tmp_path / "long.txt"
    long.write_text("# pad\n" * 1000)  # 6000 bytes, every line a comment: it parses
    with pytest.raises(SystemExit) as exit_:  # argparse's refusal, before the port is opened
        main(["--port", "loop://", "fault", "load", str(long)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and "6000 bytes, one FAULT load carries at most 4159" in err


# ------------------------------------------------------------------ issue 40: resets, counters, delays, bounds


def late_replies(dev) -> list[bytes]:
    """Frames the device hands its transport later (a COMBINATION's, a delayed reply), as the
    link's ``serve`` would write them."""
    sent: list[bytes] = []
    dev.late_reply = sent.extend
    return sent


def catalog(dev, image: bytes) -> None:
    ok(dev, Code.XFER_BEGIN, XferBegin(Slot.CATALOG, len(image), crc32(image)).pack())
    ok(dev, Code.XFER_DATA, XferData(Slot.CATALOG, 0, image).pack())
    ok(dev, Code.XFER_COMMIT, SlotRequest(Slot.CATALOG).pack())


def join_reply_threads() -> None:
    for thread in threading.enumerate():
        if thread.name.startswith("reply-"):
            thread.join(guards.HANG_S)
            assert not thread.is_alive()


@pytest.mark.timeout(guards.HANG_S)
def test_no_reply_to_a_combination_received_before_a_reset():
    release = threading.Event()

    def solver(ctx):
        release.wait(guards.HANG_S)
        return {"return_code": result.make_return_code(result.Status.OK)}

    dev = app(solver=solver, frame_source=lambda ctx: 1)
    catalog(dev, b"cat!")
    sent = late_replies(dev)
    load(dev, "reset after=2")
    assert frames(dev, Code.COMBINATION, Combination(0x0B, 0x1).pack()) == []  # command 1: its reply waits
    assert "APPLICATION" in ok(dev, Code.PING).decode()  # command 2: answered, then the reset
    join_reply_threads()
    release.set()
    assert sent == []  # the ICD: a reset loses what was in flight (it used to be ACKed, sequence 0, NO_RESULT)
    assert "BOOTLOADER" in ok(dev, Code.PING).decode() and counter(dev, "resets") == 1
    assert Diagnostics.unpack(ok(dev, Code.DIAGNOSTIC, DiagnosticRequest().pack())).replies == 1  # the PING's


def test_a_dropped_reply_before_a_reset_never_takes_a_counter_below_zero():
    dev = app()
    load(dev, "reset after=1\ndrop_reply count=1")
    assert frames(dev, Code.PING) == []  # command 1: executed, its reply dropped, then the reset
    diag = Diagnostics.unpack(ok(dev, Code.DIAGNOSTIC, DiagnosticRequest().pack()))
    assert diag.replies == 0 and diag.accepted == 1  # it used to read 4294967295: 0 - 1
    assert dev.counters.replies == 1 and counter(dev, "dropped_replies") == 1 == counter(dev, "resets")


def test_a_new_catalog_image_rewrites_the_upset_words():
    loads = []

    def activate(data: bytes) -> bytes:
        loads.append(data)
        return data

    dev = app(slots={Slot.CATALOG: SlotHandler(lambda d: None, activate)})
    catalog(dev, b"old catalog image")
    assert load(dev, "edac_upset region=catalog bits=2 count=2\nedac_upset region=catalog bits=1 seed=4").armed >= 2
    catalog(dev, b"the new catalog image")  # a COMMIT writes every word of the catalog
    assert fault(dev, FaultAction.STATUS).armed == 0
    go(dev)
    assert loads == [b"old catalog image", b"the new catalog image"]  # no reload
    assert [counter(dev, n) for n in ("edac_corrected", "edac_uncorrectable", "catalog_reloads")] == [0, 0, 0]


@pytest.mark.timeout(guards.HANG_S)
def test_a_delayed_reply_is_sent_later_while_the_device_serves_on():
    dev = Device(fault_injection=True)
    sent = late_replies(dev)
    waits: list[float] = []
    dev.sleep = waits.append  # never called: the device does not wait when a transport takes late replies
    arrived = threading.Event()
    dev.late_reply = lambda f: (sent.extend(f), arrived.set())
    load(dev, "delay_reply ms=50 count=1")
    assert frames(dev, Code.PING) == []  # held back
    assert len(frames(dev, Code.PING)) == 1  # the next command is served meanwhile
    assert arrived.wait(guards.HANG_S)
    assert [decode(f).code for f in sent] == [Code.PING] and waits == []
    assert counter(dev, "delayed_replies") == 1 and dev.counters.replies == 1 + 2  # FAULT, both PINGs


@pytest.mark.timeout(guards.HANG_S)
def test_fault_clear_and_a_reset_drop_the_delayed_replies_still_waiting():
    dev = app()
    sent = late_replies(dev)
    load(dev, "delay_reply ms=60000 fraction=1")
    for _ in range(3):
        assert frames(dev, Code.PING) == []
    assert len(dev.faults.delayed) == 3 and dev.counters.replies == 2 + 3  # INIT, FAULT and the PINGs'
    assert fault(dev, FaultAction.CLEAR).armed == 0  # answered at once (it used to wait 3 x 60 s)
    assert len(dev.faults.delayed) == 0 and dev.counters.replies == 2 + 1  # the PINGs' never sent
    load(dev, "delay_reply ms=60000 fraction=1")
    assert frames(dev, Code.PING) == []
    load(dev, "reset now")
    assert len(dev.faults.delayed) == 0 and sent == []
    assert counter(dev, "delayed_replies") == 4


def test_a_delayed_reply_that_finds_the_queue_full_is_dropped():
    dev = Device(fault_injection=True)
    late_replies(dev)
    load(dev, "delay_reply ms=60000 fraction=1")
    for _ in range(MAX_DELAYED + 2):
        assert frames(dev, Code.PING) == []
    assert len(dev.faults.delayed) == MAX_DELAYED and counter(dev, "dropped_replies") == 2
    fault(dev, FaultAction.CLEAR)
    assert dev.counters.replies == 2  # nothing of the PINGs was sent


def test_delayed_replies_go_in_due_order_and_a_drop_calls_unsent():
    """No clock decides the outcome: the queue's one sender is held in a reply's ``send`` by a gate
    while the others are queued, with due times in the past (already due, in a known order) or an
    hour ahead (never due within the test)."""
    queue = DelayedReplies(limit=3)
    sent, unsent, gate = [], [], threading.Event()

    def held():
        assert gate.wait(guards.HANG_S)
        sent.append("held")

    def until(condition):
        for _ in range(int(guards.HANG_S / 0.01)):  # a hang guard polling the queue
            if condition():
                return
            threading.Event().wait(0.01)
        raise AssertionError("the delayed-reply sender hung")

    assert queue.add(0.0, held, lambda: unsent.append("held"))
    until(lambda: len(queue) == 0)  # the sender holds it, waiting on the gate
    assert queue.add(3600.0, lambda: sent.append("late"), lambda: unsent.append("late"))
    assert queue.add(-500.0, lambda: sent.append("second"), lambda: unsent.append("second"))
    assert queue.add(-1000.0, lambda: sent.append("first"), lambda: unsent.append("first"))  # due before "second"
    assert not queue.add(-2000.0, lambda: sent.append("full"), lambda: unsent.append("full"))  # 3 wait: refused
    gate.set()
    until(lambda: len(queue) == 1)
    until(lambda: len(sent) == 3)
    assert sent == ["held", "first", "second"]
    assert queue.add(3600.0, lambda: None, lambda: unsent.append("after"))  # a sent reply frees its place
    assert queue.drop() == 2 and sorted(unsent) == ["after", "late"] and len(queue) == 0


def test_upset_words_are_distinct_seeded_and_cheap_to_place():
    for n, k in [(1, 1), (10, 5), (10, 6), (128, 128), (16384, 3), (1 << 24, 200_000)]:
        words = draw_words(7, n, k)
        assert words.size == k and len(set(words.tolist())) == k and 0 <= words.min() and words.max() < n
        assert words.tolist() == draw_words(7, n, k).tolist()  # seeded
        assert k == n or words.tolist() != draw_words(8, n, k).tolist()
    inj = FaultInjector(lambda region: 1 << 24 if region == "catalog" else 0)  # a 64 MiB catalog
    inj.load(parse_script(f"edac_upset region=catalog bits=2 count={MAX_UPSET_WORDS}"))
    assert inj.armed == MAX_UPSET_WORDS and inj.catalog_access() and inj.armed == 0
    assert inj.counters["edac_uncorrectable"] == MAX_UPSET_WORDS


@pytest.mark.timeout(guards.HANG_S)
def test_a_script_places_at_most_a_million_upset_words_in_all():
    line = "edac_upset region=catalog bits=1 count=1000000 seed={}\n"
    script = "".join(line.format(i) for i in range(75))[:4159]  # the whole FAULT data field
    with pytest.raises(FaultScriptError) as exc:
        parse_script(script, "faults.txt")
    assert str(exc.value) == (
        "faults.txt line 2: edac_upset: the script's upsets add up to 2000000 words, over the 1000000 one script may place"
    )
    dev = Device(fault_injection=True)
    dev.store.set_active(Slot.CATALOG, bytes(1_711_896))  # a 1.7 MB catalog: 427 974 words
    info = nack(dev, Code.FAULT, FaultRequest(FaultAction.LOAD, script.encode()).pack())
    assert info.reason == NackReason.BAD_PARAMETER and "add up to 2000000 words" in info.text
    assert load(dev, line.format(0)).armed == 1_711_896 // 4  # count above the words: every word
    assert len(frames(dev, Code.PING)) == 1
