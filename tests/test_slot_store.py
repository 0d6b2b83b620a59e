"""The slot store and its transfers (issue 29, items 6, 11, 12, 13): received bytes are write-once
(a DATA with other bytes is NACKed CONFLICT and the right image still commits), a DATA costs the
same however many ranges are received (an append-only range log, checkpointed geometrically),
a patch whose COMMIT was cut after it installed its result commits again, and state damage that
used to be silent (a deleted image or slot directory, forged range lists) is one ``state:`` line."""

import json
import logging
import os
import struct

import pytest

from firmware_model.device import slots
from firmware_model.device.device import Device
from firmware_model.device.slots import SlotStore
from protocol import nsp
from protocol.catalog_patch import make_patch
from protocol.commands import (
    Code,
    NackInfo,
    NackReason,
    Slot,
    SlotImage,
    SlotRequest,
    XferBegin,
    XferData,
    XferState,
    XferStatus,
)
from protocol.crc import CRC32_RESIDUE, crc32

IMAGE = bytes((i * 7 + (i >> 8)) & 0xFF for i in range(50_000))


def send(dev: Device, code: int, data: bytes) -> nsp.Message:
    return dev.handle(nsp.command(dev.address, nsp.HOST_ADDRESS, code, data))[0]


def begin(dev: Device, slot: int, data: bytes) -> XferStatus:
    return XferStatus.unpack(send(dev, Code.XFER_BEGIN, XferBegin(slot, len(data), crc32(data)).pack()).data)


def data(dev: Device, slot: int, offset: int, chunk: bytes) -> nsp.Message:
    return send(dev, Code.XFER_DATA, XferData(slot, offset, chunk).pack())


def state_lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.getMessage().startswith("state: ")]


# --------------------------------------------------------------------------- 7: what a BEGIN resumes


def test_a_begin_never_resumes_on_the_crc_every_self_checked_image_has():
    """Two images of one length that each end with their own CRC-32 share the whole-image CRC-32
    0x2144DF1C: the second BEGIN starts afresh (it resumed the first one's bytes); a BEGIN of the
    same image with an ordinary CRC-32 still resumes."""
    dev = Device()
    first, second = (body + crc32(body).to_bytes(4, "little") for body in (b"A" * 5000, b"B" * 5000))
    assert crc32(first) == crc32(second) == CRC32_RESIDUE
    begin(dev, Slot.FRAME, first)
    assert data(dev, Slot.FRAME, 0, first[:3000]).ack
    assert begin(dev, Slot.FRAME, second).received == 0
    plain = b"C" * 5004
    begin(dev, Slot.FRAME, plain)
    assert data(dev, Slot.FRAME, 0, plain[:3000]).ack
    assert begin(dev, Slot.FRAME, plain).received == 3000


# --------------------------------------------------------------------------- 6: write-once bytes


@pytest.mark.parametrize("persisted", [False, True])
def test_a_data_with_other_bytes_over_received_ones_is_refused_and_the_right_image_commits(tmp_path, persisted):
    dev = Device(store=SlotStore(tmp_path if persisted else None))
    begin(dev, 0, IMAGE)
    for off in range(0, 20_000, 4000):
        assert data(dev, 0, off, IMAGE[off : off + 4000]).ack
    assert data(dev, 0, 4000, IMAGE[4000:8000]).ack  # a retry: the same bytes
    poison = bytearray(IMAGE[6000:23_000])  # another client's bytes over received ones, past them too
    poison[1234] ^= 0x40
    rep = data(dev, 0, 6000, bytes(poison))
    assert not rep.ack
    info = NackInfo.unpack(rep.data)
    assert info.reason == NackReason.CONFLICT and "byte 7234 differs" in info.text
    st = XferStatus.unpack(send(dev, Code.XFER_STATUS, b"\x00").data)
    assert (st.contiguous, st.received) == (20_000, 20_000)  # nothing of the refused DATA was kept
    assert data(dev, 0, 18_000, IMAGE[18_000:30_000]).ack  # overlapping with the same bytes: the new part kept
    for off in range(30_000, len(IMAGE), 4000):
        assert data(dev, 0, off, IMAGE[off : off + 4000]).ack
    rep = send(dev, Code.XFER_COMMIT, b"\x00")
    assert rep.ack and SlotImage.unpack(rep.data).crc32 == crc32(IMAGE)


# --------------------------------------------------------------------------- 11: O(1) per DATA


def test_a_data_costs_the_same_however_many_ranges_are_received(tmp_path, monkeypatch):
    """Every other 100-byte chunk of 1 MB (5 243 ranges): the metadata written stays proportional to
    the DATAs (it rewrote the whole range list at each: 5 243 x up to 70 kB, ~190 MB), and a restart
    finds the same ranges."""
    image = (IMAGE * 21)[: 1 << 20]
    written = []
    real_dumps = json.dumps
    monkeypatch.setattr(json, "dumps", lambda *a, **k: written.append(real_dumps(*a, **k)) or written[-1])
    store = SlotStore(tmp_path)
    store.begin(0, len(image), crc32(image))
    for off in range(0, len(image), 200):
        store.write(0, off, image[off : off + 100])
    ranges = [list(r) for r in store.transfer(0).ranges]
    assert len(ranges) == 5243
    assert sum(map(len, written)) < 2_000_000  # checkpoints of 1, 2, 4, ... ranges: ~0.3 MB in all
    log = (tmp_path / "slot0" / "partial.log").stat().st_size
    assert log <= 16 + 12 * 5243
    store.close()
    again = SlotStore(tmp_path)
    assert again.transfer(0).ranges == ranges
    for off in range(100, len(image), 200):  # the rest, then the whole image is there
        again.write(0, off, image[off : off + 100])
    assert again.transfer(0).complete and again.transfer_bytes(0) == image


def test_ranges_merge_by_bisection():
    tr = slots.Transfer(0, 100, 0)
    for a, b in ((10, 20), (30, 40), (50, 60), (20, 30), (0, 5), (55, 70), (90, 100), (45, 50)):
        tr.add(a, b)
    assert tr.ranges == [[0, 5], [10, 40], [45, 70], [90, 100]]
    assert (
        tr.overlaps(0, 12) == [(0, 5), (10, 12)]
        and tr.overlaps(40, 45) == []
        and tr.overlaps(60, 95)
        == [
            (60, 70),
            (90, 95),
        ]
    )
    tr.add(0, 100)
    assert tr.complete


def test_a_kill_between_the_bytes_and_their_record_loses_only_that_data(tmp_path):
    """The record follows the bytes: a record without its bytes cannot be written by the device, and
    bytes without their record are simply asked for again."""
    store = SlotStore(tmp_path)
    store.begin(0, len(IMAGE), crc32(IMAGE))
    store.write(0, 0, IMAGE[:1000])
    store.write(0, 1000, IMAGE[1000:2000])
    store.close()
    with open(tmp_path / "slot0" / "partial.bin", "r+b") as fh:  # bytes written, the kill before the record
        fh.seek(5000)
        fh.write(IMAGE[5000:6000])
    assert SlotStore(tmp_path).transfer(0).ranges == [[0, 2000]]


def older_transfer(root, written: list[tuple[int, int]], claimed: list[list[int]]) -> bool:
    """The ``partial.bin`` + ``partial.json`` of a state directory from before the range log:
    ``written`` ranges of IMAGE in a sparse file, ``claimed`` ranges listed; does the file system
    report the never-written bytes as holes?"""
    sub = root / "slot0"
    sub.mkdir()
    with open(sub / "partial.bin", "wb") as fh:
        fh.truncate(len(IMAGE))
        for a, b in written:
            fh.seek(a)
            fh.write(IMAGE[a:b])
        fh.flush()
        try:
            sparse = os.lseek(fh.fileno(), 0, os.SEEK_HOLE) < len(IMAGE)
        except OSError:
            sparse = False
    (sub / "partial.json").write_text(json.dumps({"length": len(IMAGE), "crc32": crc32(IMAGE), "ranges": claimed}))
    return sparse


def test_the_partial_json_of_an_older_state_directory_is_read_and_rewritten(tmp_path, caplog):
    sub = tmp_path / "slot0"
    older_transfer(tmp_path, [(0, 3000), (10_000, 12_000)], [[0, 3000], [10_000, 12_000]])
    with caplog.at_level(logging.WARNING):
        store = SlotStore(tmp_path)
    assert state_lines(caplog) == [] and store.transfer(0).ranges == [[0, 3000], [10_000, 12_000]]
    meta = json.loads((sub / "partial.json").read_text())
    assert meta["format"] == 2 and meta["ranges"] == [
        [0, 3000, crc32(IMAGE[:3000])],
        [10_000, 12_000, crc32(IMAGE[10_000:12_000])],
    ]
    store.write(0, 3000, IMAGE[3000:10_000])
    store.close()
    assert SlotStore(tmp_path).transfer(0).ranges == [[0, 12_000]]


# --------------------------------------------------------------------------- 12: a patch cut after it installed


def test_a_patch_whose_commit_was_cut_after_it_installed_its_result_commits_again(tmp_path, caplog):
    base, new = IMAGE, bytearray(IMAGE)
    new[100:110] = b"0123456789"
    new = bytes(new)
    patch = make_patch(base, new)
    dev = Device(store=SlotStore(tmp_path))
    assert begin(dev, 0, base) and data(dev, 0, 0, base[:4000]).ack
    for off in range(4000, len(base), 4000):
        data(dev, 0, off, base[off : off + 4000])
    assert send(dev, Code.XFER_COMMIT, b"\x00").ack
    begin(dev, Slot.CATALOG_PATCH, patch)
    assert data(dev, Slot.CATALOG_PATCH, 0, patch).ack
    SlotStore(tmp_path).set_active(0, new)  # the COMMIT installed the result, the kill came before the drop
    dev = Device(store=SlotStore(tmp_path))
    assert XferStatus.unpack(send(dev, Code.XFER_STATUS, b"\x03").data).state == XferState.COMPLETE
    with caplog.at_level(logging.WARNING):
        rep = send(dev, Code.XFER_COMMIT, SlotRequest(Slot.CATALOG_PATCH).pack())
    assert rep.ack, NackInfo.unpack(rep.data).text  # was BASE_MISMATCH 0x0502, until an ABORT by hand
    assert SlotImage.unpack(rep.data) == SlotImage(Slot.CATALOG_PATCH, True, len(new), crc32(new))
    assert any("active image already" in r.getMessage() for r in caplog.records)
    assert XferStatus.unpack(send(dev, Code.XFER_STATUS, b"\x03").data).state == XferState.NONE
    assert dev.transfers.store.active(0) == new
    # a patch made for another catalog, whose result is not active either, is still refused
    other = make_patch(bytes(reversed(base)), bytes(reversed(new)))
    begin(dev, Slot.CATALOG_PATCH, other)
    data(dev, Slot.CATALOG_PATCH, 0, other)
    rep = send(dev, Code.XFER_COMMIT, SlotRequest(Slot.CATALOG_PATCH).pack())
    assert not rep.ack and NackInfo.unpack(rep.data).reason == 0x0502


def test_kills_during_patch_commits_leave_no_patch_stuck():
    from ground.testing import commit_kill

    tally, found = commit_kill.run(seed=5, kills=4)  # two catalog commits killed, two patch commits
    assert tally.failures == 0 and found["stuck"] == 0, (tally.notes, found)


# --------------------------------------------------------------------------- 13: damage that was silent


def _committed_with_transfer(root) -> None:
    store = SlotStore(root)
    store.set_active(0, IMAGE)
    store.set_active(2, b'{"sigma_rg": 0.05}')
    store.begin(0, len(IMAGE), crc32(IMAGE))
    store.write(0, 0, IMAGE[:10_000])
    store.write(0, 20_000, IMAGE[20_000:25_000])


def _forge_record(root) -> None:
    with open(root / "slot0" / "partial.log", "ab") as fh:
        fh.write(struct.pack("<III", 30_000, 40_000, 0x12345678))


def _forge_checkpoint(root) -> None:
    path = root / "slot0" / "partial.json"
    meta = json.loads(path.read_text())
    meta["ranges"].append([40_000, 50_000, 0])
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize(
    ("damage", "says", "image", "ranges"),
    [
        (
            lambda r: (r / "slot0" / "active.img").unlink(),
            "slot0/active.img is missing",
            None,
            [[0, 10_000], [20_000, 25_000]],
        ),
        (lambda r: __import__("shutil").rmtree(r / "slot0"), "slot0/ is missing", None, None),
        (_forge_record, "partial.log: 1 of", IMAGE, [[0, 10_000], [20_000, 25_000]]),
        (_forge_checkpoint, "partial.json: 1 of", IMAGE, [[0, 10_000], [20_000, 25_000]]),
    ],
    ids=["image_deleted", "slot_dir_deleted", "forged_log_record", "forged_checkpoint_range"],
)
def test_damage_that_was_silent_is_one_state_line(tmp_path, caplog, damage, says, image, ranges):
    _committed_with_transfer(tmp_path)
    damage(tmp_path)
    with caplog.at_level(logging.WARNING):
        store = SlotStore(tmp_path)
    lines = state_lines(caplog)
    assert len(lines) == 1 and says in lines[0], lines
    assert store.active(0) == image and store.active(2) == b'{"sigma_rg": 0.05}'
    tr = store.transfer(0)
    assert (tr.ranges if tr else None) == ranges
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        SlotStore(tmp_path)  # said once: the state directory now says what the device holds
    assert state_lines(caplog) == []


def test_older_ranges_over_bytes_never_written_are_one_state_line(tmp_path, caplog):
    if not older_transfer(tmp_path, [(0, 8192)], [[0, 8192], [20_000, 40_000]]):
        pytest.skip("this file system does not report holes")
    with caplog.at_level(logging.WARNING):
        store = SlotStore(tmp_path)
    lines = state_lines(caplog)
    assert len(lines) == 1 and "never written (first [20000, 40000))" in lines[0], lines
    assert store.transfer(0).ranges == [[0, 8192]]


def test_a_commit_cut_before_its_manifest_or_a_directory_from_before_manifests_starts_silent(tmp_path, caplog):
    store = SlotStore(tmp_path)
    store.set_active(0, IMAGE)
    old_manifest = (tmp_path / "manifest.json").read_text()
    store.set_active(0, IMAGE[::-1])
    (tmp_path / "manifest.json").write_text(old_manifest)  # the kill came between the image and the manifest
    with caplog.at_level(logging.WARNING):
        assert SlotStore(tmp_path).active(0) == IMAGE[::-1]
    (tmp_path / "manifest.json").unlink()
    with caplog.at_level(logging.WARNING):
        assert SlotStore(tmp_path).active(0) == IMAGE[::-1]
    assert state_lines(caplog) == []
    assert json.loads((tmp_path / "manifest.json").read_text()) == {
        "slots": {"0": {"length": len(IMAGE), "crc32": crc32(IMAGE[::-1])}}
    }
