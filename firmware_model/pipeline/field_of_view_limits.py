"""The horizontal fields of view (deg) a field-of-view range or hint may name: the whole-sky
search (``sky_search``) covers them, and a field catalog's half-angle on the short side of a
landscape frame stays under 45 deg. Numbers alone, importable without numpy: the ground's
``--fov-deg`` and ``--fov-range`` state and check the same range.
"""

#: Horizontal fields of view (deg) a range or hint may name.
FOV_LIMITS_DEG = (1.0, 90.0)
