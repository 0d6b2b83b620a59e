"""Maintenance mode, the FLASH command and the NAND model (docs/ICD.md section 15, issue 45)."""

import os
import signal
import struct
import subprocess
import sys
import threading
import time

import guards
import pytest

from firmware_model.device.device import Device
from firmware_model.device.nand import (
    APP_BLOCK,
    LOGICAL_PAGES,
    MAINTENANCE_ADDRESS,
    Nand,
)
from firmware_model.device.slots import SlotStore
from protocol import edac, flash, nsp, result, slip
from protocol.commands import APP_START_ADDRESS, Code, CrcRequest, MemorySpace, NackInfo, NackReason, ReadRange
from protocol.crc import crc16_mcrf4xx
from protocol.flash import PAGE_BYTES, PAGES_PER_BLOCK, Failure, Sub

APP_PAGE = APP_BLOCK * PAGES_PER_BLOCK


def _send(dev, code, data=b""):
    frames = dev.receive(nsp.command(0x0E, 0x11, code, data).frame())
    return [nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(f)[0].data) for f in frames]


def _flash(dev, sub, *fields, data=b"", long=False):
    (rep,) = _send(dev, Code.CRC, flash.command(sub, *fields, data=data, long=long))
    return rep


def _maintenance(dev):
    (rep,) = _send(dev, Code.INIT, struct.pack("<I", MAINTENANCE_ADDRESS))
    assert rep.ack
    assert _send(dev, Code.PING)[0].data.startswith(b"ST16-EMU MAINTENANCE")


def test_flash_subcommands_outside_maintenance_mode_are_nacked_with_the_reason_and_crc_still_works():
    dev = Device()
    (rep,) = _send(dev, Code.CRC, flash.command(Sub.ERASE_BLOCK, 64))
    info = NackInfo.unpack(rep.data)
    assert not rep.ack and info.reason == NackReason.WRONG_MODE and "maintenance mode" in info.text
    (rep,) = _send(dev, Code.CRC, CrcRequest(MemorySpace.EDAC, 0x100, 16).pack())
    assert rep.ack and len(rep.data) == 11  # the supervisor's CRC


def test_page_buffer_erase_write_read_and_crcs():
    dev = Device()
    _maintenance(dev)
    payload = bytes(range(256)) * 2
    rep = _flash(dev, Sub.WRITE_BUFFER, 100, data=payload)
    assert rep.ack and rep.data == bytes([1]) + struct.pack("<H", 100) + payload
    rep = _flash(dev, Sub.READ_BUFFER, 100, 0)  # short form: 0 = 256 bytes
    assert rep.ack and rep.data[3:] == payload[:256]
    rep = _flash(dev, Sub.READ_BUFFER, 100, 512, long=True)
    assert rep.data[3:] == payload
    page = 70 * PAGES_PER_BLOCK + 3
    assert _flash(dev, Sub.ERASE_BLOCK, page).ack
    assert _flash(dev, Sub.WRITE_PAGE, page).ack
    buffer = b"\xff" * 100 + payload + b"\xff" * (PAGE_BYTES - 612)
    assert _flash(dev, Sub.CRC_BUFFER).data == bytes([7]) + struct.pack("<H", crc16_mcrf4xx(buffer))
    rep = _flash(dev, Sub.CRC_NAND, page, page)
    assert rep.ack and rep.data[9:] == struct.pack("<H", crc16_mcrf4xx(buffer))
    # a page written twice without an erase: operation failed
    rep = _flash(dev, Sub.WRITE_PAGE, page)
    assert not rep.ack and flash.unpack_failure(rep.data)[2] == Failure.OPERATION
    # an erased page has no CRC
    rep = _flash(dev, Sub.CRC_NAND, page + 1, page + 1)
    assert not rep.ack and flash.unpack_failure(rep.data)[2:] == (Failure.OPERATION, page + 1)
    _flash(dev, Sub.WRITE_BUFFER, 0, data=b"\x00" * 8)
    assert _flash(dev, Sub.READ_PAGE, page).ack  # back into the buffer
    assert _flash(dev, Sub.READ_BUFFER, 100, 4).data[3:] == payload[:4]


@pytest.mark.parametrize(
    "sub, fields",
    [
        (Sub.ERASE_BLOCK, (LOGICAL_PAGES,)),
        (Sub.WRITE_PAGE, (0xFFFFFFFF,)),
        (Sub.CRC_NAND, (10, 5)),
        (Sub.FIND_BAD_BLOCKS, (0, LOGICAL_PAGES)),
        (Sub.READ_DISTURB_TEST, (20, 10, 1000)),
        (Sub.MAKE_BOOT_BLOCK, (65,)),
    ],
)
def test_a_page_or_block_out_of_range_is_the_syntax_failed_reply(sub, fields):
    dev = Device()
    _maintenance(dev)
    rep = _flash(dev, sub, *fields)
    got_sub, echo, kind, page = flash.unpack_failure(rep.data)
    assert not rep.ack and got_sub == sub and kind == Failure.SYNTAX
    assert echo == struct.pack(flash.FIELDS[sub], *fields)


def test_find_bad_blocks_counts_the_factory_flags():
    dev = Device()
    _maintenance(dev)
    nand = dev.maintenance.nand
    rep = _flash(dev, Sub.FIND_BAD_BLOCKS, 0, LOGICAL_PAGES - 1)
    count, first = struct.unpack_from("<II", rep.data, 9)
    logical_bad = sorted(b for b in nand.factory_bad if b * PAGES_PER_BLOCK < LOGICAL_PAGES)
    assert count == len(logical_bad) and first == logical_bad[0] * PAGES_PER_BLOCK


def test_an_erase_of_a_factory_bad_block_is_relocated_and_the_data_reads_back():
    dev = Device()
    _maintenance(dev)
    nand = dev.maintenance.nand
    bad = min(b for b in nand.factory_bad if b * PAGES_PER_BLOCK < LOGICAL_PAGES)
    page = bad * PAGES_PER_BLOCK
    assert _flash(dev, Sub.ERASE_BLOCK, page).ack
    assert nand.physical_block(bad) != bad
    _flash(dev, Sub.WRITE_BUFFER, 0, data=b"relocated")
    assert _flash(dev, Sub.WRITE_PAGE, page).ack
    _flash(dev, Sub.WRITE_BUFFER, 0, data=b"xxxxxxxxx")
    assert _flash(dev, Sub.READ_PAGE, page).ack
    assert _flash(dev, Sub.READ_BUFFER, 0, 9).data[3:] == b"relocated"


def test_read_disturbance_accumulates_with_reads_and_a_rewrite_clears_it():
    """The figure: after N reads the error counts; after Rewrite NAND, 0."""
    nand = Nand(disturb_reads=1000)
    pages = range(APP_PAGE, APP_PAGE + 64)
    for _ in range(40):
        for p in pages:
            try:
                nand.read_page(p)
            except Exception:
                pass
    corrected, uncorrectable, bad = nand.error_counts()
    assert corrected + uncorrectable > 0 and bad == len(nand.factory_bad)
    blocks, fixed, lost = nand.rewrite(APP_BLOCK, APP_BLOCK)
    assert blocks == 1 and fixed >= corrected
    for p in pages:
        nand.read_page(p)
    assert nand.error_counts()[:2] == (0, 0)


def test_the_read_disturbance_test_reports_progress_in_edac_and_the_ecc_failure():
    dev = Device()
    _maintenance(dev)
    dev.maintenance.nand.disturb_reads = 50_000
    done = threading.Event()
    replies = []

    def late(frames):
        replies.extend(frames)
        done.set()

    dev.late_reply = late
    assert _send(dev, Code.CRC, flash.command(Sub.READ_DISTURB_TEST, APP_PAGE, APP_PAGE + 63, 20_000)) == []
    assert done.wait(guards.REPLY_S * 10)
    (rep,) = [nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(f)[0].data) for f in replies]
    message = _send(dev, Code.READ_EDAC, ReadRange(edac.BOOT_MESSAGE_AT, 64).pack())[0].data[2:]
    assert message.startswith(b"NAND DISTURB ") and b"CYCLES" in message
    # 64 pages x 20 000 cycles = 1.28 M reads of one block: ~25 flipped bits, some page holds two
    sub, echo, kind, page = flash.unpack_failure(rep.data)
    assert not rep.ack and kind == Failure.ECC and APP_PAGE <= page <= APP_PAGE + 63
    # a short test passes: success reply with the cycles completed
    fresh = Device()
    _maintenance(fresh)
    fresh.late_reply = None
    (rep,) = _send(fresh, Code.CRC, flash.command(Sub.READ_DISTURB_TEST, APP_PAGE, APP_PAGE + 63, 3000))
    assert rep.ack and rep.data == bytes([13]) + struct.pack("<III", APP_PAGE, APP_PAGE + 63, 3000)


def test_flash_error_counts_reach_the_hardware_telemetry():
    def solver(ctx):
        return {"return_code": result.make_return_code(result.Status.OK)}

    dev = Device(solver=solver, frame_source=lambda ctx: "frame")
    dev.runner.transfers.objects[0] = "catalog"
    dev.maintenance.nand.disturb_reads = 100
    for _ in range(10):
        for p in range(APP_PAGE, APP_PAGE + 64):
            try:
                dev.maintenance.nand.read_page(p)
            except Exception:
                pass
    counts = dev.maintenance.nand.error_counts()
    assert counts[0] + counts[1] > 0
    assert _send(dev, Code.INIT, struct.pack("<I", APP_START_ADDRESS))[0].ack
    assert _send(dev, Code.GO, b"\x0b")[0].ack
    assert dev.wait_idle(guards.REPLY_S)
    rec = result.parse(dev.runner.result)
    assert tuple(int(v) for v in rec["hardware"]["flash_errors"]) == counts


def test_the_nand_persists_and_a_kill_during_writes_loses_nothing_committed(tmp_path):
    """A child erases and programs pages in a loop, printing each one once it returned, and is
    killed -9 at a random moment: every printed page reads back."""
    root = tmp_path / "nand"
    script = f"""
import sys
from firmware_model.device.nand import Nand
from protocol.flash import PAGES_PER_BLOCK, PAGE_BYTES
nand = Nand({str(root)!r})
for k in range(1000):
    block = 100 + k
    nand.erase_block(block)
    nand.write_page(block * PAGES_PER_BLOCK, bytes([k % 256]) * PAGE_BYTES)
    print(k, flush=True)
"""
    child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    seen = []
    deadline = time.monotonic() + guards.HANG_S
    while len(seen) < 30 and time.monotonic() < deadline:
        line = child.stdout.readline()
        if not line:
            break
        seen.append(int(line))
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    assert len(seen) >= 30, "the child wrote too few pages before the deadline"
    nand = Nand(root)
    for k in seen:
        assert nand.read_page((100 + k) * PAGES_PER_BLOCK) == bytes([k % 256]) * PAGE_BYTES


def test_the_device_keeps_its_nand_in_the_state_directory(tmp_path):
    dev = Device(store=SlotStore(tmp_path / "state"))
    _maintenance(dev)
    page = 300 * PAGES_PER_BLOCK
    _flash(dev, Sub.ERASE_BLOCK, page)
    _flash(dev, Sub.WRITE_BUFFER, 0, data=b"kept")
    assert _flash(dev, Sub.WRITE_PAGE, page).ack
    again = Device(store=SlotStore(tmp_path / "state"))
    assert again.maintenance.nand.read_page(page)[:4] == b"kept"


def test_scripted_flash_faults_are_counted_and_a_rewrite_repairs_them():
    from firmware_model.device.faults import parse_script

    dev = Device(fault_injection=True)
    nand = dev.maintenance.nand
    script = "flash_ecc bits=1 count=3 seed=2\nflash_bad_block count=1\nflash_disturb reads=500\n"
    dev.arm(parse_script(script))
    assert dev.faults.counters["flash_ecc"] == 3 and dev.faults.counters["flash_bad_block"] == 1
    assert nand.disturb_reads == 500
    failing = set(nand.failing)
    _maintenance(dev)
    # the flight software reads the NAND, sees the errors, and rewrites every programmed block
    for pp in sorted(nand.pages):
        try:
            nand.read_page(pp)
        except Exception:
            pass
    corrected, _, bad = nand.error_counts()
    assert corrected >= 1 and bad == len(nand.factory_bad)
    for first, last in ((0, 255), (APP_PAGE, APP_PAGE + 255)):
        rep = _flash(dev, Sub.REWRITE_NAND, first, last)
        assert rep.ack or flash.unpack_failure(rep.data)[2] == Failure.ECC
    assert nand.error_counts()[2] == len(nand.factory_bad) + len(failing)  # the failing block relocated, bad
    assert not nand.failing and nand.error_counts()[0] == 0


def test_the_ground_flash_command_through_a_pty(tmp_path):
    """st16-ground's flash helper on a served device: the replies, a failure reply's kind and
    page, and WRONG_MODE outside maintenance mode."""
    import argparse

    from firmware_model.device.link import PtyLink, serve
    from ground.link.client import Client, Nack
    from ground.link.commands import COMMANDS
    from ground.link.flash_ops import FlashFailed, flash_command

    dev = Device()
    link = PtyLink()
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(dev, link, stop), daemon=True)
    thread.start()
    try:
        with Client(link.path, timeout=guards.REPLY_S) as c:
            with pytest.raises(Nack, match="WRONG_MODE"):
                flash_command(c, Sub.ERASE_BLOCK, 64)
            c.init(MAINTENANCE_ADDRESS)
            assert flash_command(c, Sub.WRITE_BUFFER, 0, data=b"abc") == struct.pack("<H", 0) + b"abc"
            with pytest.raises(FlashFailed) as failed:
                flash_command(c, Sub.CRC_NAND, 5, 1)
            assert failed.value.kind == Failure.SYNTAX
            run = COMMANDS["flash"][2]
            out = run(c, argparse.Namespace(sub="crc-nand", fields=[100, 100], data=b"", long=False))
            assert out == {"sub": "crc_nand", "ok": False, "failure": "operation", "page": 100}
            out = run(c, argparse.Namespace(sub="7", fields=[], data=b"", long=False))
            assert out["ok"] and len(bytes.fromhex(out["reply_hex"])) == 2
    finally:
        stop.set()
        thread.join(guards.HANG_S)
        link.close()


def test_a_boot_from_nand_reads_the_boot_block_and_the_image_and_fails_when_they_are_lost():
    """GO with LOAD_NAND reads the NAND: a primary boot block with an uncorrectable page falls back
    to a backup; an uncorrectable application image stops the boot; Rewrite NAND cannot save it
    (rewritten as read), a rewrite of the image from the ground can."""
    dev = Device(solver=lambda ctx: {"return_code": result.make_return_code(result.Status.OK)})
    nand = dev.maintenance.nand
    nand.errors[3] = 2  # the primary boot block: a page lost
    assert _send(dev, Code.GO, b"\x02")[0].ack  # booted from the backup at page 64
    assert nand.error_counts()[1] == 1
    dev.reset()
    nand.errors[APP_PAGE + 10] = 2
    (rep,) = _send(dev, Code.GO, b"\x02")
    info = NackInfo.unpack(rep.data)
    assert not rep.ack and info.reason == NackReason.EDAC_UNCORRECTABLE and str(APP_PAGE + 10) in info.text
    assert not dev.app_mode
    # maintenance: the ground writes the page again from its copy of the image
    _maintenance(dev)
    good = nand.pages[APP_PAGE + 11]  # (any content will do: the model checks ECC, not the code)
    assert _flash(dev, Sub.REWRITE_NAND, APP_PAGE, APP_PAGE + 63).ack is False  # ECC failed: rewritten as read
    assert nand.errors.get(APP_PAGE + 10, 0) == 0 and good == nand.pages[APP_PAGE + 11]
    assert _send(dev, Code.GO, b"\x02")[0].ack


def test_the_catalog_lives_in_the_nand_and_an_uncorrectable_page_stops_the_solve(tmp_path):
    """A committed catalog is programmed into the NAND; every GO reads it; an uncorrectable page
    NACKs the GO until the NAND is rewritten, a corrected one only counts."""
    from firmware_model.device.nand import CATALOG_BLOCK, CATALOG_MAGIC

    store = SlotStore(tmp_path / "state")
    dev = Device(store=store, solver=lambda ctx: {"return_code": result.make_return_code(result.Status.OK)})
    image = bytes(range(256)) * 40  # 10 240 bytes: 5 pages + the header
    dev.maintenance.store_catalog(image)
    dev.runner.transfers.objects[0] = "catalog"
    nand = dev.maintenance.nand
    first = CATALOG_BLOCK * PAGES_PER_BLOCK
    assert nand.read_page(first).startswith(CATALOG_MAGIC) and nand.read_page(first + 1)[:256] == bytes(range(256))
    assert _send(dev, Code.INIT, struct.pack("<I", APP_START_ADDRESS))[0].ack
    nand.errors[nand.physical_page(first + 2)] = 1
    assert _send(dev, Code.GO, b"\x09")[0].ack  # a corrected error: the solve goes on, it counts
    assert dev.wait_idle(guards.REPLY_S) and nand.error_counts()[0] == 1
    nand.errors[nand.physical_page(first + 3)] = 2
    (rep,) = _send(dev, Code.GO, b"\x09")
    info = NackInfo.unpack(rep.data)
    assert not rep.ack and info.reason == NackReason.EDAC_UNCORRECTABLE and str(first + 3) in info.text
    # the ground commits the catalog again: the NAND copy is rewritten whole
    nand.pages[nand.physical_page(first)] = b"\xff" * PAGE_BYTES  # (forces the reprogram)
    dev.maintenance.store_catalog(image)
    assert _send(dev, Code.GO, b"\x09")[0].ack
    assert dev.wait_idle(guards.REPLY_S)
    # it persisted: a restart finds the catalog in the NAND
    again = Device(store=SlotStore(tmp_path / "state"))
    assert again.maintenance.nand.read_page(first + 1)[:256] == bytes(range(256))


def test_a_catalog_is_programmed_with_one_write_per_block_and_its_header_last(tmp_path, monkeypatch):
    """A 15 MB catalog is about 7 400 pages: programming it must write each block's file once (not
    once per page, which took 5 s quiet and over 30 s beside busy loops), and the header page,
    which makes the copy valid, goes in last."""
    import firmware_model.device.nand as nand_module
    from firmware_model.device.nand import CATALOG_BLOCK, CATALOG_MAGIC

    dev = Device(store=SlotStore(tmp_path / "state"))
    written: list[str] = []
    real = nand_module.atomic_write
    monkeypatch.setattr(nand_module, "atomic_write", lambda path, data: (written.append(path.name), real(path, data)))
    image = bytes(range(256)) * (8 * PAGES_PER_BLOCK * PAGE_BYTES // 256)  # 8 blocks of pages + a header page
    dev.maintenance.store_catalog(image)
    blocks = 8 + 1
    catalog_files = [name for name in written if name.startswith("block-")]
    assert len(catalog_files) <= 2 * blocks + 1, len(catalog_files)  # erase + program per block, the header again
    first = CATALOG_BLOCK * PAGES_PER_BLOCK
    nand = dev.maintenance.nand
    assert nand.read_page(first).startswith(CATALOG_MAGIC)
    assert nand.read_page(first + 8 * PAGES_PER_BLOCK)[:256] == bytes(range(256))
    assert catalog_files[-1] == f"block-{nand.physical_block(CATALOG_BLOCK):05x}.bin"


def test_realistic_timing_runs_the_read_disturbance_test_at_the_real_unit_s_pace():
    """``--timing realistic`` reads at the ICD's ~9000 pages/s (the functional processor is silent
    as long as the real one); the default fast timing at compute speed."""
    from firmware_model.device.cli import build_device, build_parser
    from firmware_model.device.nand import ICD_PAGE_READ_S

    assert build_device(build_parser().parse_args(["--pty"])).maintenance.pace_s == 0.0
    realistic = build_device(build_parser().parse_args(["--pty", "--timing", "realistic"]))
    assert realistic.maintenance.pace_s == ICD_PAGE_READ_S
