"""Damaged state directories (truncated, flipped, garbage, missing or foreign files): the device
starts, says what it ignored in one line each, answers PING and keeps its catalog intact or has
none, never another one (fixed seeds; long run: bench/bench_fuzz.py)."""

import logging

from firmware_model.device.slots import SlotStore
from ground.testing import state_faults
from ground.testing.tally import Tally


def test_the_base_state_starts_without_a_word(tmp_path):
    state_faults.base_state(tmp_path, state_faults.catalog_image(1))
    with state_faults.in_process_device(tmp_path) as (device, text):
        assert text == "" and 0 in device._objects and SlotStore(tmp_path).transfer(0) is not None


def test_every_kind_of_damage_alone_and_combined_in_process():
    tally = state_faults.run(seed=1, trials=len(state_faults.DAMAGE) + 20, process=False)
    assert tally.failures == 0, tally.notes
    assert tally.faults > len(state_faults.DAMAGE) + 20


def test_damaged_state_gives_one_line_messages_and_a_serving_device_process():
    tally = state_faults.run(seed=2, trials=3, process=True)  # img_bit_flips, img_deleted, img_empty
    assert tally.failures == 0, tally.notes
    assert tally.messages == 9


def test_a_reloaded_transfer_beyond_the_size_limit_is_dropped_with_a_message(tmp_path, caplog):
    state_faults.base_state(tmp_path, state_faults.catalog_image(1))
    (tmp_path / "slot0" / "partial.json").write_text('{"length": 1099511627776, "crc32": 0, "ranges": []}')
    with caplog.at_level(logging.WARNING):
        assert SlotStore(tmp_path).transfer(0) is None
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 1 and "\n" not in messages[0]
    assert messages[0].startswith("state: slot 0: partial transfer unreadable") and "outside" in messages[0]


def test_the_check_sees_a_lost_catalog():
    tally = Tally()
    state_faults._check_slots(False, 0, 1, b"cat", ["x"], touches_img=False, touches_partial=False, tally=tally)
    state_faults._check_slots(True, 1234, 1, b"cat", ["x"], touches_img=True, touches_partial=False, tally=tally)
    assert tally.state_corruptions == 2
