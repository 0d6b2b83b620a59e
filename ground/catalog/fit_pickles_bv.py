"""Build the shipped ``data/pickles_templates.csv``: B-V of each Pickles template, default-QE ratios.

Each solar-metallicity Pickles template gets the median catalog B-V of the Yale BSC5 stars whose
MK type maps to it (:func:`ground.catalog.colour.match_template`; at least ``MIN_STARS`` stars,
B-V without uncertainty flag), so the B-V lookup of :class:`ColourModel` is calibrated on the
same B-V scale it is applied to. The default-QE colour ratios let the lookup work on machines
without the spectra. Run:

    python -m ground.catalog.fit_pickles_bv /work/shared/data/bsc5/catalog.dat /work/shared/data/pickles
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ground.catalog.colour import ColourModel, default_qe, match_template, parse_mk, pickles_templates, photon_signals, \
    ratios_from_signals, read_sed
from ground.catalog.sources import read_bsc5

OUT = Path(__file__).with_name("data") / "pickles_templates.csv"
MIN_STARS = 3


def template_bv(bsc5: Path, pickles_dir: Path) -> dict[str, tuple[float, int]]:
    """Template -> (median B-V, number of stars) over BSC5 stars of that type."""
    templates = pickles_templates(pickles_dir)
    table = read_bsc5(bsc5)
    groups: dict[str, list[float]] = {}
    for sp, bv in zip(table.sptype, table.bv):
        mk = parse_mk(sp)
        name = match_template(mk, templates) if mk and np.isfinite(bv) else None
        if name:
            groups.setdefault(name, []).append(bv)
    return {n: (float(np.median(v)), len(v)) for n, v in groups.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bsc5", type=Path)
    parser.add_argument("pickles_dir", type=Path)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    bvs = template_bv(args.bsc5, args.pickles_dir)
    qe = default_qe()
    lines = [
        "# Pickles (1998) solar-metallicity templates: median Yale BSC5 B-V of the stars mapped to each",
        f"# (blank if fewer than {MIN_STARS}), and Lambda_rg/Lambda_bg for the default MT9P031-like QE.",
        "# Made by ground/catalog/fit_pickles_bv.py.",
        "template,bv,n_stars,rg_default,bg_default",
    ]
    for name in sorted(pickles_templates(args.pickles_dir)):
        bv, n = bvs.get(name, (np.nan, 0))
        rg, bg = ratios_from_signals(photon_signals(qe, *read_sed(args.pickles_dir / f"{name}.sed")))
        bv_text = f"{bv:.3f}" if n >= MIN_STARS else ""
        lines.append(f"{name},{bv_text},{n},{rg:.6f},{bg:.6f}")
    args.out.write_text("\n".join(lines) + "\n")
    model = ColourModel(qe=qe, pickles_dir=args.pickles_dir)
    print(f"wrote {args.out}; B-V lookup range {model.bv_range}, rms ln(rg) {model.bv_fit_rms[0]:.4f}, "
          f"ln(bg) {model.bv_fit_rms[1]:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
