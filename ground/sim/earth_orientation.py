"""Earth orientation from tables the project controls: the one place the ground side turns UTC into
the Earth's rotation (UT1 - UTC) and polar motion.

astropy's default, ``IERS_Auto``, compares the wall clock with the date of its bundled
predictions: once those are more than 30 days older than *today*, every time past the last
measured value fails (``interpolating from IERS_Auto using predictive values that are more than
30.0 days old``) unless the table can be downloaded. A device or replay that works today would stop
working a month after install. Here the values come only from the files of the installed
``astropy-iers-data`` package, whatever today's date:

* **IERS-B** (``eopc04.1962-now``, final values) where it covers the time;
* past it, the bundled **IERS Bulletin A** (``finals2000A.all``): its rapid values, then its
  predictions, about a year beyond the release of the package (the table's own 1-sigma
  ``e_UT1_UTC`` reaches ~0.03 s at its end);
* past that (and before 1962): **UT1 - UTC = 0 and no polar motion**. Bounded: the IERS inserts
  leap seconds to keep |UT1 - UTC| under 0.9 s, so the Earth's rotation angle is off by at most
  0.9 s x 15.04 arcsec/s = 13.5 arcsec, and |polar motion| has stayed under 0.6 arcsec. What
  that costs, measured (``tests/test_earth_orientation.py`` keeps the figures):
  :data:`SUBSATELLITE_ERROR_KM` of sub-satellite point (at the equator, where a rotation error
  moves it most) and :data:`REFRACTION_ERROR_ARCSEC` of refraction correction at 10 deg
  altitude and above.

Nothing global is changed: :func:`gcrs_to_itrs` computes with ERFA from the table directly, and
:func:`tables` gives astropy's coordinate transforms (AltAz) the table only inside its ``with``
block (astropy's ``earth_orientation_table`` and ``iers.conf.auto_download`` set back on exit;
a lock keeps two threads' blocks from interleaving). No network access, ever.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache

import erfa
import numpy as np

#: Largest |UT1 - UTC| the IERS allows (s): leap seconds keep UTC within it.
MAX_DUT1_S = 0.9
#: Largest |polar motion| per axis seen in the IERS record (arcsec, ~0.6 in 1962-2026).
MAX_POLAR_MOTION_ARCSEC = 0.6
#: Sub-satellite point error (km) past the tables, measured: UT1 - UTC off by 0.9 s and polar
#: motion by 0.6 arcsec per axis, at the equator, 550 km up (tests/test_earth_orientation.py).
SUBSATELLITE_ERROR_KM = 0.42
#: Refraction correction error (arcsec) past the tables, measured over altitudes 10-90 deg with
#: UT1 - UTC off by 0.9 s, 1013 hPa, 10 degC (tests/test_earth_orientation.py).
REFRACTION_ERROR_ARCSEC = 0.08

#: Where a value came from (:func:`eop`'s ``source``).
FROM_B, FROM_A, FROM_A_PREDICTION, OUTSIDE = "IERS-B", "IERS-A", "IERS-A prediction", "outside the tables (zero)"
_SOURCES = (FROM_B, FROM_A, FROM_A_PREDICTION, OUTSIDE)
_ARCSEC = np.pi / (180.0 * 3600.0)


@dataclass(frozen=True)
class Table:
    """The merged table: MJD (UTC days), UT1 - UTC (s), polar motion x, y (arcsec), source index
    (into :data:`_SOURCES`) per row; rows daily, MJD increasing."""

    mjd: np.ndarray
    dut1: np.ndarray
    xp: np.ndarray
    yp: np.ndarray
    source: np.ndarray

    @property
    def b_end_mjd(self) -> float:
        return float(self.mjd[self.source == 0][-1])

    @property
    def end_mjd(self) -> float:
        return float(self.mjd[-1])


@lru_cache(maxsize=1)
def table() -> Table:
    """The merged table from the installed ``astropy-iers-data`` files (read once)."""
    from astropy.utils import iers

    b = iers.IERS_B.read(iers.IERS_B_FILE)
    a = iers.IERS_A.read(iers.IERS_A_FILE)
    b_mjd = np.asarray(b["MJD"].to_value("d"), float)
    a_mjd = np.asarray(a["MJD"].to_value("d"), float)
    later = a_mjd > b_mjd[-1]
    a_flag = np.asarray(a["UT1Flag_A"])[later]
    src = np.concatenate([np.zeros(len(b_mjd), int), np.where(a_flag == "P", 2, 1)])
    return Table(
        mjd=np.concatenate([b_mjd, a_mjd[later]]),
        dut1=np.concatenate([b["UT1_UTC"].to_value("s"), a["UT1_UTC_A"].to_value("s")[later]]),
        xp=np.concatenate([b["PM_x"].to_value("arcsec"), a["PM_x_A"].to_value("arcsec")[later]]),
        yp=np.concatenate([b["PM_y"].to_value("arcsec"), a["PM_y_A"].to_value("arcsec")[later]]),
        source=src,
    )


def _interpolate(mjd_utc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(UT1 - UTC s, xp arcsec, yp arcsec, source index) at UTC MJDs: linear between the daily rows
    (a leap second's 1-s step in UT1 - UTC taken out, as astropy does), zero outside the table."""
    tab = table()
    m = np.atleast_1d(np.asarray(mjd_utc, float))
    i = np.clip(np.searchsorted(tab.mjd, m, side="right"), 1, len(tab.mjd) - 1)
    f = (m - tab.mjd[i - 1]) / (tab.mjd[i] - tab.mjd[i - 1])
    step = tab.dut1[i] - tab.dut1[i - 1]
    dut1 = tab.dut1[i - 1] + f * (step - np.round(step))
    xp = tab.xp[i - 1] + f * (tab.xp[i] - tab.xp[i - 1])
    yp = tab.yp[i - 1] + f * (tab.yp[i] - tab.yp[i - 1])
    src = tab.source[i]
    outside = (m < tab.mjd[0]) | (m > tab.mjd[-1]) | ~np.isfinite(m)
    dut1, xp, yp = (np.where(outside, 0.0, v) for v in (dut1, xp, yp))
    return dut1, xp, yp, np.where(outside, 3, src)


@dataclass(frozen=True)
class EOP:
    """Earth orientation at one time: ``dut1_s`` = UT1 - UTC (s), polar motion ``xp_arcsec``,
    ``yp_arcsec``, and the ``source`` it came from (``FROM_B``, ``FROM_A``, ...)."""

    dut1_s: float
    xp_arcsec: float
    yp_arcsec: float
    source: str


def eop(t) -> EOP:
    """Earth orientation at an astropy ``Time`` (scalar), from the project's table."""
    utc = t.utc
    dut1, xp, yp, src = _interpolate(np.asarray(utc.mjd, float))
    return EOP(float(dut1[0]), float(xp[0]), float(yp[0]), _SOURCES[int(src[0])])


def gcrs_to_itrs(position_gcrs_km, t_posix: float, dut1_offset_s: float = 0.0, pm_offset_arcsec: float = 0.0):
    """The ITRS position (km) of a GCRS one at POSIX UTC ``t_posix``: IAU 2006/2000A with the
    project's UT1 - UTC and polar motion (ERFA ``c2t06a``; no astropy state touched). The offsets
    perturb the table's values (to measure the error budget)."""
    from astropy.time import Time

    t = Time(t_posix, format="unix", scale="utc")
    e = eop(t)
    utc, tt = t.utc, t.tt
    ut1_1, ut1_2 = erfa.utcut1(utc.jd1, utc.jd2, e.dut1_s + dut1_offset_s)
    xp = (e.xp_arcsec + pm_offset_arcsec) * _ARCSEC
    yp = (e.yp_arcsec + pm_offset_arcsec) * _ARCSEC
    rc2t = erfa.c2t06a(tt.jd1, tt.jd2, ut1_1, ut1_2, xp, yp)
    return rc2t @ np.asarray(position_gcrs_km, dtype=float)


def subsatellite_point(position_gcrs_km, t_posix: float, **offsets) -> tuple[float, float, float]:
    """(geodetic latitude deg, longitude deg, height km) on WGS84 under a GCRS position (km) at
    POSIX UTC ``t_posix``."""
    itrs_m = gcrs_to_itrs(position_gcrs_km, t_posix, **offsets) * 1000.0
    lon, lat, height = erfa.gc2gd(1, itrs_m)
    return float(np.degrees(lat)), float(np.degrees(lon)), float(height) / 1000.0


def _astropy_table(dut1_offset_s: float = 0.0):
    """The table as an astropy IERS table (for ``earth_orientation_table``): the same values as
    :func:`eop` at any time, no range error, never refreshed."""
    import astropy.units as u
    from astropy.utils import iers

    class ProjectIERS(iers.IERS):
        """astropy's IERS table interface over :func:`_interpolate`."""

        def _interpolate(self, jd1, jd2, columns, source=None):
            mjd, frac = self.mjd_utc(jd1, jd2)
            scalar = np.ndim(mjd) == 0
            dut1, xp, yp, src = _interpolate(np.asarray(mjd, float) + np.asarray(frac, float))
            zero = np.zeros_like(dut1)
            values = {"UT1_UTC": dut1 + dut1_offset_s, "PM_x": xp, "PM_y": yp, "dX_2000A": zero, "dY_2000A": zero}
            out = [values[c] * (u.s if c == "UT1_UTC" else u.arcsec) for c in columns]
            if source is not None:
                # astropy's codes: 0 IERS-B, 1 IERS-A, 2 prediction; outside the table: a prediction
                out.append(np.minimum(src, 2))
            if scalar:
                out = [v[0] for v in out]
            return out if len(out) > 1 else out[0]

    tab = table()
    return ProjectIERS(
        {
            "MJD": tab.mjd * u.d,
            "UT1_UTC": tab.dut1 * u.s,
            "PM_x": tab.xp * u.arcsec,
            "PM_y": tab.yp * u.arcsec,
            "dX_2000A": np.zeros(len(tab.mjd)) * u.arcsec,
            "dY_2000A": np.zeros(len(tab.mjd)) * u.arcsec,
        }
    )


_LOCK = threading.RLock()


@contextlib.contextmanager
def tables(dut1_offset_s: float = 0.0) -> Iterator[None]:
    """Inside the block, astropy's transforms that need Earth orientation (AltAz, ITRS, ``Time.ut1``)
    use the project's table, never download, and never fail for a time past the bundled tables;
    astropy's settings are as they were after it. ``dut1_offset_s`` perturbs UT1 - UTC (to measure
    the error budget)."""
    from astropy.utils import iers

    with _LOCK, iers.conf.set_temp("auto_download", False):
        with iers.earth_orientation_table.set(_cached_astropy_table(dut1_offset_s)):
            yield


@lru_cache(maxsize=4)
def _cached_astropy_table(dut1_offset_s: float):
    return _astropy_table(dut1_offset_s)
