"""A device process for the ground's runs (the demo, the HIL loop, tests and benchmarks):
``st16-device --pty`` started as a child and stopped; and attitudes worth rendering, whose field
holds enough catalog stars."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.reference_frames import attitude_from_radec_roll

#: A rendered frame shows at least this many catalog stars (a "well-populated field").
MIN_CATALOG_STARS = 8
#: Degrees beyond a body's exclusion angle that :func:`pick_attitudes` keeps a boresight clear by.
EXCLUSION_MARGIN_DEG = 5.0


def pick_attitudes(catalog, camera: CameraModel, n: int, rng, epoch: str | None = None) -> list[np.ndarray]:
    """``n`` random attitudes whose field holds at least MIN_CATALOG_STARS catalog stars; with
    ``epoch`` (ISO-8601 UTC, the frames' time), only those whose boresight is clear of the Sun and
    the Moon by their default exclusion angles plus :data:`EXCLUSION_MARGIN_DEG` (geocentric), so
    that a run of frames stamped with that time is not refused for a body a tracker would not be
    pointed at."""
    out: list[np.ndarray] = []
    radius = np.arctan(np.hypot(camera.width, camera.height) / 2 / camera.f)
    bodies = {}
    if epoch is not None:
        from firmware_model.pipeline.exclusion import ExclusionLimits
        from firmware_model.pipeline.sky_bodies import sky_bodies

        limits = ExclusionLimits()
        bodies = {name: (b, limits.limit_deg(name) + EXCLUSION_MARGIN_DEG) for name, b in sky_bodies(epoch).items()}
    while len(out) < n:
        ra, dec, roll = rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi)
        a = attitude_from_radec_roll(ra, dec, roll)
        if any(np.degrees(b.edge_angle(a[2])) < clear_deg for b, clear_deg in bodies.values()):
            continue
        near = catalog.stars_within(a[2], radius)
        x, y = camera.vector_to_pixel(catalog.vec[near] @ a.T)
        if np.count_nonzero(camera.in_frame(x, y)) >= MIN_CATALOG_STARS:
            out.append(a)
    return out


def start_device(state_dir: Path, *extra: str) -> tuple[subprocess.Popen[str], str]:
    """``st16-device --pty --state STATE_DIR EXTRA...`` as a child: (the process, its pty) once it
    says ``listening on``."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "firmware_model.device.cli", "--pty", "--state", str(state_dir), *extra],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None  # stdout=PIPE
    line = proc.stdout.readline().strip()
    if not line.startswith("listening on "):
        proc.kill()
        raise RuntimeError(f"device did not start: {line!r}")
    return proc, line[len("listening on ") :]


#: How long :func:`stop_device` waits for a device to end after SIGTERM (s): beyond the device's own
#: stop watchdog (``firmware_model.device.cli.STOP_WATCHDOG_S``), for a device without it.
STOP_TIMEOUT_S = 30.0


def stop_device(proc: subprocess.Popen[str]) -> int:
    """SIGTERM, and its exit code (not 0: also one line on stderr; a stop the device's own
    watchdog ended is 1, its threads' stacks above it). A device still running
    :data:`STOP_TIMEOUT_S` later is asked for its stacks (SIGUSR1), killed, and reported
    (RuntimeError)."""
    proc.send_signal(signal.SIGTERM)
    try:
        rc = proc.wait(timeout=STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(1.0)  # the dump's time to reach stderr (a hang guard's pause, decides nothing)
        proc.kill()
        proc.wait()
        raise RuntimeError(
            f"device pid {proc.pid} did not stop within {STOP_TIMEOUT_S:g} s of SIGTERM (its stacks: its stderr)"
        ) from None
    if proc.stdout is not None:  # start_device's pipe
        proc.stdout.close()
    if rc != 0:
        print(f"device pid {proc.pid} stopped with exit status {rc}", file=sys.stderr)
    return rc
