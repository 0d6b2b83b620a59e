"""``st16-device --heads FILE``: 1-4 tracker heads behind one link (docs/ICD.md section 14).

FILE is JSON::

    {"heads": [
        {"address": "0x0E", "mount_q": [1, 0, 0, 0]},
        {"address": "0x0F", "mount_q": [0.7071068, 0, 0.7071068, 0],
         "camera": "cam_b.json", "params": "params_b.json"}
    ]}

``address`` is the head's NSP address (a number, or a string in any base ``int(s, 0)`` reads:
``"0x0F"``, ``"15"``), 0x00-0xFF, distinct; ``mount_q`` the head's mounting, the body-to-sensor
rotation as a scalar-first unit quaternion (docs/CONVENTIONS.md: ``v_sensor = M @ v_body``);
``camera`` and ``params`` optionally replace ``--camera`` and ``--params`` for that head (a
relative path is taken from the heads file's folder). Each head is a whole
:class:`~firmware_model.device.device.Device`: its own state, result, counters, clock, solver and,
with ``--state DIR``, its own folder ``DIR/head-0xAA``.

With heads, the capture source gives the **body's** attitude (``--sky``'s ``q_icrs_to_sensor``
column is read as ``q_icrs_to_body``; the attitude feed's samples likewise); each head renders its
own view through its mounting, so the Sun can blind one head and not another. ``--sky`` gives
every head its own copy of the schedule (the n-th GO of each head renders the n-th row); the
attitude feed is one listener shared by the heads, so its heads share one camera. ``--frames``
replays the same files to every head (a file is a sensor's view: no mounting applies).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from firmware_model.device.bus import MAX_HEADS, Bus
from firmware_model.device.device import Device, SolveContext
from firmware_model.device.faults import Fault
from firmware_model.reference_frames import quat_to_matrix
from protocol import nsp

log = logging.getLogger(__name__)

MAX_FILE_BYTES = 64 * 1024  #: a heads file is a few lines; anything larger is a wrong file
UNIT_TOLERANCE = 1e-6  #: |norm(mount_q) - 1| allowed
HEAD_KEYS = {"address", "mount_q", "camera", "params"}


@dataclass(frozen=True)
class HeadSpec:
    """One head of the heads file."""

    address: int
    mount_q: tuple[float, float, float, float]
    camera: str | None = None
    params: str | None = None

    @property
    def mount(self) -> np.ndarray:
        """The body-to-sensor matrix ``M``: ``v_sensor = M @ v_body``."""
        return quat_to_matrix(self.mount_q)


def parse_heads(obj: Any, name: str = "heads file", base: Path | None = None) -> tuple[HeadSpec, ...]:
    """The heads of a parsed heads file; ValueError (one line naming ``name``) when it is wrong."""
    if not isinstance(obj, dict) or not isinstance(obj.get("heads"), list):
        raise ValueError(f'{name}: expected {{"heads": [{{"address": ..., "mount_q": [w, x, y, z]}}, ...]}}')
    rows = obj["heads"]
    if not 1 <= len(rows) <= MAX_HEADS:
        raise ValueError(f"{name}: {len(rows)} heads; a bus carries 1-{MAX_HEADS}")
    heads: list[HeadSpec] = []
    seen: set[int] = set()
    for k, row in enumerate(rows, 1):
        where = f"{name}: head {k}"
        if not isinstance(row, dict):
            raise ValueError(f"{where}: expected an object")
        unknown = sorted(set(row) - HEAD_KEYS)
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {unknown}; known: {sorted(HEAD_KEYS)}")
        address = _address(row.get("address"), where)
        if address in seen:
            raise ValueError(f"{where}: duplicate address 0x{address:02X}")
        seen.add(address)
        mount = _mount(row.get("mount_q", [1.0, 0.0, 0.0, 0.0]), where)
        files = {}
        for key in ("camera", "params"):
            value = row.get(key)
            if value is not None:
                if not isinstance(value, str) or not value:
                    raise ValueError(f"{where}: {key} must be a file name")
                path = Path(value)
                files[key] = str(path if path.is_absolute() or base is None else base / path)
        heads.append(HeadSpec(address, mount, **files))
    return tuple(heads)


def _address(value: Any, where: str) -> int:
    if isinstance(value, bool) or value is None:
        raise ValueError(f"{where}: address missing (a number 0x00-0xFF)")
    if isinstance(value, str):
        try:
            value = int(value, 0)
        except ValueError:
            raise ValueError(f"{where}: address {_echo(value)} is not a number") from None
    if not isinstance(value, int):
        raise ValueError(f"{where}: address {_echo(value)} is not a number")
    if not 0 <= value <= 0xFF:
        raise ValueError(f"{where}: address {value:#x} outside 0x00-0xFF")
    return value


def _echo(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _mount(value: Any, where: str) -> tuple[float, float, float, float]:
    if (
        not isinstance(value, list)
        or len(value) != 4
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    ):
        raise ValueError(f"{where}: mount_q must be 4 numbers [w, x, y, z]")
    q = tuple(float(v) for v in value)
    norm = math.sqrt(sum(v * v for v in q))
    if not math.isfinite(norm) or abs(norm - 1.0) > UNIT_TOLERANCE:
        raise ValueError(f"{where}: mount_q norm {norm:.9g} is not 1 (a unit quaternion, scalar first)")
    return q  # type: ignore[return-value]


def load_heads(path: str) -> tuple[HeadSpec, ...]:
    """The heads file at ``path``; ValueError naming it."""
    file = Path(path)
    try:
        if not file.is_file():
            raise ValueError(f"--heads {path}: {'not a regular file' if file.exists() else 'no such file'}")
        if file.stat().st_size > MAX_FILE_BYTES:
            raise ValueError(f"--heads {path}: over {MAX_FILE_BYTES} bytes: not a heads file")
        obj = json.loads(file.read_bytes())
    except OSError as exc:
        raise ValueError(f"--heads {path}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"--heads {path}: not JSON ({str(exc)[:80]})") from None
    return parse_heads(obj, f"--heads {path}", Path(path).parent)


class MountedSource:
    """A body-attitude capture source seen through one head's mounting: calls ``source(ctx,
    mount=M)``."""

    def __init__(self, source: Callable[..., Any], mount: np.ndarray):
        self.source = source
        self.mount = mount

    def __call__(self, ctx: SolveContext) -> Any:
        return self.source(ctx, mount=self.mount)

    def ready(self) -> None:
        ready = getattr(self.source, "ready", None)
        if ready is not None:
            ready()


def build_bus(args: argparse.Namespace, heads: tuple[HeadSpec, ...]) -> Bus:
    """One :class:`Device` per head (``cli.build_device`` with the head's address, camera,
    parameters and state folder), its capture source mounted, on one :class:`Bus`."""
    from firmware_model.device import cli  # the one device builder

    shared = None
    if args.attitude_feed:  # one listener for every head: their clocks follow its simulated time
        from firmware_model.device.sensor_input import load_frame_source

        cameras = {h.camera or args.camera for h in heads}
        if len(cameras) > 1:
            raise ValueError("--attitude-feed with --heads: the heads share one feed, so one camera (drop 'camera')")
        shared = load_frame_source("attitude_feed", args.attitude_feed, cli.load_camera(cameras.pop()))
    devices: list[Device] = []
    for head in heads:
        ns = argparse.Namespace(**vars(args))
        ns.address = head.address
        ns.camera = head.camera or args.camera
        ns.params = head.params or args.params
        ns.state = None if args.state is None else str(Path(args.state) / f"head-0x{head.address:02X}")
        device = cli.build_device(ns, shared_source=shared)
        if args.sky or args.attitude_feed:
            device.frame_source = MountedSource(device.frame_source, head.mount)  # type: ignore[arg-type]
        devices.append(device)
    ready = getattr(shared, "ready", None)
    if ready is not None:
        ready()
    return Bus(devices)


def build_from_file(args: argparse.Namespace, faults: tuple[Fault, ...]) -> Bus:
    """``st16-device --heads``: the bus of the heads file's heads, ``faults`` armed in each (served
    as ``cli.main`` serves one device); a bad heads file or option raises ValueError in one line."""
    if args.address != nsp.DEVICE_ADDRESS:
        raise ValueError("--address and --heads: the heads file gives each head's address")
    heads = load_heads(args.heads)
    bus = build_bus(args, heads)
    bus.arm(faults)
    log.info("heads %s", ", ".join(f"0x{h.address:02X}" for h in heads))
    return bus
