"""A real ``st16-device --pty`` process and a raw link to its pty, for the conformance suite: a
copy of the few lines of ground/sim/device_process.py, not an import of it (the suite depends on
nothing of the project but the device's command line)."""

from __future__ import annotations

import os
import select
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from .nsp_min import Link

#: Hang guard for a device start (the first start after an install compiles kernels, ~40 s).
START_S = 180.0


def device_command() -> list[str]:
    """The ``st16-device`` entry point beside this interpreter (the venv's), else on PATH."""
    beside = Path(sys.executable).parent / "st16-device"
    if beside.exists():
        return [str(beside)]
    found = shutil.which("st16-device")
    if found is None:
        pytest.fail("st16-device is not installed: pip install -e '.[test]'", pytrace=False)
    return [found]


class DeviceProcess:
    """One ``st16-device --pty --state DIR EXTRA...`` child and a raw link to its pty."""

    def __init__(self, state_dir: Path, *extra: str) -> None:
        self.proc = subprocess.Popen(
            [*device_command(), "--pty", "--state", str(state_dir), *extra], stdout=subprocess.PIPE
        )
        assert self.proc.stdout is not None
        line = self._first_line()
        if not line.startswith("listening on "):
            self.proc.kill()
            self.proc.wait()
            raise RuntimeError(f"device did not start: {line!r}")
        self.path = line[len("listening on ") :]
        self.port = serial.Serial(self.path, baudrate=115200, timeout=0)
        self.link = Link(self.port)

    def _first_line(self) -> str:
        assert self.proc.stdout is not None
        fd, buf, deadline = self.proc.stdout.fileno(), b"", time.monotonic() + START_S
        while b"\n" not in buf:
            ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
            if not ready:
                self.proc.kill()
                raise RuntimeError(f"device said nothing within the {START_S} s hang guard")
            chunk = os.read(fd, 4096)
            if not chunk:
                break
            buf += chunk
        return buf.split(b"\n", 1)[0].decode(errors="replace").strip()

    def stop(self) -> int:
        """SIGTERM, reaped; the exit status."""
        self.port.close()
        self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return rc
