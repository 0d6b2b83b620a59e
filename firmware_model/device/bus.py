"""Several tracker heads on one link: the RS-485 bus (docs/ICD.md section 14).

The ICD puts several trackers on one command line, each on its own NSP address: a tracker acts
only on commands addressed to it, and its telemetry line is three-stated when idle. :class:`Bus`
is that line seen from the heads' side. It owns the SLIP decoding and routes each complete frame
to the one head whose address is the frame's destination (byte 0), so

* a head answers only its own address, and two heads never answer one command (the addresses are
  distinct, checked when the bus is built);
* a frame to an address no head has is ignored and counted (:attr:`Bus.unknown`);
* framing errors and oversize frames are heard by every head's UART: each head counts them, as a
  lone device does; a frame for one head is ``other_address`` to the others.

Replies never interleave on the line: the bus has the face of a
:class:`~firmware_model.device.device.Device` that :func:`firmware_model.device.link.serve` drives
(``receive(chunk, arrived)``, ``late_reply``, ``wait_idle``), and ``serve`` writes one command's
frames, and each late reply, under one lock, whichever head produced them. The bus itself keeps
the same rule for a caller that takes late replies without ``serve`` (:meth:`Bus.late_reply`
wraps each head's callback in :attr:`Bus.write_lock`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence

from firmware_model.device.device import Device
from firmware_model.device.faults import Fault
from protocol import nsp, slip

MAX_HEADS = 4  #: the heads one bus carries (issue 45: 1-4)


class Bus:
    """The heads ``heads`` (distinct addresses, 1..:data:`MAX_HEADS`) on one line."""

    def __init__(self, heads: Sequence[Device]):
        if not 1 <= len(heads) <= MAX_HEADS:
            raise ValueError(f"a bus carries 1-{MAX_HEADS} heads, got {len(heads)}")
        by_address: dict[int, Device] = {}
        for head in heads:
            if head.address in by_address:
                raise ValueError(f"two heads at address 0x{head.address:02X}")
            by_address[head.address] = head
        self.heads: tuple[Device, ...] = tuple(heads)
        self.by_address = by_address
        self._decoder = slip.Decoder(nsp.MAX_MESSAGE)
        self.unknown = 0  #: complete frames whose destination no head has (ignored)
        self.framing = 0  #: frames dropped for a bad escape (each head counts them too)
        self.oversize = 0  #: frames dropped as too long (each head counts them too)
        self.routed = {a: 0 for a in by_address}  #: frames handed to each head
        self.write_lock = threading.Lock()  #: held while one head's late reply is handed on
        self._late: Callable[[list[bytes]], None] | None = None

    # ------------------------------------------------------------------ the Device's face for serve

    @property
    def late_reply(self) -> Callable[[list[bytes]], None] | None:
        return self._late

    @late_reply.setter
    def late_reply(self, callback: Callable[[list[bytes]], None] | None) -> None:
        """Give every head ``callback`` for its late replies, one head's reply at a time."""
        self._late = callback
        wrapped = None if callback is None else self._serialised(callback)
        for head in self.heads:
            head.late_reply = wrapped

    def _serialised(self, callback: Callable[[list[bytes]], None]) -> Callable[[list[bytes]], None]:
        def late(frames: list[bytes]) -> None:
            with self.write_lock:
                callback(frames)

        return late

    def receive(self, chunk: bytes, arrived: float | None = None) -> list[bytes]:
        """Feed the line's bytes; the frames to transmit, in order (one command's replies, whole)."""
        out: list[bytes] = []
        for event in self._decoder.feed(chunk):
            if isinstance(event, slip.FramingError):
                self.framing += 1
                for head in self.heads:
                    head.counters.framing += 1
            elif isinstance(event, slip.Oversize):
                self.oversize += 1
                for head in self.heads:
                    head.counters.oversize += 1
            else:
                out.extend(self._route(event.data, arrived))
        return out

    def _route(self, raw: bytes, arrived: float | None) -> list[bytes]:
        head = self.by_address.get(raw[0])
        if head is None:
            self.unknown += 1
            for other in self.heads:
                other.counters.other_address += 1
            return []
        self.routed[head.address] += 1
        for other in self.heads:
            if other is not head:
                other.counters.other_address += 1
        # the head decodes the frame itself (runts and bad CRCs counted by the addressed head)
        return head.receive(slip.encode(raw), arrived)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until no head runs a sequence; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        for head in self.heads:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not head.wait_idle(left):
                return False
        return True

    # ------------------------------------------------------------------ the heads together

    @property
    def busy(self) -> bool:
        return any(head.busy for head in self.heads)

    def arm(self, faults: tuple[Fault, ...]) -> int:
        """Arm ``faults`` in every head; the number armed per head."""
        armed = 0
        for head in self.heads:
            armed = head.arm(faults)
        return armed

    def drop_delayed(self) -> None:
        """Drop every head's delayed replies (serving stops)."""
        for head in self.heads:
            head.faults.delayed.drop()

    def close(self) -> None:
        """Close each head's solver (its index-building process), once per solver."""
        seen: set[int] = set()
        for head in self.heads:
            close = getattr(head.solver, "close", None)
            if close is not None and id(head.solver) not in seen:
                seen.add(id(head.solver))
                close()
