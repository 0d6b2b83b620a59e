"""Time correlation with the device clock, as a flight driver does it (docs/ICD.md section 6,
TIME): poll TIME, fit the device clock against the host's, map the device's time tags (the result's
``epoch``) to host time.

Each poll's latch is placed at the midpoint of its exchange (or, on a paced line, at the host's
send time plus the command frame's UART time); only the polls whose round trip is in the fastest
quarter are fitted, as NTP does, since a poll delayed in either direction says little about when
its latch happened. The fit is a straight line: the device clock's offset and rate.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from protocol import nsp
from protocol.commands import Code


@dataclass(frozen=True)
class ClockMap:
    """``device_s = offset + rate * (host_s - host0)``: the device clock against the host's."""

    host0: float
    offset: float
    rate: float
    polls: int  #: polls fitted

    def to_host(self, device_s: float) -> float:
        """Host time (the host clock's s) of a device time tag (s of the TIME count)."""
        return self.host0 + (device_s - self.offset) / self.rate

    @property
    def drift_ppm(self) -> float:
        """How much faster the device clock runs than the host's, ppm."""
        return (self.rate - 1.0) * 1e6


def latch_estimate(t_send: float, t_recv: float, baud: int | None = None) -> float:
    """The host's estimate of when a TIME command's final FEND reached the device: the exchange's
    midpoint, or on a paced line (``baud``) the send time plus the frame's time on the line."""
    if baud is None:
        return 0.5 * (t_send + t_recv)
    n = len(nsp.command(nsp.DEVICE_ADDRESS, nsp.HOST_ADDRESS, Code.TIME).frame())
    return t_send + n * 10.0 / baud


def fit(host: np.ndarray, device: np.ndarray, rtt: np.ndarray) -> ClockMap:
    """The line through the polls (host s, device s) whose round trip ``rtt`` is in the fastest
    quarter (at least two polls)."""
    keep = rtt <= np.percentile(rtt, 25)
    if keep.sum() < 2:
        keep = np.argsort(rtt)[:2]
    h, d = host[keep], device[keep]
    host0 = float(host[0])
    if np.ptp(h) > 0:
        rate, offset = np.polyfit(h - host0, d, 1)
    else:
        rate, offset = 1.0, float(np.mean(d - (h - host0)))
    return ClockMap(host0, float(offset), float(rate), int(np.size(h)))


def correlate(
    client,
    polls: int = 20,
    gap_s: float = 0.01,
    clock: Callable[[], float] = time.monotonic,
    baud: int | None = None,
) -> ClockMap:
    """Poll TIME ``polls`` times ``gap_s`` apart on ``client`` and fit (``clock``: the host clock)."""
    host, device, rtt = [], [], []
    for _ in range(polls):
        t0 = clock()
        micros = client.time()
        t1 = clock()
        host.append(latch_estimate(t0, t1, baud))
        device.append(micros / 1e6)
        rtt.append(t1 - t0)
        time.sleep(gap_s)
    return fit(np.array(host), np.array(device), np.array(rtt))
