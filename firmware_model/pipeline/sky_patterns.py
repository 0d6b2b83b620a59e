"""The whole-sky pattern table: one :class:`PatternIndex` for every field of view of 5-60 deg.

A pattern's key does not depend on the focal length (``scale_free``), so one table can serve
every field if it holds, for each field, the patterns a frame of that field shows: its brightest
stars, a few degrees apart on a narrow field and tens of degrees apart on a wide one. The table
is the union of per-field pattern sets (``scale_free.field_patterns``) on a ladder of minor
half-fields :data:`HALF_FIELDS_DEG` (ratio :data:`LADDER_RATIO`, as tetra3 builds its database
for a field range), each from the stars a field of that size shows about
:data:`STARS_IN_VIEW` of (:func:`magnitude_limit`), every 4-set once. A frame's pattern finds its
catalog pattern whatever its scale; the focal length comes from the ratio of their largest edges.

The stars are the caller's, brightest first (row order is brightness order, which the search's
check uses); the ground builds them from the bundled Hipparcos (``ground.catalog.sky_database``).

Units: radians unless a name ends ``_deg``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from firmware_model.catalog.star_counts import magnitude_for_count
from firmware_model.pipeline import scale_free
from firmware_model.pipeline.pattern_index import PatternIndex

#: Ratio of successive minor half-fields of the ladder.
LADDER_RATIO = 1.3
#: The ladder: minor half-fields (deg) from a 5 deg x 3.75 deg field's to a 60 deg square one's.
HALF_FIELDS_DEG = tuple(1.8 * LADDER_RATIO**k for k in range(12))
#: Pattern stars a field of each size shows (``CatalogDesign.for_field``'s stars in view).
STARS_IN_VIEW = 15.0
#: Faintest pattern star (V): the bundled catalog's depth for the narrowest field.
FAINTEST_MAG = 7.5
#: Neighbours each pattern star's own patterns draw on (``scale_free.CATALOG_NEIGHBOURS`` for one
#: field): fewer here, the ladder's neighbouring rungs repeat much of each field's patterns.
NEIGHBOURS = 6


def magnitude_limit(half_field_deg: float) -> float:
    """The V magnitude that puts :data:`STARS_IN_VIEW` stars in a 4:3 field of this minor
    half-field (``CatalogDesign.for_field``'s star counts), clamped to V 3.5 - :data:`FAINTEST_MAG`."""
    area = (2.0 * half_field_deg) ** 2 * 4.0 / 3.0
    return min(max(magnitude_for_count(STARS_IN_VIEW, area), 3.5), FAINTEST_MAG)


def sky_pattern_index(
    vec: np.ndarray, mag: np.ndarray, progress: Callable[[int, int], None] | None = None
) -> PatternIndex:
    """The whole-sky table of the stars ``vec`` (N, 3), ``mag`` (N,) (brightest first):
    ``progress(done, total)`` after each rung of the ladder (its size and build time for the
    bundled Hipparcos: docs/identification.md, "Blind and wide")."""
    if np.any(np.diff(mag) < 0):
        raise ValueError("sky pattern stars must come brightest first")
    parts, total = [], len(HALF_FIELDS_DEG)
    for done, half in enumerate(HALF_FIELDS_DEG, 1):
        n = int(np.searchsorted(mag, magnitude_limit(half), "right"))
        if n >= 4:
            groups, _, _ = scale_free.field_patterns(vec, mag, n, math.radians(half), NEIGHBOURS)
            parts.append(groups)
        if progress is not None:
            progress(done, total)
    groups = scale_free.unique_rows(np.concatenate(parts))  # each 4-set once, whichever rungs made it
    keys, top = scale_free.pattern_keys(vec, groups)
    return PatternIndex.from_patterns(vec, groups, keys, top)
