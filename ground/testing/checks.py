"""Checks shared by the campaigns: a device still answers PING, and what it sent is valid NSP."""

from __future__ import annotations

import time

from ground.link.client import Client, LinkError
from ground.testing.device_proc import DeviceProcess
from ground.testing.tally import Tally
from protocol import nsp, slip

QUIET = 0.03  #: seconds without a byte that end a drain
DRAIN_BOUND = 5.0  #: seconds a drain may last at most (a device still sending past that is a hang)


def drain(client: Client, tally: Tally, quiet: float = QUIET, bound: float = DRAIN_BOUND) -> bytes:
    """Read until the line is quiet for ``quiet`` s; count a hang if it never is within ``bound`` s.
    Every frame read is checked to be a valid NSP message from the device to the host."""
    out = bytearray()
    start = last = time.monotonic()
    while time.monotonic() - last < quiet:
        if time.monotonic() - start > bound:
            tally.fail("hangs", f"the device kept sending for {bound} s")
            break
        chunk = client.read_raw(quiet / 3)
        if chunk:
            out += chunk
            last = time.monotonic()
    check_replies(bytes(out), client, tally)
    return bytes(out)


def check_replies(data: bytes, client: Client, tally: Tally) -> int:
    """Count the device's frames in ``data``; each must decode and go from the device to the host."""
    n = 0
    for event in slip.Decoder(nsp.MAX_MESSAGE).feed(data + bytes([slip.FEND])):
        try:
            msg = nsp.decode(event.data) if isinstance(event, slip.Frame) else None
        except nsp.MessageError:
            msg = None
        if msg is None or (msg.dst, msg.src) != (client.host_address, client.device_address):
            tally.fail("bad_replies", f"device sent {event!r:.120}")
        n += 1
    return n


def ping_check(client: Client, tally: Tally, device: DeviceProcess | None = None, bound: float | None = None) -> bool:
    """One PING through ``client``: True if answered with a banner within ``bound`` s (default:
    the client's timeout plus 1 s). Otherwise counts a crash (device process gone), a hang (the
    call overran its bound) or an unanswered ping."""
    tally.messages += 1
    bound = client.timeout * (1 + client.retries) + 1.0 if bound is None else bound
    t0 = time.monotonic()
    try:
        banner = client.ping()
        ok = banner.startswith("ST16-EMU")
        if not ok:
            tally.fail("misattributed", f"PING answered {banner!r:.80}")
    except LinkError as exc:
        ok = False
        if device is not None and not device.alive:
            tally.fail("crashes", f"device exited {device.proc.returncode}: {device.stderr()[-300:]!r}")
        else:
            tally.fail("unanswered_pings", str(exc)[:200])
    if time.monotonic() - t0 > bound:
        tally.fail("hangs", f"PING took {time.monotonic() - t0:.2f} s (bound {bound:.2f} s)")
    return ok


def stderr_check(device: DeviceProcess, tally: Tally) -> None:
    """Count the tracebacks the device printed (each is a bug, even if it kept serving)."""
    from ground.testing.device_proc import tracebacks

    text = device.stderr()
    n = tracebacks(text)
    if n:
        tally.tracebacks += n
        tally.notes.append(f"tracebacks: {text[text.find('Traceback') :][:600]}")
