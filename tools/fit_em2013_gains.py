"""Build the shipped ``data/qe_em2013.csv``: the MT9P031-like model with the channel gains that
reproduce Enright & McVittie's catalog colour ratios (seed 000 table 4).

The paper publishes the catalog ratios of Orion's belt: delta-Ori (O9.5 II) and zeta-Ori (O9.7 Ib)
share a reference spectrum, rg 0.652 / bg 1.232; epsilon-Ori (B0 Ia) rg 0.674 / bg 1.161. Each star
takes its Pickles template by its BSC5 MK type (:func:`ground.catalog.colour.match_template`:
O9 V, O9 V, B0 I), and the red and blue responses of the MT9P031-like model (no IR-cut filter, as on
the paper's detector) are scaled by the gains ``g_r``, ``g_b`` that fit the three stars in least
squares (closed form: ``g = sum(t m) / sum(m^2)``). A gain is a per-channel QE level; the shapes,
and so the spread of ratios across spectral types, are the MT9P031-like model's. Run:

    python tools/fit_em2013_gains.py /work/shared/data/bsc5/catalog.dat /work/shared/data/pickles
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ground.atomic_write import write_text
from ground.catalog.colour import EM2013_TABLE4, ColourModel, default_qe, match_template, parse_mk
from ground.catalog.sources import read_bsc5

DATA = Path(__file__).resolve().parents[1] / "ground" / "catalog" / "data"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bsc5", type=Path)
    parser.add_argument("pickles_dir", type=Path)
    parser.add_argument("--out", type=Path, default=DATA / "qe_em2013.csv")
    args = parser.parse_args(argv)
    base = default_qe()
    model = ColourModel(qe=base, pickles_dir=args.pickles_dir)
    bsc = read_bsc5(args.bsc5)
    model_rg, model_bg, paper_rg, paper_bg, names = [], [], [], [], []
    for hr, (star, rg, bg) in EM2013_TABLE4.items():
        sptype = str(bsc.sptype[np.flatnonzero(bsc.star_id == hr)[0]])
        template = match_template(parse_mk(sptype), model.templates)
        m_rg, m_bg = model.template_ratios(template)
        model_rg.append(m_rg), model_bg.append(m_bg), paper_rg.append(rg), paper_bg.append(bg)
        names.append(f"{star} {sptype} -> {template}")
    m_rg, m_bg, t_rg, t_bg = (np.array(v) for v in (model_rg, model_bg, paper_rg, paper_bg))
    g_r, g_b = float(t_rg @ m_rg / (m_rg @ m_rg)), float(t_bg @ m_bg / (m_bg @ m_bg))
    for name, a, b, c, d in zip(names, m_rg * g_r, m_bg * g_b, t_rg, t_bg):
        print(f"{name}: rg {a:.3f} (paper {c:.3f}), bg {b:.3f} (paper {d:.3f})")
    print(f"gains g_r {g_r:.4f}, g_b {g_b:.4f}")
    lines = [
        "# Enright & McVittie (2013) effective response: the MT9P031-like model (no IR-cut filter) with red x "
        f"{g_r:.4f} and blue x {g_b:.4f},",
        "# the channel gains that fit the paper's table 4 catalog ratios (delta/epsilon/zeta Ori) in least squares.",
        "# An ASSUMED model, not a measured curve. Made by tools/fit_em2013_gains.py; see docs/catalog.md.",
        "wavelength_nm,red,green,blue",
    ]
    body = [
        f"{w:.0f},{r * g_r:.5f},{g:.5f},{b * g_b:.5f}" for w, r, g, b in zip(base.wavelength_nm, base.r, base.g, base.b)
    ]
    write_text(args.out, "\n".join(lines + body) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
