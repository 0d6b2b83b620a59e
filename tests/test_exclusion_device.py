"""The exclusion parameters over the link, against ``st16-device`` as a process: an angle outside
0-90 deg (or a memory outside 0-3600 s) is NACKed on COMMIT with reason 0x0402 and the text, and
the slot keeps its previous set; a valid set is taken."""

import json

import guards
import pytest

from ground.link.client import Client, Nack
from ground.testing.device_proc import DeviceProcess
from protocol.commands import Slot


@pytest.fixture
def device(tmp_path):
    proc = DeviceProcess("--pty", "--state", str(tmp_path / "state"))
    try:
        yield proc
    finally:
        proc.stop()


def test_out_of_range_exclusion_parameters_are_nacked_with_the_reason(device):
    good = json.dumps({"sun_exclusion_deg": 45, "exclusion_memory_s": 0}).encode()
    with Client(device.path, timeout=guards.REPLY_S) as c:
        c.upload(Slot.PARAMS, good, progress=False)
        for bad, text in (
            ({"sun_exclusion_deg": 91}, "sun_exclusion_deg must be a number in [0, 90] deg, got 91"),
            ({"moon_exclusion_deg": -5}, "moon_exclusion_deg must be a number in [0, 90] deg, got -5"),
            ({"earth_exclusion_deg": "20"}, "earth_exclusion_deg must be a number in [0, 90] deg, got '20'"),
            ({"exclusion_memory_s": 7200}, "exclusion_memory_s must be a number in [0, 3600] s, got 7200"),
        ):
            with pytest.raises(Nack) as err:
                c.upload(Slot.PARAMS, json.dumps(bad).encode(), progress=False)
            assert err.value.reason == 0x0402 and err.value.text == text
        info = c.slot_info(Slot.PARAMS)
        assert info.active and info.length == len(good)  # the previous set stays active
    assert device.alive and "Traceback" not in device.stderr()
