"""``st16-device`` as a child process for fault campaigns: start, check, stop, read its stderr.

stderr goes to a file (a pipe nobody reads could fill and stall the device); :meth:`stderr`
returns it, and :func:`tracebacks` counts the tracebacks in a text.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

START_TIMEOUT = 30.0  #: seconds the device may take to print its ``listening on`` line


def device_command() -> list[str]:
    """The ``st16-device`` entry point of this interpreter's environment."""
    script = Path(sys.executable).parent / "st16-device"
    if script.exists():
        return [str(script)]
    found = shutil.which("st16-device")
    return [found] if found else [sys.executable, "-m", "firmware_model.device.cli"]


def tracebacks(text: str) -> int:
    return text.count("Traceback (most recent call last)")


class DeviceProcess:
    """``st16-device ARGS``; :attr:`path` is the link it serves (``listening on <path>``).
    Raises RuntimeError with the device's stderr if it exits before listening."""

    def __init__(self, *args: str):
        self._err = tempfile.TemporaryFile(mode="w+")
        self.proc = subprocess.Popen(device_command() + list(args), stdout=subprocess.PIPE, stderr=self._err, text=True)
        assert self.proc.stdout is not None  # stdout=PIPE
        line = self.proc.stdout.readline().strip()
        if not line.startswith("listening on "):
            self.proc.wait(START_TIMEOUT)
            raise RuntimeError(f"st16-device did not start (exit {self.proc.returncode}): {line!r} {self.stderr()!r}")
        self.path = line[len("listening on ") :]

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def stderr(self) -> str:
        self._err.flush()
        self._err.seek(0)
        return self._err.read()

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int:
        """Signal the device and wait; SIGKILL if it does not exit in ``timeout`` s. Exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        if self.proc.stdout is not None:  # the pipe opened in __init__
            self.proc.stdout.close()
        return rc

    def __enter__(self) -> DeviceProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
