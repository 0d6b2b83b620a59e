"""Fixtures of the conformance suite: real ``st16-device --pty`` processes (``conf_device``),
opened raw with pyserial and spoken to in bytes (``nsp_min.Link``); every device started is
stopped with SIGTERM and reaped at teardown."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from .conf_device import DeviceProcess
from .icd import init_application
from .nsp_min import Link


@pytest.fixture
def start_device(tmp_path) -> Iterator:
    """``start(*extra)``: a fresh device (bootloader mode, its own state directory); every device
    started is stopped and reaped at teardown."""
    started: list[DeviceProcess] = []

    def start(*extra: str) -> DeviceProcess:
        dev = DeviceProcess(tmp_path / f"state{len(started)}", *extra)
        started.append(dev)
        return dev

    yield start
    for dev in started:
        dev.stop()


@pytest.fixture
def boot(start_device) -> Link:
    """A fresh device in bootloader mode, default arguments."""
    return start_device().link


@pytest.fixture(scope="session")
def app_device(tmp_path_factory) -> Iterator[DeviceProcess]:
    """One device for the session, put in application mode once (INIT 0x00002000)."""
    dev = DeviceProcess(tmp_path_factory.mktemp("conformance-app"))
    try:
        assert init_application(dev.link).ack
        yield dev
    finally:
        dev.stop()


@pytest.fixture
def app(app_device) -> Link:
    """The session's application-mode device, its input drained."""
    app_device.link.drain()
    return app_device.link
