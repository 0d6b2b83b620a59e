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
with the noise from a bank drawn at start-up, once per install (kept in the user cache, then
loaded: ``ground.sim.exposure``), so GO -> result stays within the device's budget (docs/hil.md).
"""

from __future__ import annotations

import csv
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.device.device import FrameUnavailable
from firmware_model.pipeline.raw_frame import PATTERNS, normalise_pattern
from firmware_model.pipeline.sky_bodies import ATMOSPHERE_KM, EARTH_RADIUS_KM
from firmware_model.reference_frames import quat_to_matrix
from ground.sim.detector_effects import (
    MAX_SOURCE_HITS_PER_FRAME,
    check_hits,
    effects_from_options,
    parse_option_pairs,
)
from ground.sim.exposure import ExposureRenderer, noise_cache_dir
from ground.sim.orbit import CircularOrbit, parse_utc, utc_iso
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


#: A row's ``seed``: a whole number in this range (numpy's generators take any non-negative one).
SEED_RANGE = (0, 2**32 - 1)
#: Bodies a spacecraft cannot be inside (besides the Earth and its atmosphere): those rendered.
SOLID_BODIES = ("moon", "sun")


def check_position(r: np.ndarray, epoch_utc: str | None = None) -> str | None:
    """Why a GCRS position (km) cannot be the spacecraft's, or None: not finite, inside the Earth's
    atmosphere, or (with ``epoch_utc``, ISO-8601 UTC) inside the Moon or the Sun then."""
    if not np.all(np.isfinite(r)):
        return "position holds NaN or infinite values"
    if float(np.linalg.norm(r)) <= EARTH_RADIUS_KM + ATMOSPHERE_KM:
        return f"position {np.linalg.norm(r):.0f} km from the geocentre is inside the atmosphere"
    if float(np.linalg.norm(r)) > MAX_POSITION_KM:
        return f"position {np.linalg.norm(r):.3g} km from the geocentre is beyond {MAX_POSITION_KM:g} km"
    if epoch_utc is not None:
        from firmware_model.pipeline.planets import RADIUS_KM, astrometric_positions

        for name, rel in astrometric_positions(epoch_utc, SOLID_BODIES, observer_gcrs_km=r).items():
            d = float(np.linalg.norm(rel))
            if d <= RADIUS_KM[name]:
                return f"position is inside the {name.title()} ({d:.0f} km from its centre, radius {RADIUS_KM[name]:.0f} km)"
    return None


#: The farthest a spacecraft may be from the geocentre (km): 10 times the Moon's distance, as far
#: as the rendered geometry (Earth, Moon, Sun as seen from near the Earth) is meant to hold.
MAX_POSITION_KM = 4.0e6


def _row_position(name: str, k: int, row: dict, epoch_utc: str | None) -> np.ndarray | None:
    given = [bool((row.get(c) or "").strip()) for c in POSITION_COLUMNS]
    if not any(given):
        return None
    if not all(given):
        raise ValueError(f"{name}: row {k + 1}: position needs all of {', '.join(POSITION_COLUMNS)}")
    try:
        r = np.array([float(row[c]) for c in POSITION_COLUMNS])
    except ValueError:
        raise ValueError(f"{name}: row {k + 1}: position is not numeric") from None
    why = check_position(r, epoch_utc)
    if why:
        raise ValueError(f"{name}: row {k + 1}: {why}")
    return r


def _row_time(name: str, k: int, row: dict) -> str | None:
    text = (row.get("time") or "").strip()
    if not text:
        return None
    try:
        return parse_utc(text).isot
    except ValueError as exc:
        raise ValueError(f"{name}: row {k + 1}: time {_shown(text)!r} {exc}") from None


def _row_pattern(name: str, k: int, row: dict) -> str:
    text = (row.get("pattern") or "RGGB").strip()
    try:
        return normalise_pattern(text or "RGGB")
    except ValueError:
        raise ValueError(f"{name}: row {k + 1}: pattern {_shown(text)!r} is not one of {', '.join(PATTERNS)}") from None


def _row_seed(name: str, k: int, row: dict) -> int:
    text = (row.get("seed") or "").strip()
    if not text:
        return k
    lo, hi = SEED_RANGE
    try:
        seed = int(text)
    except ValueError:
        seed = -1
    if not lo <= seed <= hi:
        raise ValueError(f"{name}: row {k + 1}: seed {_shown(text)!r} is not a whole number from {lo} to {hi}")
    return seed


def _shown(text: str) -> str:
    return text if len(text) <= 40 else f"{text[:37]}... ({len(text)} characters)"


def _header(name: str, text: str, key: str) -> tuple[int, str] | None:
    """The schedule's comment line ``# KEY: VALUE`` as (line number, VALUE), None without one;
    ValueError naming the line of a second one."""
    found = None
    for n, line in enumerate(text.splitlines(), 1):
        body = line.strip().lstrip("#").strip() if line.lstrip().startswith("#") else ""
        if body.lower().startswith(key):
            if found is not None:
                raise ValueError(f"{name}: line {n}: a second {key[:-1]} line")
            found = (n, body[len(key) :].strip())
    return found


def _read(path) -> tuple[str, str]:
    """(the name to report, the whole text) of a schedule, read once: a pipe (``<(cat ...)``) can
    be read only once."""
    name = str(path)
    try:
        return name, Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{name}: {getattr(exc, 'strerror', None) or exc}") from None


def _orbit(name: str, text: str) -> CircularOrbit | None:
    found = _header(name, text, ORBIT_HEADER)
    if found is None:
        return None
    try:
        return CircularOrbit.parse(found[1])
    except ValueError as exc:
        raise ValueError(f"{name}: line {found[0]}: {exc}") from None


def _effects(name: str, text: str, orbit: CircularOrbit | None):
    found = _header(name, text, EFFECTS_HEADER)
    if found is None:
        return None
    try:
        return effects_from_options(parse_option_pairs(found[1]), orbit)
    except ValueError as exc:
        raise ValueError(f"{name}: line {found[0]}: {exc}") from None


def _rows(name: str, text: str) -> list[Exposure]:
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    rows = list(csv.DictReader(lines))
    if not rows:
        raise ValueError(f"{name}: empty schedule")
    missing = {"qw", "qx", "qy", "qz"} - set(rows[0])
    if missing:
        raise ValueError(f"{name}: schedule lacks column(s) {sorted(missing)}")
    out = []
    for k, row in enumerate(rows):
        try:
            q = np.array([float(row[c]) for c in ("qw", "qx", "qy", "qz")])
        except (TypeError, ValueError):
            raise ValueError(f"{name}: row {k + 1}: quaternion is not numeric") from None
        norm = np.linalg.norm(q)
        if not np.isfinite(norm) or abs(norm - 1.0) > 1e-6:
            raise ValueError(f"{name}: row {k + 1}: quaternion norm {norm:.9f} is not 1")
        time_utc = _row_time(name, k, row)
        out.append(
            Exposure(
                q / norm,
                _row_pattern(name, k, row),
                _row_seed(name, k, row),
                time_utc,
                _row_position(name, k, row, time_utc),
            )
        )
    return out


@dataclass(frozen=True)
class Schedule:
    """A whole schedule file, read once: its rows, its ``# orbit:`` and its ``# effects:``."""

    rows: list[Exposure]
    orbit: CircularOrbit | None
    effects: Any

    @classmethod
    def read(cls, path) -> Schedule:
        """ValueError with one line naming the file and the row or line of the first fault."""
        name, text = _read(path)
        orbit = _orbit(name, text)
        return cls(_rows(name, text), orbit, _effects(name, text, orbit))


def read_orbit(path) -> CircularOrbit | None:
    """The schedule's ``# orbit: ...`` line as an orbit, None without one; ValueError naming the line."""
    return _orbit(*_read(path))


def read_effects(path, orbit: CircularOrbit | None):
    """The schedule's ``# effects: KEY=VALUE ...`` line (``detector_effects.SOURCE_OPTIONS``) as
    ``MissionEffects`` on ``orbit``, None without one; ValueError naming the line."""
    return _effects(*_read(path), orbit)


def read_schedule(path) -> list[Exposure]:
    """Rows of a schedule CSV, with precise errors naming the row."""
    return _rows(*_read(path))


class SkySource:
    """Capture source: render the sky at the next scheduled attitude (module docstring)."""

    def __init__(self, spec: str, camera: CameraModel):
        sched = Schedule.read(spec)  # once: a pipe cannot be read again
        self.schedule, self.orbit, self.effects = sched.rows, sched.orbit, sched.effects
        try:
            for pattern in sorted({e.pattern for e in self.schedule}):
                check_hits(self.effects, DetectorModel(pattern=pattern), camera, MAX_SOURCE_HITS_PER_FRAME)
        except ValueError as exc:
            raise ValueError(f"{spec}: {exc}") from None
        self.renderer = ExposureRenderer(camera, cache_dir=noise_cache_dir())
        # at start-up, not inside the first GO
        bodies = self.orbit is not None or any(e.time_utc or e.position_km is not None for e in self.schedule)
        self.timestamps = bodies  #: whether a frame may carry a time (the device loads its ephemerides then)
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
            from astropy.time import Time  # astropy is slow to import: only for a row with a time

            t_posix = float(Time(exp.time_utc, scale="utc").unix) + det.exposure_s / 2.0
        elif started is not None and (exp.position_km is not None or self.orbit is not None):
            t_posix = started + det.exposure_s / 2.0
        if t_posix is not None:
            epoch = utc_iso(t_posix)  # the mid-time: the bodies' epoch
        position = exp.position_km
        if position is None and self.orbit is not None and t_posix is not None:
            position = self.orbit.position_gcrs_km(t_posix)
        if position is not None and epoch is not None:
            why = check_position(position, epoch)  # the Moon moves: checked at the exposure's time
            if why:
                raise FrameUnavailable(f"sky schedule row {(self._next - 1) % len(self.schedule) + 1}: {why}")
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
