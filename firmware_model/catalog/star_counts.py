"""How many stars the sky holds to a magnitude: ``N(<V) ~ 10^(0.515 V + 0.63)`` over the whole sky,
a fit to Hipparcos within ~10 % for V 4-7. Catalog designs (``ground.catalog.design``) and the
whole-sky pattern table (``firmware_model.pipeline.sky_patterns``) size their stars with it."""

from __future__ import annotations

import math

#: Square degrees in the whole sky.
SKY_DEG2 = 41253.0


def magnitude_for_count(stars: float, area_deg2: float) -> float:
    """The V magnitude down to which a field of ``area_deg2`` holds ``stars`` stars on average."""
    return (math.log10(stars * SKY_DEG2 / area_deg2) - 0.63) / 0.515
