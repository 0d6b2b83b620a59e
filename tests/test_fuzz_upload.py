"""Transfer faults never replace the active catalog (SLOT_INFO and the state file checked after
each), valid images sent out of order or overlapping do, and a device killed mid-transfer
restarts with the catalog it had (fixed seed; long run: bench/bench_fuzz.py)."""

import threading

from firmware_model.device.catalog_slot import catalog_slot_handler
from firmware_model.device.device import Device
from firmware_model.device.link import PtyLink, serve
from firmware_model.device.slots import SlotStore
from ground.link.client import Client
from ground.testing import upload_faults
from ground.testing.tally import Tally


def test_every_transfer_fault_keeps_the_active_catalog_and_a_kill_loses_nothing():
    tally = upload_faults.run(seed=3, scenarios=len(upload_faults.SCENARIOS), restarts=1)
    assert tally.failures == 0, tally.notes
    assert tally.faults == len(upload_faults.SCENARIOS) - len(upload_faults.FAULTLESS) + 1


def test_the_state_check_sees_a_replaced_image(tmp_path):
    image, other = upload_faults.catalog_image(1), upload_faults.catalog_image(2)
    device = Device(store=SlotStore(tmp_path), slots={0: catalog_slot_handler()})
    link, stop = PtyLink(), threading.Event()
    thread = threading.Thread(target=serve, args=(device, link, stop), daemon=True)
    thread.start()
    try:
        with Client(link.path) as c:
            c.upload(0, image, progress=False)
            tally = Tally()
            upload_faults.check_state(c, tmp_path, image, tally, "same")
            assert tally.failures == 0
            upload_faults.check_state(c, tmp_path, other, tally, "other")
            assert tally.state_corruptions == 2  # SLOT_INFO and active.img both disagree
    finally:
        stop.set()
        thread.join(2)
        link.close()
