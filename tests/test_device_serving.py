"""``st16-device``'s one start/serve/stop sequence (``cli.serve_until_stopped``), whatever serves the
link: one device or the heads' bus. Start-up's objects are frozen out of the garbage collector
before ``listening on``, and serving stops by dropping delayed replies, waiting for the running
sequence, closing the link, then the solvers."""

import gc
import signal
import subprocess
import sys
import time

import guards
import pytest

from firmware_model.device import cli


class Target:
    """A stand-in for a Device or a Bus: records what the serving sequence calls."""

    def __init__(self, calls: list):
        self.calls = calls

    def drop_delayed(self):
        self.calls.append("drop_delayed")

    def wait_idle(self, timeout=None):
        self.calls.append("wait_idle")
        return True

    def close(self):
        self.calls.append("close")


@pytest.fixture
def served(monkeypatch, capsys):
    """Runs ``serve_until_stopped`` on a pty with ``serve`` replaced: what it was called with, the
    freeze count at that moment, the calls in order and stdout."""
    seen: dict = {"served": False}

    def fake_serve(target, link, stop, **kw):
        seen["freeze_count"] = gc.get_freeze_count()
        seen["served"] = True
        if isinstance(target, Target):
            target.calls.append("serve")

    monkeypatch.setattr(cli, "serve", fake_serve)

    def run(build):
        gc.unfreeze()
        try:
            args = cli.build_parser().parse_args(["--pty"])
            rc = cli.serve_until_stopped(args, 0.0, build)
        finally:
            gc.unfreeze()
        return rc, seen, capsys.readouterr()

    return run


def test_the_target_is_served_frozen_and_stopped_in_order(served):
    calls: list = []
    rc, seen, out = served(lambda args, faults: Target(calls))
    assert rc == 0
    assert out.out.startswith("listening on ")
    assert seen["freeze_count"] > 0
    assert calls == ["serve", "drop_delayed", "wait_idle", "close"]


def test_a_build_that_fails_is_one_line_and_nothing_is_served(served):
    def build(args, faults):
        raise ValueError("heads file h.json: no such file")

    rc, seen, out = served(build)
    assert rc == 2
    assert out.err == "st16-device: heads file h.json: no such file\n"
    assert "listening" not in out.out and not seen["served"]


def test_the_heads_option_is_served_by_the_same_sequence(monkeypatch):
    """``--heads`` builds the bus through ``serve_until_stopped`` too (it had its own copy, without
    the garbage collector's freeze)."""
    from firmware_model.device import heads

    used = {}

    def fake(args, turnaround_ms, build):
        used["build"] = build
        return 0

    monkeypatch.setattr(cli, "serve_until_stopped", fake)
    assert cli.main(["--pty", "--heads", "h.json"]) == 0
    assert used["build"] is heads.build_from_file


STUCK_AT_STOP = """
import sys, threading
from firmware_model.device import cli

cli.STOP_WATCHDOG_S = 1.0


class Stuck:
    late_reply = None

    def drop_delayed(self):
        pass

    def wait_idle(self, timeout=None):
        return True

    def close(self):  # as a child process or a thread that never ends would hold the exit
        threading.Event().wait()


sys.exit(cli.serve_until_stopped(cli.build_parser().parse_args(["--pty"]), 0.0, lambda args, faults: Stuck()))
"""


@pytest.mark.timeout(3 * guards.HANG_S)
def test_a_stop_that_cannot_finish_ends_the_process_with_every_thread_s_stack():
    """SIGTERM, and a stop held by something that never ends: the process still ends (status 1),
    with the stacks on stderr naming where it was held (it used to wait for ever)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", STUCK_AT_STOP], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().startswith("listening on ")
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=guards.HANG_S)
    finally:
        proc.kill()
    assert proc.returncode == 1
    assert "Timeout" in err and "in close" in err, err


@pytest.mark.timeout(3 * guards.HANG_S)
def test_signals_that_keep_coming_do_not_postpone_the_stop_s_end():
    """SIGTERM again and again while the stop is held: the watchdog counts from the first (a
    later signal used to restart its count, so a process signalled more often than its bound
    never ended)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", STUCK_AT_STOP], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().startswith("listening on ")
        sent = 0
        while proc.poll() is None and sent < guards.HANG_S / 0.25:  # a hang guard: signals for 60 s at most
            proc.send_signal(signal.SIGTERM)
            sent += 1
            time.sleep(0.25)  # more often than the stuck process' 1 s bound
        ended_while_signalled = proc.poll() is not None
        _, err = proc.communicate(timeout=guards.HANG_S)
    finally:
        proc.kill()
    assert ended_while_signalled, f"still running after {sent} signals"
    assert proc.returncode == 1
    assert "Timeout" in err and "in close" in err, err
