"""``st16-device --sky SCHEDULE``: the emulated sensor renders each exposure from the real sky.

The schedule is a CSV file with a header; columns ``qw, qx, qy, qz`` (scalar-first
``q_icrs_to_sensor``) are required, ``pattern`` (RGGB/BGGR/GRBG/GBRG/MONO, default RGGB),
``seed`` (noise seed, default the row number), ``time`` (the exposure's start, ISO-8601 UTC: the
frame's ``timestamp``) and ``x_km, y_km, z_km`` (the spacecraft's GCRS position, km; all three or
none) are optional; ``#`` starts a comment line, and a comment line ``# orbit: ALT_KM[,INC_DEG
[,RAAN_DEG[,ARG_LAT_DEG[,EPOCH_UTC]]]]`` gives a circular orbit (``ground.sim.orbit``) that places
the spacecraft at the exposure's time when a row carries no position. Each GO captures the next
row, wrapping around at the end, so a HIL harness that knows the schedule knows the truth of every
solve.

**Bright bodies** (``ground.sim.glare``) are rendered when the row says when or where the exposure
is: a ``time`` (the Sun and the Moon at its mid-time, ``time`` + exposure / 2), or a position or
orbit (then at the GO time + exposure / 2 when the row has no ``time``), the Earth too when the
position is known; such a frame carries ``timestamp`` and ``metadata["sc_position_km"]`` for the
device's bright-body check. A row with neither renders the stars alone with no timestamp, as
before: the same frame whatever the date (the device's check then has no time either, and tracking
takes the GO time). A comment line ``# effects: KEY=VALUE ...`` adds the detector effects over a
mission (``ground.sim.detector_effects.SOURCE_OPTIONS``: ``cosmic_rate``, ``hits_per_frame``,
``saa`` (with the orbit), ``dose_krad``, ``temperature_c`` or ``duty``), drawn from the row's seed.
Registered as the ``sky`` entry point of ``st16.frame_sources`` (the device
never imports ``ground``; the entry point plugs it in). Exposures render only the stars in view
with the noise from a bank drawn at start-up (``ground.sim.exposure``), so GO -> result stays
within the device's budget (docs/hil.md).
"""

from __future__ import annotations

import csv
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.time import Time

from firmware_model.camera import CameraModel
from firmware_model.pipeline.sky_bodies import ATMOSPHERE_KM, EARTH_RADIUS_KM
from firmware_model.reference_frames import quat_to_matrix
from ground.sim.detector_effects import effects_from_options
from ground.sim.exposure import ExposureRenderer
from ground.sim.orbit import CircularOrbit, utc_iso
from ground.sim.sensor_sim import DetectorModel

ORBIT_HEADER = "orbit:"  #: the comment line that gives the schedule's orbit: ``# orbit: ALT,...``
EFFECTS_HEADER = "effects:"  #: the comment line of the detector effects: ``# effects: cosmic_rate=4 ...``
POSITION_COLUMNS = ("x_km", "y_km", "z_km")


@dataclass(frozen=True)
class Exposure:
    q_icrs_to_sensor: np.ndarray
    pattern: str
    seed: int
    time_utc: str | None = None  #: the exposure's start, ISO-8601 UTC (None: not given)
    position_km: np.ndarray | None = None  #: GCRS position (km)


def check_position(r: np.ndarray) -> str | None:
    """Why a GCRS position (km) cannot be the spacecraft's, or None."""
    if not np.all(np.isfinite(r)):
        return "position holds NaN or infinite values"
    if float(np.linalg.norm(r)) <= EARTH_RADIUS_KM + ATMOSPHERE_KM:
        return f"position {np.linalg.norm(r):.0f} km from the geocentre is inside the atmosphere"
    return None


def _row_position(path: Path, k: int, row: dict) -> np.ndarray | None:
    given = [bool((row.get(c) or "").strip()) for c in POSITION_COLUMNS]
    if not any(given):
        return None
    if not all(given):
        raise ValueError(f"{path}: row {k + 1}: position needs all of {', '.join(POSITION_COLUMNS)}")
    try:
        r = np.array([float(row[c]) for c in POSITION_COLUMNS])
    except ValueError:
        raise ValueError(f"{path}: row {k + 1}: position is not numeric") from None
    why = check_position(r)
    if why:
        raise ValueError(f"{path}: row {k + 1}: {why}")
    return r


def _row_time(path: Path, k: int, row: dict) -> str | None:
    text = (row.get("time") or "").strip()
    if not text:
        return None
    try:
        return Time(text, scale="utc").isot
    except ValueError:
        raise ValueError(f"{path}: row {k + 1}: time {text!r} is not ISO-8601 UTC (YYYY-MM-DDThh:mm:ss)") from None


def _header(path: Path, name: str) -> tuple[int, str] | None:
    """The schedule's comment line ``# NAME: VALUE`` as (line number, VALUE), None without one;
    ValueError naming the line of a second one."""
    found = None
    for n, line in enumerate(path.read_text().splitlines(), 1):
        body = line.strip().lstrip("#").strip() if line.lstrip().startswith("#") else ""
        if body.lower().startswith(name):
            if found is not None:
                raise ValueError(f"{path}: line {n}: a second {name[:-1]} line")
            found = (n, body[len(name) :].strip())
    return found


def read_orbit(path) -> CircularOrbit | None:
    """The schedule's ``# orbit: ...`` line as an orbit, None without one; ValueError naming the line."""
    path = Path(path)
    found = _header(path, ORBIT_HEADER)
    if found is None:
        return None
    try:
        return CircularOrbit.parse(found[1])
    except ValueError as exc:
        raise ValueError(f"{path}: line {found[0]}: {exc}") from None


def read_effects(path, orbit: CircularOrbit | None):
    """The schedule's ``# effects: KEY=VALUE ...`` line (``detector_effects.SOURCE_OPTIONS``) as
    ``MissionEffects`` on ``orbit``, None without one; ValueError naming the line."""
    path = Path(path)
    found = _header(path, EFFECTS_HEADER)
    if found is None:
        return None
    try:
        pairs = [item.split("=", 1) for item in found[1].replace(",", " ").split()]
        if any(len(p) != 2 for p in pairs):
            raise ValueError("expected KEY=VALUE items")
        return effects_from_options({k.strip(): v.strip() for k, v in pairs}, orbit)
    except ValueError as exc:
        raise ValueError(f"{path}: line {found[0]}: {exc}") from None


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
        out.append(
            Exposure(
                q / norm,
                (row.get("pattern") or "RGGB").upper(),
                int(row.get("seed") or k),
                _row_time(path, k, row),
                _row_position(path, k, row),
            )
        )
    return out


class SkySource:
    """Capture source: render the sky at the next scheduled attitude (module docstring)."""

    def __init__(self, spec: str, camera: CameraModel):
        self.schedule = read_schedule(spec)
        self.orbit = read_orbit(spec)
        self.effects = read_effects(spec, self.orbit)
        self.renderer = ExposureRenderer(camera)
        # at start-up, not inside the first GO
        bodies = self.orbit is not None or any(e.time_utc or e.position_km is not None for e in self.schedule)
        self._drawing = self.renderer.draw_bank(
            self.renderer.effective_detector(DetectorModel(), self.effects), glare=bodies
        )
        self._next = 0
        self._lock = threading.Lock()

    def ready(self) -> None:
        """Return once the source can render at once (its noise bank drawn)."""
        self._drawing.join()

    def __call__(self, ctx, mount=None):
        with self._lock:
            exp = self.schedule[self._next % len(self.schedule)]
            self._next += 1
        det = DetectorModel(pattern=exp.pattern)
        started = getattr(ctx, "started", None)
        epoch, t_posix = None, None
        if exp.time_utc is not None:
            t_posix = float(Time(exp.time_utc, scale="utc").unix) + det.exposure_s / 2.0
        elif started is not None and (exp.position_km is not None or self.orbit is not None):
            t_posix = started + det.exposure_s / 2.0
        if t_posix is not None:
            epoch = utc_iso(t_posix)  # the mid-time: the bodies' epoch
        position = exp.position_km
        if position is None and self.orbit is not None and t_posix is not None:
            position = self.orbit.position_gcrs_km(t_posix)
        effects = self.effects
        if effects is not None and t_posix is not None:
            effects = effects.at_time(t_posix)  # the SAA under the spacecraft at the exposure
        attitude = quat_to_matrix(exp.q_icrs_to_sensor)
        if mount is not None:  # a head's body-to-sensor mounting: the source gives the body's attitude (--heads)
            attitude = mount @ attitude
        return self.renderer.render(
            attitude,
            det,
            exp.seed,
            epoch_utc=epoch,
            sc_position_km=position,
            effects=effects,
        )
