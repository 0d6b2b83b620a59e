"""Solving on a device over the serial link (``replay``, ``solve``, ``e2e``), surviving link loss:
the same ``solve(frame, say)`` -> ``ground.solver.Solve`` as the in-process solver."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from firmware_model.pipeline.raw_frame import Frame, frame_to_bytes
from ground.link.solve_report import solve_record
from ground.solver import Solve
from protocol.commands import Slot

if TYPE_CHECKING:
    from ground.link.client import Client

_log = logging.getLogger(__name__)


class LinkSolver:
    """Uploads each frame to slot 1 and commands GO over the serial link. A device that stops
    answering is reported, waited for (PING every half second) and the frame is solved again once
    it is back."""

    def __init__(
        self,
        url: str,
        reconnect_timeout: float = 120.0,
        go_timeout: float = 60.0,
        log=None,
        upload_progress: bool = False,
        **client_kw,
    ):
        self.url = url
        self.upload_progress = upload_progress  #: a progress bar while the frame uploads (minutes at 115 200 baud)
        self.reconnect_timeout = reconnect_timeout
        self.go_timeout = go_timeout
        self.log = log
        self.client_kw = client_kw
        self.client: Client | None = None
        self.reconnects = 0

    def _connect(self) -> Client:
        from ground.link.client import Client

        client = Client(self.url, log=self.log, **self.client_kw)
        try:
            if "BOOTLOADER" in client.ping():
                client.init()
        except Exception:
            client.close()
            raise
        self.client = client
        _log.debug("connected to the device at %s", self.url)
        return client

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None

    def _wait_for_device(self, why: Exception, say, deadline: float) -> None:
        left = max(deadline - time.monotonic(), 0.0)
        say(f"device not answering ({type(why).__name__}: {why}); waiting up to {left:.0f} s")
        self.close()
        while time.monotonic() < deadline:
            try:
                self._connect()
                self.reconnects += 1
                say("device is back; solving the frame again")
                return
            except Exception:
                time.sleep(0.5)
        raise TimeoutError(f"device at {self.url} did not come back within {self.reconnect_timeout:.0f} s")

    def solve(self, frame: Frame | None, say: Callable[[str], object] | None = None) -> Solve:
        """Upload ``frame`` (or capture, when None), GO, and return the decoded result (the
        :class:`Solve`'s ``record``; no pipeline output). A silent or lost device is waited for, at
        most ``reconnect_timeout`` seconds in all for this frame (said through ``say``, by default a
        warning of this module's logger); a NACK is the device's answer and is raised
        (``ground.link.client.Nack``), never retried."""
        from ground.link.client import LinkError, Nack

        say = say or _log.warning

        data = frame_to_bytes(frame) if frame is not None else None
        deadline = None
        while True:
            try:
                client = self.client if self.client is not None else self._connect()
                if data is not None:
                    client.upload(Slot.FRAME, data, progress=self.upload_progress)
                return Solve(solve_record(client.go_and_wait(timeout=self.go_timeout)))
            except Nack:
                raise
            except (LinkError, OSError) as exc:
                if deadline is None:
                    deadline = time.monotonic() + self.reconnect_timeout
                self._wait_for_device(exc, say, deadline)
