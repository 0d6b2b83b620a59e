"""A committed slot image survives power loss: the device process is killed (SIGKILL) at random
moments while it commits images back and forth, and every restart finds one of the two intact."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from firmware_model.device.slots import SlotStore, pack_image, unpack_image
from protocol.crc import crc32

IMAGES = {"a": bytes(range(256)) * 4000, "b": bytes(reversed(range(256))) * 3000}  # 1 MB and 768 kB

WRITER = """
import sys
from firmware_model.device.slots import SlotStore
a, b = bytes(range(256)) * 4000, bytes(reversed(range(256))) * 3000
store = SlotStore(sys.argv[1])
store.set_active(0, a)
print("ready", flush=True)
while True:
    store.set_active(0, b)
    store.set_active(0, a)
"""


def test_image_file_round_trip_and_damage_is_refused():
    data = IMAGES["a"]
    assert unpack_image(pack_image(data)) == data
    blob = bytearray(pack_image(data))
    blob[-1] ^= 1
    for bad in (bytes(blob), pack_image(data)[:-1], b"NOTANIMG" + pack_image(data)[8:], b"ST16"):
        with pytest.raises(ValueError):
            unpack_image(bad)


def test_kill_during_commit_leaves_the_old_or_the_new_image(tmp_path):
    rng = np.random.default_rng(7)
    seen = set()
    for k in range(25):
        state = tmp_path / f"s{k}"
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(state)], stdout=subprocess.PIPE, text=True)
        try:
            assert proc.stdout.readline().strip() == "ready"
            time.sleep(float(rng.uniform(0.0, 0.08)))
        finally:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
        data = SlotStore(state).active(0)
        assert data in (IMAGES["a"], IMAGES["b"]), f"kill {k}: neither image after restart"
        seen.add(data)
    assert len(seen) == 2  # the kills did land in both halves of the loop


def test_a_state_directory_of_the_old_two_file_layout_is_read_and_replaced(tmp_path):
    sub = tmp_path / "slot0"
    sub.mkdir()
    (sub / "active.bin").write_bytes(IMAGES["b"])
    (sub / "active.json").write_text(json.dumps({"length": len(IMAGES["b"]), "crc32": crc32(IMAGES["b"])}))
    store = SlotStore(tmp_path)
    assert store.active(0) == IMAGES["b"]
    store.set_active(0, IMAGES["a"])
    assert sorted(p.name for p in sub.iterdir()) == ["active.img"]
    assert SlotStore(tmp_path).active(0) == IMAGES["a"]
