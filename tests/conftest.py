"""Shared fixtures: the read-only data in ../shared (skipped cleanly when absent)."""

import threading
from pathlib import Path

import pytest
from hypothesis import settings

# Property tests check behaviour, not speed: no per-example deadline (the machine is shared).
settings.register_profile("project", deadline=None)
settings.load_profile("project")

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture
def served_device():
    """Path of a pty served by an in-process default Device (stopped after the test)."""
    from firmware_model.device.device import Device
    from firmware_model.device.link import PtyLink, serve

    link, stop = PtyLink(), threading.Event()
    thread = threading.Thread(target=serve, args=(Device(), link, stop), daemon=True)
    thread.start()
    yield link.path
    stop.set()
    thread.join(2)
    link.close()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    path = SHARED / "data"
    if not path.is_dir():
        pytest.skip("../shared/data is absent")
    return path
