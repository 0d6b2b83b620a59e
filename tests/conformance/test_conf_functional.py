"""The functional processor's commands: GO (1-35916, 1-35924), READ RESULT and IMAGE (1-35917),
COMBINATION (1-35918), the result's telemetry (1-35920 as paraphrased in
../shared/research/st16_icd_vs_emulator.md, 1-35924) and the cadence (1-35923)."""

import math
import string
import struct
import time

import pytest

from .icd import (
    BAD_LENGTH,
    COMBINATION,
    GO,
    GO_COMMAND,
    GO_INJECTED,
    GO_LOAD_NAND,
    GO_ON,
    HARDWARE,
    IMAGE,
    MATCHING,
    MATCHING_SIZE,
    OUT_OF_RANGE,
    dark_window,
    init_application,
    read_edac,
    read_result,
    rectangular_poke,
    result_bytes,
    result_length,
    time_us,
    wait_result_ready,
)
from .nsp_min import HANG_S

pytestmark = pytest.mark.timeout(180)

GO_SEQUENCE = GO_ON | GO_COMMAND  # 0x09: run a sequence
SEQUENCE_STATES = {0, 1, 2, 3}  # ours: IDLE, RUNNING, DONE, TERMINATED (the page's Table 32 is not visible)
RUNNING = 1


def combination(go_code: int, mask: int) -> bytes:
    """COMBINATION data (ours where the page shows none): u8 go code + u32 section mask."""
    return struct.pack("<BI", go_code, mask)


def printable(text: bytes) -> bool:
    return bool(text) and all(chr(c) in string.printable for c in text)


def run_sequence(link) -> None:
    """GO with COMMAND, then the result length polled until ready (a hang guard only)."""
    assert link.one(GO, bytes((GO_SEQUENCE,))).ack
    wait_result_ready(link)


# -- GO ---------------------------------------------------------------------------------------------


def test_conf_go_starts_a_sequence(app):
    """1-35916, GO (0x0B): "The Go Code command starts (or terminates) a star tracker sequence."
    A GO with COMMAND is acknowledged with its code and a new result follows (its sequence
    number, the result's first u32 [COSMOS overlay], advances by one)."""
    before = struct.unpack("<I", result_bytes(app, 0, 4))[0]
    msg = app.one(GO, bytes((GO_SEQUENCE,)))
    assert msg.ack and msg.data == bytes((GO_SEQUENCE,))
    wait_result_ready(app)
    assert struct.unpack("<I", result_bytes(app, 0, 4))[0] == before + 1


def test_conf_go_without_command_when_idle_is_a_no_op(app):
    """1-35916: GO "starts (or terminates)" a sequence; with nothing running, a GO without the
    COMMAND bit has nothing to terminate: acknowledged (the lead's spec: a no-op ACK), and the
    result stays."""
    run_sequence(app)
    before = result_bytes(app, 0, 4)
    assert app.one(GO, bytes((GO_ON,))).ack
    assert result_length(app) != 0 and result_bytes(app, 0, 4) == before


def test_conf_go_terminates_a_running_sequence(start_device):
    """1-35916: GO "starts (or terminates) a star tracker sequence." A sequence held 20 s
    (``--timing realistic --processing-ms 20000``) is terminated by a GO without COMMAND: the
    next GO with COMMAND is accepted at once (not refused as busy), and is terminated the same
    way."""
    link = start_device("--timing", "realistic", "--processing-ms", "20000").link
    assert init_application(link).ack
    assert link.one(GO, bytes((GO_SEQUENCE,))).ack
    assert not link.one(GO, bytes((GO_SEQUENCE,))).ack  # one sequence at a time
    assert link.one(GO, bytes((GO_ON,))).ack  # terminate
    assert link.one(GO, bytes((GO_SEQUENCE,))).ack
    assert link.one(GO, bytes((GO_ON,))).ack


def test_conf_go_bit_1_boots_the_application_from_the_bootloader(boot):
    """1-35916: "If bit 1 is set the functional processor will load its bootloader from NAND
    flash (blocks 0, 1, 2 or 3). It will then immediately attempt to load and execute an
    Application Module image from block 0x8000"; the COMBINATION failure text "may be the ASIC ID
    message" (1-35918). In bootloader mode a GO with bit 1 leaves an ASIC ID message in EDAC and
    the application then runs (IMAGE, application-only, is accepted). Polled, a hang guard."""
    assert not boot.one(IMAGE, dark_window(0, 0, 0, 1, 1)).ack
    assert boot.one(GO, bytes((GO_LOAD_NAND,))).ack
    deadline = time.monotonic() + HANG_S
    while b"ASIC ID" not in read_edac(boot, 0, 512, long=True):
        assert time.monotonic() < deadline, "no ASIC ID message in EDAC within the hang guard"
        time.sleep(0.05)
    while not boot.one(IMAGE, dark_window(0, 0, 0, 1, 1)).ack:
        assert time.monotonic() < deadline, "the application did not start within the hang guard"
        time.sleep(0.05)


# -- READ RESULT ----------------------------------------------------------------------------------


def test_conf_read_result_short_count_0_reads_256_bytes(app):
    """1-35917, READ RESULT short form: "Bytes 0 - 1 Result address to start reading; Byte 2
    Number of bytes to read. A value of 0 indicates that 256 bytes should be read." Reply: "Bytes
    0 - 1 Result address where reading started; Bytes 2 - N The data bytes"."""
    msgs = read_result(app, 0x0040, 0, long=False)
    assert all(m.ack for m in msgs) and msgs[-1].final
    assert struct.unpack("<H", msgs[0].data[:2])[0] == 0x0040
    assert sum(len(m.data) - 2 for m in msgs) == 256


def test_conf_read_result_long_form_and_multi_message_reply(app):
    """1-35917, READ RESULT long form: "Bytes 0 - 1 Result address to start reading; Byte 2 - 3
    Number of bytes to read." 1-35910: "If a reply is too large to fit into a single message then
    the final message has the bit set to '1' and the others have the bit cleared to '0'." 2616
    bytes (the standard structure) come in several messages, Final on the last only; the first
    starts at the requested address; the data add up to the count."""
    msgs = read_result(app, 0x0000, 2616)
    assert len(msgs) > 1
    assert all(m.ack for m in msgs)
    assert [m.final for m in msgs] == [False] * (len(msgs) - 1) + [True]
    assert struct.unpack("<H", msgs[0].data[:2])[0] == 0
    assert sum(len(m.data) - 2 for m in msgs) == 2616


# -- IMAGE ----------------------------------------------------------------------------------------


def test_conf_image_allowed_only_in_application_mode(boot):
    """1-35917, IMAGE (0x10): "This is allowed only in application mode." Refused (ACK 0) in
    bootloader mode, accepted after INIT."""
    field = dark_window(1, 10, 10, 2, 2)
    assert not boot.one(IMAGE, field).ack
    assert init_application(boot).ack
    assert boot.one(IMAGE, field).ack


def test_conf_dark_window_reply_is_an_echo(app):
    """1-35917, Dark Window: "The reply is simply an echo of the command." (26 bytes: subcommand 0,
    buffer, first row, first column, rows, columns, dark values 0-7)."""
    field = dark_window(0, 100, 200, 3, 4, (11, 12, 13, 14, 15, 16, 17, 18))
    assert len(field) == 26
    msg = app.one(IMAGE, field)
    assert msg.ack and msg.data == field


def test_conf_dark_window_out_of_range_is_nacked(app):
    """1-35917, Dark Window: "NACK is returned if any of the parameters is out of range." A window
    starting at row 0xFFF0 lies outside any sensor."""
    assert not app.one(IMAGE, dark_window(0, 0xFFF0, 0, 1, 1)).ack


def test_conf_image_reserved_subcommands_are_nacked(app):
    """1-35917, Table 28: subcommand "2+ Reserved"."""
    assert not app.one(IMAGE, bytes((2,)) + dark_window(0, 0, 0, 1, 1)[1:]).ack
    assert not app.one(IMAGE, bytes((0xFF,))).ack


def test_conf_rectangular_poke_accepted_and_echoes_its_header(app):
    """1-35917, Table 28: subcommand 1 "Rectangular Poke" (its format is not in the public copy;
    layout ours, issue 39: 10-byte header + rows x columns u16 pixels); the reply echoes the
    header."""
    field = rectangular_poke(0, 10, 20, 2, 3)
    msg = app.one(IMAGE, field)
    assert msg.ack and msg.data == field[:10]


def test_conf_rectangular_poke_of_the_wrong_length_is_nacked(app):
    """Rectangular Poke (layout ours): 2 x 3 announced, 5 pixels sent: NACK BAD_LENGTH."""
    field = rectangular_poke(0, 10, 20, 2, 3)[:-2]
    msg = app.one(IMAGE, field)
    assert not msg.ack and msg.nack_reason == BAD_LENGTH


def test_conf_rectangular_poke_outside_the_sensor_is_nacked(app):
    """1-35917 (Dark Window's rule, "NACK is returned if any of the parameters is out of range",
    applied to the poke: ours): a rectangle from row 0xFFF0 is NACKed OUT_OF_RANGE."""
    msg = app.one(IMAGE, rectangular_poke(0, 0xFFF0, 0, 1, 1))
    assert not msg.ack and msg.nack_reason == OUT_OF_RANGE


def test_conf_go_processes_an_injected_image_buffer(app):
    """Image injection through the link (issue 39, ours): after a Rectangular Poke into buffer 0,
    a GO with bit 0x40 processes that buffer instead of exposing; a result follows."""
    assert app.one(IMAGE, rectangular_poke(0, 0, 0, 4, 4)).ack
    assert app.one(GO, bytes((GO_INJECTED | GO_SEQUENCE,))).ack
    wait_result_ready(app)


# -- COMBINATION ----------------------------------------------------------------------------------


def test_conf_combination_success_acked_final_on_last(app):
    """1-35918, COMBINATION "Successful Reply Format": "For a success, the ACK bit will be set to
    '1'. The number of reply messages generated depends on the amount of data requested. The
    final message will have the PF bit set to '1'. All other reply messages will have the PF bit
    set to '0'." Centroid (832 bytes) + matching (352 bytes) telemetry, go code 0 (no
    sequence)."""
    msgs = app.request(COMBINATION, combination(0x00, 0x0200 | 0x0400))
    assert all(m.ack for m in msgs)
    assert [m.final for m in msgs] == [False] * (len(msgs) - 1) + [True]
    assert sum(len(m.data) - 2 for m in msgs) == 832 + 352


def test_conf_combination_success_parts_count_bytes_already_transmitted(app):
    """1-35918, COMBINATION "Successful Reply Format": "Bytes 0 - 1 Number of bytes already
    transmitted; Bytes 2 - N Result telemetry data". Each message's first two bytes count the
    telemetry bytes the earlier messages of the reply carried (0 for the first)."""
    msgs = app.request(COMBINATION, combination(0x00, 0x0200 | 0x0400))
    sent = 0
    for m in msgs:
        assert struct.unpack("<H", m.data[:2])[0] == sent, [struct.unpack("<H", x.data[:2])[0] for x in msgs]
        sent += len(m.data) - 2


def test_conf_combination_failure_reply_for_the_self_test_section(app):
    """1-35918, COMBINATION "Failure Reply Format": "Bytes 0 Sequence state; Bytes 1 - N Error
    message [...] The ACK bit will be set to '0' [...] Only one failure reply message will be
    generated, and the PF bit is set to '1'." The self-test section (0x0800) is not produced (the
    lead's spec), so it fails: state byte (ours: 0-3), then ASCII text."""
    msgs = app.request(COMBINATION, combination(0x00, 0x0800))
    assert len(msgs) == 1
    (msg,) = msgs
    assert not msg.ack and msg.final
    assert msg.data[0] in SEQUENCE_STATES and printable(msg.data[1:]), msg.data


def test_conf_combination_while_a_sequence_runs_fails_with_state_running(start_device):
    """1-35918: "If the functional processor stops before generating the full set of data
    required by the COMBINATION command, a failure reply will be generated." While a sequence
    runs (held 20 s), a COMBINATION with COMMAND gets one message, ACK 0, PF 1, state RUNNING
    (ours: 1), then text."""
    link = start_device("--timing", "realistic", "--processing-ms", "20000").link
    assert init_application(link).ack
    assert link.one(GO, bytes((GO_SEQUENCE,))).ack
    msgs = link.request(COMBINATION, combination(GO_SEQUENCE, 0x0001))
    assert len(msgs) == 1
    (msg,) = msgs
    assert not msg.ack and msg.final and msg.data[0] == RUNNING and printable(msg.data[1:]), msg.data
    assert link.one(GO, bytes((GO_ON,))).ack  # terminate


# -- the result's telemetry -----------------------------------------------------------------------


def test_conf_matching_telemetry_quaternion_and_attitude_covariance(app):
    """1-35920 (paraphrased in st16_icd_vs_emulator.md row 4; the page itself was not retrieved
    for this suite): matching telemetry +0x60 the inertial quaternion, scalar first, four f64;
    +0x80 six f64, the upper triangle of the attitude covariance. Two records of 176 bytes at
    result 0x7E8 [COSMOS overlay]: every number finite, the quaternion zero (no attitude) or of
    unit norm, the covariance's diagonal (xx, yy, zz: elements 0, 3, 5 of the upper triangle
    row by row) not negative."""
    run_sequence(app)
    raw = result_bytes(app, MATCHING, 2 * MATCHING_SIZE)
    for i in range(2):
        rec = raw[i * MATCHING_SIZE : (i + 1) * MATCHING_SIZE]
        q = struct.unpack_from("<4d", rec, 0x60)
        cov = struct.unpack_from("<6d", rec, 0x80)
        assert all(math.isfinite(v) for v in (*q, *cov)), (q, cov)
        norm = math.sqrt(sum(v * v for v in q))
        assert norm == 0 or abs(norm - 1) < 1e-6, q
        assert min(cov[0], cov[3], cov[5]) >= 0, cov


def test_conf_hardware_telemetry_begins_with_flash_error_counts(app):
    """1-35924, "Periodic Flash Rebuild": "The current health of the NAND flash can be estimated
    by reading the flash error counts at the beginning of the hardware telemetry." The layout is
    not shown (the emulator's: three u32 at result 0x048: ECC corrected, ECC uncorrectable, bad
    blocks). A fresh unit's counts are counts: small whole numbers, the same in two results with
    no flash work between them."""
    run_sequence(app)
    first = struct.unpack("<3I", result_bytes(app, HARDWARE, 12))
    run_sequence(app)
    again = struct.unpack("<3I", result_bytes(app, HARDWARE, 12))
    assert all(n < 1 << 20 for n in first), first
    assert again[1:] == first[1:], (first, again)  # uncorrectable errors and bad blocks do not appear by themselves


def test_conf_realistic_timing_cycles_at_about_2_hz_at_most(start_device):
    """1-35923: "If the star tracker is cycling at its maximum rate (~2 Hz) it may accumulate
    172,800 cycles in a day." With ``--timing realistic`` and its defaults (the real unit's cycle,
    issue 39), three back-to-back GO-to-result cycles take at least 3 x 0.45 s on the device's
    own clock (TIME): a lower bound, which a loaded machine cannot break."""
    link = start_device("--timing", "realistic").link
    assert init_application(link).ack
    start = time_us(link)
    for _ in range(3):
        run_sequence(link)
    cycle_s = (time_us(link) - start) / 3e6
    assert cycle_s >= 0.45, f"{cycle_s:.3f} s per cycle: faster than ~2 Hz"
