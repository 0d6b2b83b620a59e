"""Children a test interrupts with Ctrl-C (SIGINT), started so that neither the test runner's
signal state nor a failed assertion leaves one running.

* The child gets SIGINT at its default disposition: a test runner started in the background by a
  shell (CI, ``&``) inherits SIGINT ignored, and a Python child would then never see the signal.
* The child runs in its own session: a Ctrl-C typed at the test runner is not delivered to it a
  second time, and its whole process group (multiprocessing workers included) can be killed.
* Its stderr is a pseudo-terminal, so the command shows its progress bar: the test waits for the
  bar to count poses (the run is under way) instead of sleeping a guessed time.
* On the way out the session's process group is killed (SIGKILL), whatever happened.
"""

from __future__ import annotations

import os
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

HANG_GUARD_S = 120.0  #: real seconds after which a child that has not got on is a failure

#: a tqdm bar that has counted at least one pose: "... 40/100000 ..."
COUNTING = re.compile(rb"\b[1-9]\d*/\d+ ")


#: one drawing of the tqdm bar of a ``sim`` command
BAR = re.compile(r"sim \w+:[^\r\n]*?pose/s\]")


def without_bar(err: str) -> list[str]:
    """The lines of ``err`` once every drawing of the progress bar is taken out."""
    return [line.strip() for line in BAR.sub("", err).splitlines() if line.strip()]


def default_sigint() -> None:
    """``preexec_fn`` of a child a test sends SIGINT: the signal at its default disposition."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Child:
    """A running ``python -m ground.cli ARGS`` (see the module docstring)."""

    def __init__(self, args: list[str]):
        master, slave = os.openpty()
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "ground.cli", *args],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=slave,
                start_new_session=True,
                preexec_fn=default_sigint,
            )
        except BaseException:
            os.close(master)
            raise
        finally:
            os.close(slave)
        self._master = master
        self.err = b""  #: everything the child wrote to stderr so far

    def _read(self, until: float) -> bool:
        """Read what stderr has until ``until`` (monotonic s); False once it is closed."""
        ready, _, _ = select.select([self._master], [], [], max(0.0, until - time.monotonic()))
        if not ready:
            return True
        try:
            data = os.read(self._master, 65536)
        except OSError:  # EIO: every writer of the terminal has gone
            return False
        self.err += data
        return bool(data)

    def wait_for(self, pattern: re.Pattern[bytes], what: str) -> None:
        """Until stderr matches ``pattern``; AssertionError (with stderr) if the child ends first or
        the hang guard passes."""
        deadline = time.monotonic() + HANG_GUARD_S
        while not pattern.search(self.err):
            if time.monotonic() > deadline or not self._read(min(deadline, time.monotonic() + 0.5)):
                raise AssertionError(f"no {what}; stderr: {self.err.decode(errors='replace')[-2000:]}")

    def interrupt(self) -> tuple[int, str]:
        """Ctrl-C: SIGINT to the child alone; returns its exit code and its whole stderr once it ends
        (within the hang guard)."""
        self.proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + HANG_GUARD_S
        while self.proc.poll() is None and time.monotonic() < deadline:
            self._read(time.monotonic() + 0.1)
        code = self.proc.wait(max(1.0, deadline - time.monotonic()))
        while select.select([self._master], [], [], 0.0)[0] and self._read(time.monotonic()):
            pass  # what it wrote before it ended (a worker left behind may hold the terminal open)
        return code, self.err.decode(errors="replace")

    def kill(self) -> None:
        """SIGKILL to the child's whole process group (its workers too); then reap it."""
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait()
        os.close(self._master)


@contextmanager
def interruptible(args: list[str]) -> Iterator[Child]:
    """``with interruptible([...]) as child``: the child of the module docstring, killed on exit."""
    child = Child(args)
    try:
        yield child
    finally:
        child.kill()
