"""``st16-device --sky SCHEDULE``: the emulated sensor renders each exposure from the real sky.

The schedule is a CSV file with a header; columns ``qw, qx, qy, qz`` (scalar-first
``q_icrs_to_sensor``) are required, ``pattern`` (RGGB/BGGR/GRBG/GBRG/MONO, default RGGB) and
``seed`` (noise seed, default the row number) are optional; ``#`` starts a comment line.
Each GO captures the next row, wrapping around at the end, so a HIL harness that knows the
schedule knows the truth of every solve. Registered as the ``sky`` entry point of
``st16.frame_sources`` (the device never imports ``ground``; the entry point plugs it in).
Exposures render only the stars in view with the noise from a bank drawn at start-up
(``ground.sim.exposure``), so GO -> result stays within the device's budget (docs/hil.md).
"""

from __future__ import annotations

import csv
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.reference_frames import quat_to_matrix
from ground.sim.exposure import ExposureRenderer
from ground.sim.sensor_sim import DetectorModel


@dataclass(frozen=True)
class Exposure:
    q_icrs_to_sensor: np.ndarray
    pattern: str
    seed: int


def read_schedule(path) -> list[Exposure]:
    """Rows of a schedule CSV, with precise errors naming the line."""
    path = Path(path)
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    rows = list(csv.DictReader(lines))
    if not rows:
        raise ValueError(f"{path}: empty schedule")
    missing = {"qw", "qx", "qy", "qz"} - set(rows[0])
    if missing:
        raise ValueError(f"{path}: schedule lacks column(s) {sorted(missing)}")
    out = []
    for k, row in enumerate(rows):
        try:
            q = np.array([float(row[c]) for c in ("qw", "qx", "qy", "qz")])
        except ValueError:
            raise ValueError(f"{path}: row {k + 1}: quaternion is not numeric: {row}") from None
        norm = np.linalg.norm(q)
        if not np.isfinite(norm) or abs(norm - 1.0) > 1e-6:
            raise ValueError(f"{path}: row {k + 1}: quaternion norm {norm:.9f} is not 1")
        out.append(Exposure(q / norm, (row.get("pattern") or "RGGB").upper(), int(row.get("seed") or k)))
    return out


class SkySource:
    """Capture source: render the sky at the next scheduled attitude (module docstring)."""

    def __init__(self, spec: str, camera: CameraModel):
        self.schedule = read_schedule(spec)
        self.renderer = ExposureRenderer(camera)
        self._drawing = self.renderer.draw_bank(DetectorModel())  # at start-up, not inside the first GO
        self._next = 0
        self._lock = threading.Lock()

    def ready(self) -> None:
        """Return once the source can render at once (its noise bank drawn)."""
        self._drawing.join()

    def __call__(self, ctx):
        with self._lock:
            exp = self.schedule[self._next % len(self.schedule)]
            self._next += 1
        return self.renderer.render(quat_to_matrix(exp.q_icrs_to_sensor), DetectorModel(pattern=exp.pattern), exp.seed)
