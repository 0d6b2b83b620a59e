"""Colour model: detector QE x stellar spectrum -> colour ratios (Enright & McVittie eqs 10-11).

``Lambda_rg = S_r / S_g`` and ``Lambda_bg = S_b / S_g`` with photon-counting integrals
``S_c = int chi_c(lambda) F_lambda(lambda) lambda dlambda`` over the detector band (wavelengths in
nm). The ``lambda`` factor is a deliberate deviation from the paper: its eqs 10-11 integrate
``chi_c I(lambda) dlambda`` with no ``lambda``; a photon detector counts ``F_lambda lambda / (h c)``
photons, so the factor is kept by default and ``photon_weighting=False`` gives the paper's form
(its size on table 4: ``bench/bench_colour_models.py``, docs/catalog.md). Spectra, best first
(``ColourSource``):

1. ``PICKLES_MK``: the Pickles (1998) template nearest to the star's MK type (:func:`match_template`);
2. ``BV_LOOKUP`` / ``VI_LOOKUP``: ln(ratio) as a quartic in B-V (or V-I, which keeps growing for M
   stars where B-V saturates) fitted over the solar-metallicity Pickles dwarfs and giants, each
   template placed at the median catalog colour of the stars of its type
   (``data/pickles_templates.csv``, made by ``tools/fit_pickles_bv.py``);
3. ``BLACKBODY``: a Planck spectrum at the Ballesteros (2012) temperature of B-V, last resort
   (7-8 % rms from the MK-template ratios of bright stars, more for M stars; docs/catalog.md);
4. ``NONE``: no type and no colour index: ratios are NaN.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from enum import IntEnum
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
from scipy.constants import Boltzmann as K_BOLTZMANN
from scipy.constants import Planck as H_PLANCK
from scipy.constants import speed_of_light as C_LIGHT

VI_FROM_BV = 1.0  # B-V from which the V-I lookup is preferred (B-V saturates for M stars)
BV_BLUE_HOLD = 0.2  # mag below the B-V lookup range where the blue-end ratios are still used
BV_PHYSICAL_MIN = -0.5  # B-V below this is not a stellar colour (Ballesteros T diverges at -0.67)
SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
DEFAULT_PICKLES_DIR = SHARED_DATA / "pickles"
DEFAULT_QE_NAME = "mt9p031_like"
#: detector responses shipped as ``data/qe_<name>.csv``, each with its template ratios in
#: ``data/pickles_templates.csv`` (docs/catalog.md says what each assumes)
QE_MODELS = ("mt9p031_like", "mt9p031_like_ircut", "em2013")
#: Enright & McVittie (seed 000) table 4, catalog columns: BSC5 HR -> (star, Lambda_rg, Lambda_bg);
#: what ``em2013`` is fitted to (``tools/fit_em2013_gains.py``) and compared with (``bench/bench_colour_models.py``)
EM2013_TABLE4 = {
    1852: ("delta-Ori", 0.652, 1.232),
    1903: ("epsilon-Ori", 0.674, 1.161),
    1948: ("zeta-Ori", 0.652, 1.232),
}
#: the BSC5 MK types of the table-4 stars (O9.5 II and O9.7 Ib take one template, B0 Ia another)
EM2013_TABLE4_SPTYPE = {1852: "O9.5II", 1903: "B0Ia", 1948: "O9.7Ib"}
#: table 4 held out one template at a time: (stars the gains are fitted on, stars predicted), BSC5 HR;
#: delta and zeta share a template and the paper's ratios, so each split fits on one template
EM2013_HELD_OUT = (((1852, 1948), (1903,)), ((1903,), (1852, 1948)))


class ColourDataError(ValueError):
    """A QE table or spectrum is unusable; the message names the file, line and value."""


class ColourSource(IntEnum):
    """Where a star's colour ratios came from (stored per star in the catalog image flags)."""

    NONE = 0
    PICKLES_MK = 1
    BV_LOOKUP = 2
    BLACKBODY = 3
    VI_LOOKUP = 4


# --- detector QE -----------------------------------------------------------------------------------


@dataclass
class QETable:
    """Per-channel response chi_r, chi_g, chi_b (QE, fraction) at increasing wavelengths (nm)."""

    wavelength_nm: np.ndarray
    r: np.ndarray
    g: np.ndarray
    b: np.ndarray
    name: str = "custom"
    provenance: str = ""

    def __post_init__(self):
        w = np.asarray(self.wavelength_nm, dtype=float)
        if w.ndim != 1 or len(w) < 2:
            raise ColourDataError(f"QE table {self.name}: need at least two wavelengths")
        rgb = [np.asarray(a, dtype=float) for a in (self.r, self.g, self.b)]
        for label, arr in zip("RGB", rgb):
            if arr.shape != w.shape:
                raise ColourDataError(f"QE table {self.name}: column {label} is not a column of length {len(w)}")
        bad = first_bad_row(np.column_stack([w, *rgb]))
        if bad is not None:
            raise ColourDataError(f"QE table {self.name}: row {bad[0] + 1} ({w[bad[0]]} nm): {bad[1]}")
        self.wavelength_nm = w
        self.r, self.g, self.b = rgb

    @property
    def band(self) -> tuple[float, float]:
        return float(self.wavelength_nm[0]), float(self.wavelength_nm[-1])

    def at(self, wavelength_nm: np.ndarray) -> np.ndarray:
        """Responses at ``wavelength_nm`` (linear interpolation, 0 outside), shape (3, n)."""
        w = self.wavelength_nm
        return np.stack([np.interp(wavelength_nm, w, c, left=0.0, right=0.0) for c in (self.r, self.g, self.b)])


def load_qe_csv(path: str | Path, name: str | None = None, percent: bool | None = None) -> QETable:
    """Read ``wavelength_nm, R, G, B`` rows (``#`` comments and one header line allowed), on one
    wavelength step; a row that breaks this is named (line, column, value).

    Values above 1.5 anywhere are taken as percent (``percent=None``) and divided by 100.
    """
    path = Path(path)
    rows, lines, header_seen, comments = [], [], False, []
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ColourDataError(f"{path}: cannot read QE table ({exc})") from exc
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            comments.append(s.lstrip("# "))
            continue
        parts = [p.strip() for p in s.split(",")]
        if len(parts) != 4:
            raise ColourDataError(
                f"{path}: line {lineno}: expected 4 columns (wavelength_nm,R,G,B), got {len(parts)}: {s!r}"
            )
        missing = [c for c, p in zip(("wavelength", "R", "G", "B"), parts) if not p]
        if missing:
            raise ColourDataError(f"{path}: line {lineno}: column {missing[0]} is empty: {s!r}")
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            if rows or header_seen:
                raise ColourDataError(f"{path}: line {lineno}: not numeric: {s!r}") from None
            header_seen = True
            continue
        lines.append(lineno)
    if len(rows) < 2:
        raise ColourDataError(f"{path}: {len(rows)} QE row(s); at least two are needed")
    a = np.array(rows)
    bad = first_bad_row(a, one_step=True)
    if bad is not None:
        raise ColourDataError(f"{path}: line {lines[bad[0]]}: {bad[1]}")
    if percent is None:
        percent = bool(a[:, 1:].max() > 1.5)
    if percent:
        a[:, 1:] /= 100.0
    return QETable(a[:, 0], a[:, 1], a[:, 2], a[:, 3], name=name or path.stem, provenance="; ".join(comments))


def first_bad_row(a: np.ndarray, one_step: bool = False) -> tuple[int, str] | None:
    """(row, what) of the first row of ``a`` (wavelength_nm, R, G, B) that a QE table cannot hold:
    a value not finite, a negative response, a wavelength not positive or not increasing, and with
    ``one_step`` a wavelength step other than the table's first (1 % slack); None if every row is good."""
    bad = ~np.isfinite(a)
    if bad.any():
        k, c = np.argwhere(bad)[0]
        return int(k), f"column {'wRGB'[c]} is not finite ({a[k, c]})"
    if a[0, 0] <= 0:
        return 0, f"wavelength {a[0, 0]} nm is not positive"
    neg = np.argwhere(a[:, 1:] < 0)
    if len(neg):
        k, c = neg[0]
        return int(k), f"{'RGB'[c]} is negative ({a[k, c + 1]})"
    step = np.diff(a[:, 0])
    if (step <= 0).any():
        k = int(np.argmax(step <= 0))
        return k + 1, f"wavelength {a[k + 1, 0]} nm does not increase from {a[k, 0]} nm"
    off = np.flatnonzero(np.abs(step - step[0]) > 0.01 * step[0])
    if one_step and len(off):
        k = int(off[0])
        return k + 1, (
            f"wavelength step {step[k]:g} nm where the table's step is {step[0]:g} nm "
            "(resample every channel to one step)"
        )
    return None


def shipped_qe(name: str = DEFAULT_QE_NAME) -> QETable:
    """One of the shipped detector models ``QE_MODELS`` (see docs/catalog.md for what each assumes)."""
    if name not in QE_MODELS:
        raise ColourDataError(f"unknown QE model {name!r}; shipped models: {', '.join(QE_MODELS)}")
    with resources.as_file(resources.files("ground.catalog").joinpath(f"data/qe_{name}.csv")) as p:
        return load_qe_csv(p, name=name, percent=False)


def default_qe() -> QETable:
    """The shipped MT9P031-like colour CMOS model, no IR-cut filter (the ST-16's)."""
    return shipped_qe(DEFAULT_QE_NAME)


def load_qe(spec: str | Path | None) -> QETable:
    """A shipped model by name, a ``wavelength_nm,R,G,B`` CSV by path, or the default (None)."""
    if spec is None or spec == "":
        return default_qe()
    if str(spec) in QE_MODELS:
        return shipped_qe(str(spec))
    if not Path(spec).exists():
        raise ColourDataError(f"{spec}: neither a shipped QE model ({', '.join(QE_MODELS)}) nor a file")
    return load_qe_csv(spec)


# --- spectra ---------------------------------------------------------------------------------------


def read_sed(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A Pickles ``.sed`` file: (wavelength in nm, F_lambda), wavelengths strictly increasing."""
    path = Path(path)
    if not path.is_file():
        raise ColourDataError(f"{path}: spectrum file missing")
    try:
        a = np.loadtxt(path, comments="#", ndmin=2)
    except ValueError as exc:
        raise ColourDataError(f"{path}: malformed spectrum: {exc}") from None
    if a.shape[1] != 2 or len(a) < 2:
        raise ColourDataError(f"{path}: expected two columns (Angstrom, F_lambda), got shape {a.shape}")
    w, f = a[:, 0] / 10.0, a[:, 1]
    bad = np.flatnonzero(np.diff(w) <= 0)
    if len(bad):
        raise ColourDataError(
            f"{path}: line {bad[0] + 2}: wavelength not increasing ({a[bad[0], 0]} -> {a[bad[0] + 1, 0]} A)"
        )
    # the library holds noise-level negatives (-1e-6 of the 5556 A level): tolerated below 0.1 % of the peak
    bad = np.flatnonzero(~np.isfinite(f) | (f < -1e-3 * np.nanmax(np.abs(f))))
    if len(bad):
        raise ColourDataError(f"{path}: line {bad[0] + 1}: flux {f[bad[0]]} is negative or not finite")
    return w, f


def planck_lambda(wavelength_nm: np.ndarray, temperature: float) -> np.ndarray:
    """Blackbody spectral radiance B_lambda (W sr^-1 m^-3) at ``temperature`` kelvin."""
    lam = np.asarray(wavelength_nm, dtype=float) * 1e-9
    x = H_PLANCK * C_LIGHT / (lam * K_BOLTZMANN * temperature)
    return 2 * H_PLANCK * C_LIGHT**2 / lam**5 / np.expm1(x)


def ballesteros_temperature(bv) -> np.ndarray:
    """Effective temperature (K) from B-V, Ballesteros (2012, EPL 97, 34008)."""
    bv = np.asarray(bv, dtype=float)
    return 4600.0 * (1.0 / (0.92 * bv + 1.7) + 1.0 / (0.92 * bv + 0.62))


# --- MK types and the Pickles library -------------------------------------------------------------

_CLASSES = "OBAFGKM"
_LUM = {"Ia0": 1, "Ia": 1, "Iab": 1, "Ib": 1, "I": 1, "II": 2, "III": 3, "IV": 4, "V": 5, "VI": 5}
_PREFIX_LUM = {"c": 1, "sg": 4, "g": 3, "sd": 5, "d": 5}


@dataclass(frozen=True)
class MKType:
    """Parsed MK type: temperature index ``10 * class + subclass`` (O0 = 0 ... M10 = 70), luminosity 1-5."""

    temp_index: float
    lum: int | None  # 1 = I (supergiant) ... 5 = V (dwarf); None if not given


def parse_mk(text: str) -> MKType | None:
    """Primary component's class, subclass and luminosity from an MK string, or None.

    Handles Mount Wilson prefixes (d, sd, sg, g, c), Am notation (the hydrogen ``h`` type is used),
    ranges (``M1-M2Ia-Iab`` -> M1, I), composites (first component of ``K0III+B9V``) and the
    half-subclass ``+`` (``K0+III`` -> K0 III). S stars are treated as M;
    carbon (C, N, R), Wolf-Rayet (W) and white dwarfs (D) give None.
    """
    # "+" before a class letter joins a composite's components; before anything else (K0+III)
    # it is "a little later" within the subclass, which the template choice does not resolve
    s = re.split(r"\+(?=\s*(?:sd|sg|d|g|c)?[OBAFGKMSCNRWD])", text.strip())[0].replace("+", "").strip()
    if not s:
        return None
    prefix_lum = None
    m = re.match(r"^(sd|sg|d|g|c)(?=[OBAFGKMS])", s)
    if m:
        prefix_lum = _PREFIX_LUM[m.group(1)]
        s = s[m.end() :]
    h = re.search(r"h([OBAFGKM])(\d+(?:\.\d+)?)", s)  # Am stars: kA2hA5mA7V
    m = h or re.match(r"^([OBAFGKMS])(\d+(?:\.\d+)?)", s)
    if not m:
        return None
    cls, sub = m.group(1), float(m.group(2))
    cls_index = _CLASSES.index("M" if cls == "S" else cls)
    rest = s[m.end() :]
    lum_m = re.search(r"(Ia0|Iab|Ia|Ib|VI|IV|V|III|II|I)", rest)
    lum = _LUM[lum_m.group(1)] if lum_m else prefix_lum
    return MKType(10.0 * cls_index + sub, lum)


def parse_template_name(name: str) -> tuple[MKType, str] | None:
    """(MKType, metallicity) of a Pickles template name such as ``a47iv``, ``m2p5v``, ``rk0iii``."""
    m = re.match(r"^([rw]?)([obafgkm])(\d+|\dp\d)(i|ii|iii|iv|v)$", name)
    if not m:
        return None
    metal, cls, digits, lum = m.groups()
    if "p" in digits:
        sub = float(digits.replace("p", "."))
    elif len(digits) == 2 and digits != "10":
        sub = (int(digits[0]) + int(digits[1])) / 2.0  # a range such as a47 = A4-A7
    else:
        sub = float(digits)
    lum_index = {"i": 1, "ii": 2, "iii": 3, "iv": 4, "v": 5}[lum]
    return MKType(10.0 * _CLASSES.index(cls.upper()) + sub, lum_index), {"": "solar", "r": "rich", "w": "weak"}[metal]


def luminosity_weight(temp_index: float) -> float:
    """Cost of one luminosity class, in subclasses: small for hot stars, large for cool ones."""
    if temp_index < 30:  # O, B, A: class and subclass dominate
        return 0.4
    if temp_index < 40:  # F
        return 1.5
    return 4.0  # G, K, M: giants and dwarfs differ strongly


def match_template(mk: MKType, templates: dict[str, MKType]) -> str | None:
    """Nearest template of the star's own class letter when the library has one (O9.5 II -> O9 V,
    not B0 I: the assignment behind seed 000 table 4), by ``|d temp_index| + w * |d lum|``; ties
    go to the first name in sorted order.

    A missing luminosity class is taken as V for O-F stars; for G-M stars it is too important to
    guess, and the star falls back to the B-V lookup (None).
    """
    lum = mk.lum
    if lum is None:
        if mk.temp_index >= 40:
            return None
        lum = 5
    w = luminosity_weight(mk.temp_index)
    own_class = {n: t for n, t in templates.items() if t.temp_index // 10 == mk.temp_index // 10}
    templates = own_class or templates
    best, best_cost = None, np.inf
    for name in sorted(templates):
        t = templates[name]
        assert t.lum is not None, name  # a template name always carries a luminosity class
        cost = abs(t.temp_index - mk.temp_index) + w * abs(t.lum - lum)
        if cost < best_cost - 1e-12:
            best, best_cost = name, cost
    return best


def pickles_templates(pickles_dir: str | Path) -> dict[str, MKType]:
    """Solar-metallicity templates present in ``pickles_dir`` (name -> MKType)."""
    pickles_dir = Path(pickles_dir)
    if not pickles_dir.is_dir():
        raise ColourDataError(f"{pickles_dir}: Pickles spectra directory missing")
    out = {}
    for p in sorted(pickles_dir.glob("*.sed")):
        parsed = parse_template_name(p.stem)
        if parsed and parsed[1] == "solar":
            out[p.stem] = parsed[0]
    if not out:
        raise ColourDataError(f"{pickles_dir}: no Pickles *.sed templates found")
    return out


# --- colour integrals -------------------------------------------------------------------------------


def photon_signals(
    qe: QETable, wavelength_nm, flux, band: tuple[float, float] | None = None, photon_weighting: bool = True
) -> np.ndarray:
    """``S_c = int chi_c F_lambda lambda dlambda`` for c = r, g, b (trapezoid on the merged grid).

    ``photon_weighting=False`` drops the ``lambda`` factor: ``int chi_c F_lambda dlambda``, the
    paper's eqs 10-11 as printed (an energy integral; a photon detector counts ``F_lambda lambda``).
    ``flux`` may be (n,) or (k, n) for k spectra on one grid; returns (3,) or (k, 3).
    """
    lo, hi = band or qe.band
    w = np.asarray(wavelength_nm, dtype=float)
    if w[0] > lo or w[-1] < hi:
        raise ColourDataError(f"spectrum covers {w[0]:.1f}-{w[-1]:.1f} nm but the band is {lo:.1f}-{hi:.1f} nm")
    if lo < qe.band[0] or hi > qe.band[1]:
        raise ColourDataError(
            f"QE table {qe.name} covers {qe.band[0]:.1f}-{qe.band[1]:.1f} nm, not the band {lo:.1f}-{hi:.1f} nm"
        )
    grid = np.union1d(w[(w > lo) & (w < hi)], qe.wavelength_nm[(qe.wavelength_nm >= lo) & (qe.wavelength_nm <= hi)])
    grid = np.union1d(grid, [lo, hi])
    flux = np.asarray(flux, dtype=float)
    f = np.interp(grid, w, flux) if flux.ndim == 1 else np.stack([np.interp(grid, w, fk) for fk in flux])
    chi = qe.at(grid)  # (3, m)
    integrand = f[..., None, :] * chi * (grid if photon_weighting else 1.0)  # (..., 3, m)
    return np.trapezoid(integrand, grid, axis=-1)


def ratios_from_signals(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Lambda_rg, Lambda_bg) from signals (..., 3)."""
    s = np.asarray(s, dtype=float)
    return s[..., 0] / s[..., 1], s[..., 2] / s[..., 1]


def blackbody_ratios(
    qe: QETable, temperature, band: tuple[float, float] | None = None, photon_weighting: bool = True
) -> tuple[np.ndarray, np.ndarray] | tuple[float, float]:
    """Colour ratios of Planck spectra at ``temperature`` (K, scalar or array) on a 0.5 nm grid:
    arrays for an array of temperatures, floats for a scalar (``photon_weighting``: :func:`photon_signals`)."""
    lo, hi = band or qe.band
    grid = np.arange(lo, hi + 0.25, 0.5)
    grid[-1] = min(grid[-1], hi)
    t = np.atleast_1d(np.asarray(temperature, dtype=float))
    flux = np.stack([planck_lambda(grid, tk) for tk in t])
    rg, bg = ratios_from_signals(photon_signals(qe, grid, flux, (lo, hi), photon_weighting))
    return (rg, bg) if np.ndim(temperature) else (float(rg[0]), float(bg[0]))


# --- the full model --------------------------------------------------------------------------------


@lru_cache(maxsize=256)
def _sed_cached(path: str):
    return read_sed(path)


def _shipped_template_type(name: str) -> MKType:
    """MK type of a template named in the shipped table (every name there parses)."""
    parsed = parse_template_name(name)
    if parsed is None:
        raise ColourDataError(f"data/pickles_templates.csv: {name!r} is not a Pickles template name")
    return parsed[0]


def shipped_template_table() -> list[dict]:
    """Rows of ``data/pickles_templates.csv``: template, bv, vi, star counts, rg/bg per shipped QE model."""
    text = resources.files("ground.catalog").joinpath("data/pickles_templates.csv").read_text()
    rows = list(csv.DictReader(line for line in text.splitlines() if not line.startswith("#")))
    for r in rows:
        for k in r:
            if k != "template" and not k.startswith("n_"):
                r[k] = float(r[k]) if r[k] else np.nan
    return rows


@dataclass
class IndexLookup:
    """ln(Lambda_rg), ln(Lambda_bg) as polynomials of one colour index (B-V or V-I), with its range."""

    index: str
    coef_rg: np.ndarray
    coef_bg: np.ndarray
    lo: float
    hi: float
    rms_ln: tuple[float, float]

    @classmethod
    def fit(cls, index: str, x, rg, bg, degree: int) -> IndexLookup:
        x, lrg, lbg = np.asarray(x, float), np.log(rg), np.log(bg)
        crg = np.polynomial.polynomial.polyfit(x, lrg, degree)
        cbg = np.polynomial.polynomial.polyfit(x, lbg, degree)
        rms = (
            float(np.std(np.polynomial.polynomial.polyval(x, crg) - lrg)),
            float(np.std(np.polynomial.polynomial.polyval(x, cbg) - lbg)),
        )
        return cls(index, crg, cbg, float(x.min()), float(x.max()), rms)

    def __call__(self, x) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, dtype=float)
        return (
            np.exp(np.polynomial.polynomial.polyval(x, self.coef_rg)),
            np.exp(np.polynomial.polynomial.polyval(x, self.coef_bg)),
        )

    def covers(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        return np.isfinite(x) & (x >= self.lo) & (x <= self.hi)


def _same_qe(a: QETable, b: QETable) -> bool:
    return all(np.array_equal(x, y) for x, y in zip((a.wavelength_nm, a.r, a.g, a.b), (b.wavelength_nm, b.r, b.g, b.b)))


@dataclass
class ColourModel:
    """Colour ratios for one detector: Pickles templates by MK type, colour-index lookups, blackbody.

    Without ``pickles_dir`` on disk, only the shipped QE models can be used (their template ratios
    are shipped); any other QE needs the spectra. ``photon_weighting`` (default True, what every
    shipped ratio and catalog image uses) weights the integrals by ``lambda``; False gives the
    paper's eqs 10-11 as printed and needs the spectra (:func:`photon_signals`).
    """

    qe: QETable = field(default_factory=default_qe)
    pickles_dir: Path | None = DEFAULT_PICKLES_DIR
    band: tuple[float, float] | None = None
    lookup_degree: int = 4
    photon_weighting: bool = True

    def __post_init__(self):
        lo, hi = self.band or self.qe.band
        self.band = (lo, hi)
        if not (self.qe.band[0] <= self.band[0] < self.band[1] <= self.qe.band[1]):
            raise ColourDataError(
                f"QE table {self.qe.name} covers {self.qe.band[0]}-{self.qe.band[1]} nm, not the band {self.band}"
            )
        spectra = self.pickles_dir if self.pickles_dir is not None and Path(self.pickles_dir).is_dir() else None
        self._have_spectra = spectra is not None
        rows = shipped_template_table()
        shipped_ok = (
            f"rg_{self.qe.name}" in rows[0]
            and _same_qe(self.qe, shipped_qe(self.qe.name))
            and self.band == self.qe.band
            and self.photon_weighting
        )
        if not self._have_spectra and not shipped_ok:
            what = "" if self.photon_weighting else " without photon weighting"
            raise ColourDataError(
                f"QE table {self.qe.name}{what} needs the Pickles spectra, but {self.pickles_dir} is missing"
            )
        self._templates = (
            pickles_templates(spectra)
            if spectra is not None
            else {r["template"]: _shipped_template_type(r["template"]) for r in rows}
        )
        self._cache: dict[str, tuple[float, float]] = {}
        if not self._have_spectra:
            name = self.qe.name
            self._cache = {r["template"]: (r[f"rg_{name}"], r[f"bg_{name}"]) for r in rows}
        self.bv_lookup = self._fit_lookup(rows, "bv")
        self.vi_lookup = self._fit_lookup(rows, "vi")

    @property
    def templates(self) -> dict[str, MKType]:
        return self._templates

    def template_ratios(self, name: str) -> tuple[float, float]:
        """(Lambda_rg, Lambda_bg) of one Pickles template."""
        if name not in self._cache:
            if self.pickles_dir is None:
                raise ColourDataError(f"template {name}: its ratios are not shipped and there are no Pickles spectra")
            w, f = _sed_cached(str(Path(self.pickles_dir) / f"{name}.sed"))
            rg, bg = ratios_from_signals(photon_signals(self.qe, w, f, self.band, self.photon_weighting))
            self._cache[name] = (float(rg), float(bg))
        return self._cache[name]

    def _fit_lookup(self, rows: list[dict], index: str) -> IndexLookup:
        """Quartic ln(ratio)(index) over solar dwarfs/giants (lum III-V), excluding M7-M10 III."""
        x, rg, bg = [], [], []
        for row in rows:
            mk = self._templates.get(row["template"])
            if mk is None or mk.lum is None or not np.isfinite(row[index]) or mk.lum < 3 or mk.temp_index >= 67:
                continue
            r, b = self.template_ratios(row["template"])
            x.append(row[index])
            rg.append(r)
            bg.append(b)
        return IndexLookup.fit(index, x, rg, bg, self.lookup_degree)

    def star_ratios(self, sptype, bv, vi=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-star (rg, bg, ColourSource codes, template names) from MK strings, B-V and V-I.

        Order: Pickles template by MK type; for red stars (B-V >= ``VI_FROM_BV``, or no B-V) the
        V-I lookup, else the B-V lookup (measured against the MK-template ratios of 4 824 Hipparcos
        stars, V <= 6: B-V lookup 4.2 / 4.8 % rms in rg / bg below B-V 1.0, where V-I gives
        4.6 / 5.2 %; V-I 2.7 / 2.5 % at B-V 1.0-1.4 and 1.9 / 3.0 % above, where B-V gives
        3.1 / 3.9 % and 2.1 / 8.1 %); the other lookup if the first does not cover the star; the
        B-V lookup held at its blue end down to ``BV_BLUE_HOLD`` below its range (hot-star colours
        saturate: 1.7 / 3.2 % rms on 63 stars, where a blackbody is off by 10 / 13 %); a blackbody
        at the Ballesteros temperature; none.
        """
        n = len(bv)
        bv = np.asarray(bv, dtype=float)
        vi = np.full(n, np.nan) if vi is None else np.asarray(vi, dtype=float)
        rg, bg = np.full(n, np.nan), np.full(n, np.nan)
        src = np.full(n, ColourSource.NONE, dtype=np.uint8)
        tmpl = np.full(n, "", dtype=object)
        for k, sp in enumerate(sptype):
            mk = parse_mk(sp) if sp else None
            name = match_template(mk, self._templates) if mk else None
            if name:
                rg[k], bg[k] = self.template_ratios(name)
                src[k], tmpl[k] = ColourSource.PICKLES_MK, name

        def take(mask, code, values):
            rg[mask], bg[mask] = values
            src[mask] = code

        todo = src == ColourSource.NONE
        red = ~(bv < VI_FROM_BV)  # also True for a missing B-V
        for lookup, code, x, first in (
            (self.vi_lookup, ColourSource.VI_LOOKUP, vi, red),
            (self.bv_lookup, ColourSource.BV_LOOKUP, bv, ~red),
            (self.vi_lookup, ColourSource.VI_LOOKUP, vi, ~red),
            (self.bv_lookup, ColourSource.BV_LOOKUP, bv, red),
        ):
            m = todo & first & lookup.covers(x)
            take(m, code, lookup(x[m]))
            todo &= ~m
        m = todo & (bv < self.bv_lookup.lo) & (bv >= self.bv_lookup.lo - BV_BLUE_HOLD)
        take(m, ColourSource.BV_LOOKUP, self.bv_lookup(np.full(m.sum(), self.bv_lookup.lo)))
        todo &= ~m
        m = todo & np.isfinite(bv) & (bv > BV_PHYSICAL_MIN)  # bluer than any star: no temperature
        if m.any():
            t = ballesteros_temperature(bv[m])
            take(m, ColourSource.BLACKBODY, blackbody_ratios(self.qe, t, self.band, self.photon_weighting))
        return rg, bg, src, tmpl


# --- seed 000 table 4: the em2013 gain fit and what it can show ---------------------------------------


def table4_ratios(model: ColourModel, sptypes: dict[int, str] | None = None) -> dict[int, tuple[float, float]]:
    """(Lambda_rg, Lambda_bg) of each table-4 star (BSC5 HR) from its Pickles template by MK type."""
    out = {}
    for hr, sp in (sptypes or EM2013_TABLE4_SPTYPE).items():
        mk = parse_mk(sp)
        name = match_template(mk, model.templates) if mk else None
        if name is None:
            raise ColourDataError(f"table 4 star HR {hr}: no Pickles template for MK type {sp!r}")
        out[hr] = model.template_ratios(name)
    return out


def fit_channel_gains(model: dict[int, tuple[float, float]], stars=None) -> tuple[float, float]:
    """Red and blue gains ``g`` with ``paper ~ g * model`` over ``stars`` (table-4 HRs, default all)
    in least squares, closed form ``g = sum(t m) / sum(m^2)``: the fit behind ``em2013``
    (``tools/fit_em2013_gains.py``). Scaling chi_r by g_r scales every Lambda_rg by g_r."""
    hrs = list(stars or EM2013_TABLE4)
    m = np.array([model[hr] for hr in hrs])
    t = np.array([EM2013_TABLE4[hr][1:] for hr in hrs])
    g = (t * m).sum(axis=0) / (m * m).sum(axis=0)
    return float(g[0]), float(g[1])


@dataclass(frozen=True)
class HeldOut:
    """One table-4 split: gains fitted on ``fit_on``, residuals (model - paper) on ``predicted``."""

    fit_on: tuple[int, ...]
    gains: tuple[float, float]
    residuals: dict[int, tuple[float, float]]  # HR -> (d rg, d bg)

    @property
    def worst(self) -> float:
        return max(abs(v) for r in self.residuals.values() for v in r)


def table4_held_out(model: dict[int, tuple[float, float]]) -> list[HeldOut]:
    """Leave one template out of the table-4 gain fit (``EM2013_HELD_OUT``): what the fit predicts
    for the stars it did not see. ``model``: :func:`table4_ratios` of the base (ungained) model."""
    out = []
    for fit_on, predicted in EM2013_HELD_OUT:
        g_r, g_b = fit_channel_gains(model, fit_on)
        res = {
            hr: (g_r * model[hr][0] - EM2013_TABLE4[hr][1], g_b * model[hr][1] - EM2013_TABLE4[hr][2])
            for hr in predicted
        }
        out.append(HeldOut(tuple(fit_on), (g_r, g_b), res))
    return out
