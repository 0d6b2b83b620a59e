"""The real sky for rendering: every catalog star to a magnitude limit, with detector colours.

Unlike an on-board catalog (selection, double merging, pairs), the rendered sky keeps all
stars to ``m_limit`` so frames carry the faint stars and close doubles a real sensor sees.
Colour ratios come from the same colour model as the catalog builder (MK template, B-V / V-I
lookups, blackbody last), so the catalog's ratios are the truth of the rendering.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ground.catalog.build import colour_model, load_source
from ground.catalog.design import CatalogDesign
from ground.sim.sensor_sim import Stars

#: Default rendering depth: about a magnitude below the reference design's mono threshold.
DEFAULT_RENDER_LIMIT = 6.5


@lru_cache(maxsize=4)
def sky_stars(
    m_limit: float = DEFAULT_RENDER_LIMIT, epoch: float = 2025.0, source: str = "hipparcos", qe_path: str | None = None
) -> Stars:
    """Stars brighter than ``m_limit`` (V) at ``epoch`` with rg/bg for the detector's QE."""
    design = CatalogDesign(m_thresh=m_limit, epoch=epoch, source=source, qe_path=qe_path)
    table = load_source(design)
    if table.epoch != epoch:
        table = table.at_epoch(epoch)
    keep = np.flatnonzero(np.isfinite(table.vmag) & (table.vmag <= m_limit))
    rg, bg, _, _ = colour_model(design).star_ratios(table.sptype[keep], table.bv[keep], table.vi[keep])
    # stars without any colour information render grey-green (rg = bg = 1) rather than vanish
    rg = np.where(np.isfinite(rg), rg, 1.0)
    bg = np.where(np.isfinite(bg), bg, 1.0)
    return Stars(ids=table.star_id[keep], vectors=table.vec[keep], vmag=table.vmag[keep], rg=rg, bg=bg)
