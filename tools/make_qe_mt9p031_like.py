"""Build the shipped ``data/qe_mt9p031_like.csv`` (an MT9P031-like colour CMOS response model, no
IR-cut filter) and ``data/qe_mt9p031_like_ircut.csv`` (the same behind an IR-cut filter).

No public MT9P031 QE curve exists (docs/catalog.md). The model, stated here once:

* 400-700 nm: the shape of the Sony IMX219 Bayer QE curves (sensor QE x colour filter, digitised
  from the datasheet by K. Hufkens, scivision/raspicam-spectra, MIT), another small-pixel
  front-illuminated Bayer CMOS, scaled so the green peak is ``GREEN_PEAK_QE``;
* 380-400 nm: linear taper to zero;
* 700-1050 nm, no IR-cut filter (as on the ST-16): the colour dyes turn transparent, so the green
  and blue channels regain response (seed 000 fig. 2: "second pass-band ... around 800 nm") with a
  logistic rise centred at ``NIR_EDGE_NM``; every channel then follows an assumed silicon
  envelope falling to zero at 1050 nm;
* the IR-cut variant multiplies every channel by an assumed short-pass filter: transmission
  ``IRCUT_PEAK`` with a logistic edge, 50 % at ``IRCUT_NM``, 10-90 % over ``IRCUT_10_90_NM``
  (typical of the 650 nm "ICF" filters of colour machine-vision cameras).

Run: ``python tools/make_qe_mt9p031_like.py /work/shared/data/qe/IMX219.csv``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ground.atomic_write import write_text
from ground.catalog.colour import load_qe_csv

DATA = Path(__file__).resolve().parents[1] / "ground" / "catalog" / "data"
GREEN_PEAK_QE = 0.45  # assumed absolute QE at the green peak
NIR_EDGE_NM, NIR_WIDTH_NM = 800.0, 15.0  # dye transparency edge (logistic centre, scale)
#: assumed silicon envelope relative to 700 nm (front-illuminated CMOS, ~2 um pixels)
SILICON_NM = np.array([700.0, 750.0, 800.0, 850.0, 900.0, 950.0, 1000.0, 1050.0])
SILICON_REL = np.array([1.00, 0.86, 0.70, 0.54, 0.38, 0.23, 0.10, 0.0])
IRCUT_NM, IRCUT_10_90_NM, IRCUT_PEAK = 650.0, 25.0, 0.95  # assumed IR-cut filter


def ir_cut(w: np.ndarray) -> np.ndarray:
    """Transmission of the assumed IR-cut filter at wavelengths ``w`` (nm)."""
    scale = IRCUT_10_90_NM / (2.0 * np.log(9.0))  # logistic 10-90 % width = 2 ln 9 scale
    return IRCUT_PEAK / (1.0 + np.exp((w - IRCUT_NM) / scale))


def build(imx219: Path) -> np.ndarray:
    """Rows (wavelength_nm, R, G, B) on 380-1050 nm at 5 nm."""
    src = load_qe_csv(imx219)
    w = np.arange(380.0, 1050.0 + 1e-9, 5.0)
    vis = src.at(np.clip(w, 400.0, 700.0))  # (3, n): IMX219 shape, held at the ends
    vis /= vis[1].max()
    vis *= GREEN_PEAK_QE
    taper = np.clip((w - 380.0) / 20.0, 0.0, 1.0)
    silicon = np.interp(w, SILICON_NM, SILICON_REL)
    out = vis * taper
    nir = w > 700.0
    red700 = vis[0, w == 700.0][0]
    dye_open = 1.0 / (1.0 + np.exp(-(w - NIR_EDGE_NM) / NIR_WIDTH_NM))
    for c in range(3):
        c700 = vis[c, w == 700.0][0]
        level = c700 + (red700 - c700) * (dye_open - dye_open[w == 700.0][0]) / (1 - dye_open[w == 700.0][0])
        out[c, nir] = (level * silicon)[nir]
    return np.column_stack([w, out.T])


def write(path: Path, rows: np.ndarray, lines: list[str]) -> None:
    header = "".join(f"# {line}\n" for line in lines) + "wavelength_nm,red,green,blue\n"
    body = "\n".join(f"{w:.0f},{r:.5f},{g:.5f},{b:.5f}" for w, r, g, b in rows)
    write_text(path, header + body + "\n")
    print(f"wrote {path} ({len(rows)} rows)")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("imx219", type=Path, help="IMX219.csv from scivision/raspicam-spectra")
    parser.add_argument("--out-dir", type=Path, default=DATA)
    args = parser.parse_args(argv)
    rows = build(args.imx219)
    common = [
        f"400-700 nm: IMX219 Bayer QE shape (K. Hufkens, scivision/raspicam-spectra, MIT), green peak scaled to {GREEN_PEAK_QE}.",
        f">700 nm: dyes open at {NIR_EDGE_NM:.0f} nm; assumed silicon envelope to 0 at 1050 nm.",
    ]
    write(
        args.out_dir / "qe_mt9p031_like.csv",
        rows,
        [
            "MT9P031-like colour CMOS QE model (fraction, not percent), NO IR-cut filter; an ASSUMED model, not a measured curve.",
            *common,
            "Made by tools/make_qe_mt9p031_like.py; see docs/catalog.md.",
        ],
    )
    cut = rows.copy()
    cut[:, 1:] *= ir_cut(rows[:, 0])[:, None]
    write(
        args.out_dir / "qe_mt9p031_like_ircut.csv",
        cut,
        [
            "MT9P031-like colour CMOS QE model (fraction) behind an ASSUMED IR-cut filter; not a measured curve.",
            *common,
            f"IR-cut: transmission {IRCUT_PEAK}, 50 % at {IRCUT_NM:.0f} nm, 10-90 % over {IRCUT_10_90_NM:.0f} nm (logistic).",
            "Made by tools/make_qe_mt9p031_like.py; see docs/catalog.md.",
        ],
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
