"""``st16-ground catalog upload/info`` over a pty: interruption, device restart, corrupt images."""

import json
import threading
from contextlib import contextmanager

import guards
import pytest

from firmware_model.device.catalog_slot import catalog_slot_handler
from firmware_model.device.device import Device
from firmware_model.device.link import PtyLink, serve
from firmware_model.device.slots import SlotStore
from ground.cli.main import main as cli_main
from ground.link.client import Client, Nack
from ground.testing.upload_faults import catalog_image as _image
from ground.testing.upload_faults import wrong_version
from protocol.catalog_image import Reason
from protocol.crc import crc32


@contextmanager
def running_device(state):
    """A device with the catalog validator on slot 0, persisting in ``state``, served on a pty."""
    device = Device(store=SlotStore(state), slots={0: catalog_slot_handler()})
    link, stop = PtyLink(), threading.Event()
    thread = threading.Thread(target=serve, args=(device, link, stop), daemon=True)
    thread.start()
    try:
        yield device, link.path
    finally:
        stop.set()
        thread.join(2)
        link.close()


def test_upload_survives_interruption_restart_and_corrupt_images(tmp_path, capsys):
    state = tmp_path / "state"
    first, second = _image(1), _image(2)
    path1, path2 = tmp_path / "one.img", tmp_path / "two.img"
    path1.write_bytes(first)
    path2.write_bytes(second)

    with running_device(state) as (_, port):
        assert cli_main(["--port", port, "--json", "catalog", "upload", str(path1)]) == 0
        up = json.loads(capsys.readouterr().out)
        assert up["verified"] and up["crc32"] == f"0x{crc32(first):08X}"
        with Client(
            port, timeout=guards.REPLY_S
        ) as c:  # start the second image, then the device goes away mid-transfer
            c.xfer_begin(0, len(second), crc32(second))
            for off in range(0, 8192, 2048):
                c.xfer_data(0, off, second[off : off + 2048])

    with running_device(state) as (device, port):  # restart: first image active, second resumable
        assert device._objects[0].n_stars == 300
        assert cli_main(["--port", port, "--json", "catalog", "info"]) == 0
        info = json.loads(capsys.readouterr().out)
        assert info["active"] and info["crc32"] == f"0x{crc32(first):08X}" and info["n_stars"] == 300
        assert cli_main(["--port", port, "--json", "catalog", "upload", str(path2)]) == 0
        up = json.loads(capsys.readouterr().out)
        assert up["resumed_from"] == 8192 and up["sent"] == len(second) - 8192

        bad = bytearray(first)
        bad[len(bad) // 2] ^= 0x04  # bit flip inside the pair table
        v2 = wrong_version(first, 2)  # a future version, header re-signed
        for corrupt, reason in (
            (bytes(bad), Reason.SECTION_CRC),
            (first[:-16], Reason.TRUNCATED),
            (v2, Reason.BAD_VERSION),
        ):
            with Client(port, timeout=guards.REPLY_S) as c:
                with pytest.raises(Nack) as exc:
                    c.upload(0, corrupt, progress=False)
                assert exc.value.reason == reason
                held = c.slot_info(0)
                assert held.active and held.crc32 == crc32(second)  # the previous catalog stays active

        (tmp_path / "bad.img").write_bytes(bytes(bad))  # the CLI refuses it before sending
        assert cli_main(["--port", port, "catalog", "upload", str(tmp_path / "bad.img")]) == 2
        assert "SECTION_CRC" in capsys.readouterr().err

    with running_device(state) as (device, port):  # restart again: the second image persisted
        with Client(port, timeout=guards.REPLY_S) as c:
            held = c.slot_info(0)
        assert held.active and held.crc32 == crc32(second)
        assert device._objects[0].meta["created_unix"] == 1_700_000_002
