"""Scripted faults through ``st16-device`` as a separate process on a pty (docs/ICD.md section 13):
each fault driven through the link, the reply the protocol promises checked, and the EDAC counter
that tells flight software the fault happened. Also the one-line refusals of a bad script on both
command lines, and FAULT on a device without ``--fault-injection``."""

import json
import signal
import struct
import subprocess
import time

import numpy as np
import pytest

from ground.cli.main import main as ground_main
from ground.link.client import Client, MalformedReply, Nack, ReplyTimeout
from ground.testing.device_proc import DeviceProcess, device_command, tracebacks
from protocol import edac, nsp, result, slip
from protocol.commands import Code, Combination, FaultAction, NackReason, Slot
from protocol.crc import crc32
from tests import guards

#: A client's wait for a reply the device is scripted never to send (a dropped reply): how long it
#: waits changes only how long the test takes. Every reply that must come is waited for with
#: guards.REPLY_S and its retries, so no clock decides an outcome on a loaded machine.
SHORT_S = 0.5


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """A catalog image and a folder of two rendered frames of the default camera."""
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_to_image
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.sim.device_process import pick_attitudes
    from ground.sim.frame_writer import write_rendered
    from ground.sim.sensor_sim import DetectorModel, render_frame
    from ground.sim.sky_model import sky_stars

    root = tmp_path_factory.mktemp("faults")
    camera = CameraModel.reference_design()
    catalog = build_catalog(CatalogDesign())
    (root / "frames").mkdir()
    for i, a in enumerate(pick_attitudes(catalog, camera, 2, np.random.default_rng(33))):
        frame = render_frame(sky_stars(), a, camera, DetectorModel(pattern="RGGB"), seed=200 + i)
        write_rendered(frame, root / "frames" / f"f{i}.dng")
    return {"image": catalog_to_image(catalog), "root": root}


@pytest.fixture(scope="module")
def device(field):
    """A device with fault injection, a state folder and the frames as its capture source, the
    catalog uploaded; its pty path."""
    args = ("--pty", "--fault-injection", "--state", str(field["root"] / "state"))
    with DeviceProcess(*args, "--frames", str(field["root"] / "frames"), "--loop") as dev:
        with Client(dev.path, timeout=guards.REPLY_S) as c:
            c.upload(Slot.CATALOG, field["image"], progress=False)
        yield dev.path
        assert dev.alive


@pytest.fixture
def client(device):
    """A client of the device in application mode with no fault armed."""
    with Client(device, timeout=guards.REPLY_S) as c:
        c.fault(FaultAction.CLEAR)
        if "BOOTLOADER" in c.ping():
            c.init()
        yield c


def counters(c: Client) -> dict[str, int]:
    """The fault counters as flight software reads them: EDAC 0x009C, nine u32."""
    raw = c.read_edac(edac.FAULT_COUNTERS_AT, 4 * len(edac.FAULT_COUNTERS))
    return dict(zip(edac.FAULT_COUNTERS, struct.unpack(f"<{len(edac.FAULT_COUNTERS)}I", raw)))


def counted(c: Client, before: dict[str, int]) -> dict[str, int]:
    """The counters that moved since ``before``, by how much."""
    return {k: v - before[k] for k, v in counters(c).items() if v != before[k]}


def test_a_delayed_reply_arrives_no_earlier_than_its_delay(client):
    before = counters(client)
    assert client.fault(FaultAction.LOAD, "delay_reply ms=300 count=1").armed == 1
    t0 = time.monotonic()
    assert "APPLICATION" in client.ping()
    assert time.monotonic() - t0 >= 0.3  # a lower bound only
    assert counted(client, before) == {"delayed_replies": 1}


def test_a_dropped_reply_times_the_host_out(device, client):
    before = counters(client)
    client.fault(FaultAction.LOAD, "drop_reply count=1")
    with Client(device, timeout=SHORT_S, retries=0) as once:
        with pytest.raises(ReplyTimeout):
            once.ping()
    with Client(device, timeout=guards.REPLY_S) as after:
        assert "APPLICATION" in after.ping()  # the next command is answered: one reply dropped
    assert counted(client, before) == {"dropped_replies": 1}


def test_a_corrupted_crc_is_a_bad_crc_to_the_client_and_no_answer(device, client):
    before = counters(client)
    client.fault(FaultAction.LOAD, "corrupt_crc count=1")
    with Client(device, timeout=guards.REPLY_S, retries=0) as once:  # the corrupted reply comes: no retry
        with pytest.raises(MalformedReply, match="bad CRC|CRC"):
            once.ping()
        assert once.bad_crcs == 1
        assert "APPLICATION" in once.ping() and once.bad_crcs == 1
    assert counted(client, before) == {"corrupted_crcs": 1}


def test_a_stuck_result_repeats_its_sequence_number(client):
    first = client.go_and_wait(timeout=guards.HANG_S)
    raw = client.read_result()  # the bytes (a parsed record's padding is not the device's)
    before = counters(client)
    client.fault(FaultAction.LOAD, "stuck_result count=1")
    again = client.go_and_wait(timeout=guards.HANG_S)
    assert int(again["sequence"]) == int(first["sequence"]) and client.read_result() == raw
    assert int(client.go_and_wait(timeout=guards.HANG_S)["sequence"]) == int(first["sequence"]) + 1
    assert counted(client, before) == {"stuck_results": 1}


def test_a_reset_returns_to_the_bootloader_with_the_catalog_kept(field, client):
    before = counters(client)
    client.fault(FaultAction.LOAD, "reset after=1")
    assert "APPLICATION" in client.ping()  # the first command is answered, then the device resets
    assert "BOOTLOADER" in client.ping()
    client.init()
    info = client.slot_info(Slot.CATALOG)
    assert info.active and info.crc32 == crc32(field["image"])
    rec = client.read_result_record()
    assert result.status_of(int(rec["return_code"])) == result.Status.NO_RESULT and int(rec["sequence"]) == 0
    assert counted(client, before) == {"resets": 1}


def test_a_single_bit_upset_reads_back_right_and_is_corrected(client):
    pattern = bytes(range(256))
    client.write_edac(0x100, pattern)
    before = counters(client)
    client.fault(FaultAction.LOAD, "edac_upset region=scratch bits=1 count=8 seed=2")
    assert client.read_edac(0x100, 256) == pattern
    assert client.read_edac(0x100, 256) == pattern
    assert counted(client, before) == {"edac_corrected": 8}


def test_a_double_bit_upset_nacks_edac_uncorrectable_until_rewritten(client):
    before = counters(client)
    client.fault(FaultAction.LOAD, "edac_upset region=scratch bits=2 seed=3")
    with pytest.raises(Nack) as exc:
        client.read_edac(0x100, 256)
    assert exc.value.reason == NackReason.EDAC_UNCORRECTABLE
    client.write_edac(0x100, bytes(256))
    assert client.read_edac(0x100, 256) == bytes(256)
    assert counted(client, before) == {"edac_uncorrectable": 1}


def test_a_frozen_detector_returns_the_previous_frame_again(client):
    first = client.go_and_wait(timeout=guards.HANG_S)
    before = counters(client)
    client.fault(FaultAction.LOAD, "frozen_detector count=1")
    frozen = client.go_and_wait(timeout=guards.HANG_S)
    moved_on = client.go_and_wait(timeout=guards.HANG_S)

    def centroids(rec) -> np.ndarray:
        n = int(rec["ext"]["n_reported"])
        return np.stack([rec["ext"]["stars"]["x"][:n], rec["ext"]["stars"]["y"][:n]], axis=1)

    assert len(centroids(first)) > 0 and int(frozen["sequence"]) == int(first["sequence"]) + 1
    assert np.array_equal(centroids(frozen), centroids(first))
    assert not np.array_equal(centroids(moved_on), centroids(first))
    assert counted(client, before) == {"frozen_frames": 1}


# ------------------------------------------------------------------ arming and refusing


def test_a_fault_file_arms_at_start_and_a_bad_one_is_one_line_exit_2(tmp_path):
    good = tmp_path / "faults.txt"
    good.write_text("# the first reply\ndrop_reply count=1\n")
    with DeviceProcess("--pty", "--faults", str(good)) as dev:
        with Client(dev.path, timeout=SHORT_S, retries=0) as c:
            with pytest.raises(ReplyTimeout):
                c.ping()
        with Client(dev.path, timeout=guards.REPLY_S) as c:
            assert counters(c)["dropped_replies"] == 1
    bad = tmp_path / "bad.txt"
    bad.write_text("drop_reply count=1\n\ndrop_replies fraction=0.5\n")
    run = subprocess.run([*device_command(), "--pty", "--faults", str(bad)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr == f"st16-device: {bad} line 3: unknown fault 'drop_replies'; known: " + (
        "delay_reply, drop_reply, corrupt_crc, stuck_result, reset, edac_upset, frozen_detector, "
        "flash_ecc, flash_bad_block, flash_disturb\n"
    )


def test_st16_ground_fault_parses_the_file_first_and_reports_the_counters(device, client, tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text("delay_reply ms=-1 count=1\n")
    with pytest.raises(SystemExit) as exit_:  # argparse's refusal (ground.cli.main.UsageError)
        ground_main(["--port", device, "fault", "load", str(bad)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{bad} line 1: ms=-1 outside 0..60000" in err
    assert client.fault(FaultAction.STATUS).armed == 0  # nothing was sent
    good = tmp_path / "good.txt"
    good.write_text("stuck_result count=2\n")
    assert ground_main(["--port", device, "--json", "fault", "load", str(good)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["action"] == "load" and out["armed"] == 1 and set(out["counters"]) == set(edac.FAULT_COUNTERS)


def test_fault_is_not_supported_without_fault_injection(served_device, capsys):
    assert ground_main(["--port", served_device, "fault", "status"]) == 5
    err = capsys.readouterr().err
    assert "NOT_SUPPORTED" in err and "start st16-device with --fault-injection" in err and err.count("\n") == 1


# ------------------------------------------------------------------ issue 40: resets, delays, the link while armed


def ping_frame() -> bytes:
    return nsp.command(nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, Code.PING).frame()


@pytest.mark.timeout(4 * guards.HANG_S)
def test_delayed_replies_are_dropped_at_fault_clear_and_sigterm_stops_the_device():
    dev = DeviceProcess("--pty", "--fault-injection")
    try:
        with Client(dev.path, timeout=guards.REPLY_S, retries=0) as c:
            c.fault(FaultAction.LOAD, "delay_reply ms=60000 fraction=1")
            for _ in range(3):
                c.write_raw(ping_frame())
            st = c.fault(FaultAction.CLEAR)  # it used to be answered after the three delays: 180 s
            assert st.armed == 0 and dict(zip(edac.FAULT_COUNTERS, st.counters))["delayed_replies"] == 3
            assert "BOOTLOADER" in c.ping()  # served at once, and no PING reply of the three comes first
            assert c.stale_replies == 0
            c.fault(FaultAction.LOAD, "delay_reply ms=60000 fraction=1")
            for _ in range(3):
                c.write_raw(ping_frame())
            assert c.fault(FaultAction.STATUS).armed == 1  # the PINGs are read: their replies wait
        rc = dev.stop(signal.SIGTERM, timeout=guards.HANG_S)  # it used to sit out the delays (SIGKILL here)
        assert rc == 0 and tracebacks(dev.stderr()) == 0
    finally:
        dev.stop(signal.SIGKILL)


@pytest.mark.timeout(2 * guards.HANG_S)
def test_a_combination_received_before_a_scripted_reset_gets_no_reply():
    with DeviceProcess("--pty", "--fault-injection", "--timing", "realistic", "--exposure-ms", "3000") as dev:
        with Client(dev.path, timeout=guards.REPLY_S) as c:
            c.init()
            c.fault(FaultAction.LOAD, "reset after=2")
            combination = nsp.command(
                nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, Code.COMBINATION, Combination(0x0B, 1).pack()
            )
            c.write_raw(combination.frame())  # command 1: its reply waits for the sequence
            c.write_raw(ping_frame())  # command 2: answered, then the reset
            seen: list[nsp.Message] = []
            decoder = slip.Decoder(nsp.MAX_MESSAGE)
            while not any(m.code == Code.PING for m in seen):
                seen += [nsp.decode(e.data) for e in decoder.feed(c.read_raw(0.2)) if hasattr(e, "data")]
            assert "BOOTLOADER" in c.ping() and "BOOTLOADER" in c.ping()
            seen += [nsp.decode(e.data) for e in decoder.feed(c.read_raw(0.2)) if hasattr(e, "data")]
            assert [m.code for m in seen] == [Code.PING]  # the COMBINATION used to be ACKed: sequence 0, NO_RESULT
            assert c.stale_replies == 0 and c.discarded == 0
            assert c.diagnostic().replies == 2  # the PINGs since the reset


@pytest.mark.timeout(2 * guards.HANG_S)
def test_the_link_is_served_while_a_million_catalog_upsets_are_armed(field, client):
    line = "edac_upset region=catalog bits=1 count=1000000 seed={}\n"
    full = "".join(line.format(i) for i in range(75))[:4159]
    with pytest.raises(Nack) as exc:  # the whole FAULT data field of them: refused before any work
        client.fault(FaultAction.LOAD, full)
    assert exc.value.reason == NackReason.BAD_PARAMETER
    assert "add up to 2000000 words, over the 1000000" in str(exc.value)
    before = counters(client)
    words = len(field["image"]) // 4
    assert client.fault(FaultAction.LOAD, line.format(0)).armed == words  # every word of the catalog
    assert "APPLICATION" in client.ping()
    client.go_and_wait(timeout=guards.HANG_S)
    assert counted(client, before) == {"edac_corrected": words}
