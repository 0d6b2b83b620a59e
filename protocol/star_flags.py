"""Bit flags attached to each detected star (detection and centroid/colour fit)."""

from enum import IntFlag


class StarFlag(IntFlag):
    """Zero means a clean colour fit. Any of SATURATED, EDGE, BLEND, FIT_FAILED or
    POOR_FIT means the centroid or colour should not be trusted blindly (``UNTRUSTED``)."""

    NONE = 0
    SATURATED = 1  # a window pixel reached the white level (excluded from the fit)
    EDGE = 2  # fit window clipped by the array edge
    BLEND = 4  # another significant peak lies in the same connected region
    NO_COLOUR = 8  # monochrome frame: rg, bg are NaN
    FIT_FAILED = 16  # PSF fit did not converge or left its window; centroid is centre of gravity
    POOR_FIT = 32  # reduced chi-square above the limit (PSF mismatch, blend, artefact)


UNTRUSTED = StarFlag.SATURATED | StarFlag.EDGE | StarFlag.BLEND | StarFlag.FIT_FAILED | StarFlag.POOR_FIT
