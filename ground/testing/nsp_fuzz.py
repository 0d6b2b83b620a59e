"""Random and mutated NSP traffic against a device process; a valid PING after every burst.

Every command code with and without Poll, oversized frames and data fields, runts, bad SLIP
escapes, bad CRCs, wrong addresses, frames cut short and garbage between frames (see
:mod:`.traffic`). After each burst the replies are drained and checked (valid NSP, device to
host), the device's error counters are read and cleared, and a PING must be answered.
"""

from __future__ import annotations

import random
import tempfile

from ground.link.client import Client, LinkError
from ground.testing.checks import drain, ping_check, stderr_check
from ground.testing.device_proc import DeviceProcess
from ground.testing.tally import Tally
from ground.testing.traffic import burst, sweep

ERROR_COUNTERS = ("framing", "runt", "oversize", "bad_crc", "other_address")


def run(
    seed: int, bursts: int, frames_per_burst: int = 10, timeout: float = 2.0, device_args: tuple[str, ...] = ("--pty",)
) -> tuple[Tally, dict[str, int]]:
    """Fuzz a fresh device (persistent state in a temporary directory) started with
    ``device_args`` (its link: ``--pty``, or ``--tcp 127.0.0.1:0``, and e.g. ``--pace --baud
    921600``). Returns the tally and the device's own error counters summed over the bursts
    (proof the faults reached it)."""
    rng = random.Random(seed)
    tally, seen = Tally(), dict.fromkeys(ERROR_COUNTERS, 0)
    with tempfile.TemporaryDirectory() as state:
        device = DeviceProcess("--state", state, *device_args)
        try:
            with Client(device.path, timeout=timeout, retries=0) as client:
                for k in range(bursts + 1):
                    if k == 0:  # every code with and without Poll, every fault kind
                        frames = sweep(rng)
                        tally.messages += len(frames)
                        tally.faults += len(frames) - 64
                        client.write_raw(b"".join(frames))
                    else:
                        data, commands, faults = burst(rng, frames_per_burst)
                        tally.messages += commands + faults
                        tally.faults += faults
                        client.write_raw(data)
                    drain(client, tally)
                    if not device.alive:
                        tally.fail("crashes", f"device exited {device.proc.returncode} after burst {k}")
                        break
                    try:
                        counters = client.diagnostic(clear=True)
                        tally.messages += 1
                        for name in ERROR_COUNTERS:
                            seen[name] += getattr(counters, name)
                    except LinkError:
                        pass  # the PING below tells whether the device still serves
                    ping_check(client, tally, device)
        finally:
            rc = device.stop()
            if rc != 0:
                tally.fail("crashes", f"device exit code {rc} at stop")
            stderr_check(device, tally)
    return tally, seen
