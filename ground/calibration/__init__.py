"""Calibration from real frames: optics (camera model) and field corrections (colour, refraction)."""
