"""Enright & McVittie fig. 7 for a detector: colour ratios of the Pickles templates against spectral type."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ground.atomic_write import save_figure
from ground.catalog.colour import ColourModel

_LUM_STYLE = {
    1: ("I", "tab:purple", "v"),
    2: ("II", "tab:brown", "<"),
    3: ("III", "tab:red", "s"),
    4: ("IV", "tab:green", ">"),
    5: ("V", "tab:blue", "o"),
}


def plot_colour_ratios(model: ColourModel, path: str | Path) -> dict[str, tuple[float, float]]:
    """Write a PNG: Lambda_rg and Lambda_bg vs type (left), Lambda_bg vs Lambda_rg (right).

    Returns the plotted template ratios (name -> (rg, bg)).
    """
    from ground.optional import pyplot

    plt = pyplot()

    names = sorted(model.templates, key=lambda n: (model.templates[n].temp_index, model.templates[n].lum))
    ratios = {n: model.template_ratios(n) for n in names}
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 5))
    for lum, (label, colour, marker) in _LUM_STYLE.items():
        sel = [n for n in names if model.templates[n].lum == lum]
        if not sel:
            continue
        t = np.array([model.templates[n].temp_index for n in sel])
        rg = np.array([ratios[n][0] for n in sel])
        bg = np.array([ratios[n][1] for n in sel])
        ax1.plot(t, rg, marker=marker, color=colour, ls="-", lw=0.8, label=f"rg, {label}")
        ax1.plot(t, bg, marker=marker, color=colour, ls="--", lw=0.8, mfc="none", label=f"bg, {label}")
        ax2.plot(rg, bg, marker=marker, color=colour, ls="-", lw=0.8, label=label)
    ax1.set_xticks(np.arange(0, 71, 10))
    ax1.set_xticklabels(["O0", "B0", "A0", "F0", "G0", "K0", "M0", "M10"])
    ax1.set_xlabel("spectral type")
    ax1.set_ylabel("colour ratio")
    ax1.set_title(f"Pickles templates, detector {model.qe.name}")
    ax1.legend(fontsize=7, ncol=2)
    ax1.grid(alpha=0.3)
    ax2.set_xlabel(r"$\Lambda_{rg}$")
    ax2.set_ylabel(r"$\Lambda_{bg}$")
    ax2.set_title("colour locus by luminosity class")
    ax2.legend(fontsize=8)
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
    return ratios
