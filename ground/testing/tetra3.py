"""The ESA tetra3 test camera of ``../shared/data/frames/tetra3-mono``, as the tests and benches
set it up: its datasheet optics (no calibration) and the catalog for its field."""

from __future__ import annotations

from firmware_model.camera import CameraModel
from ground.catalog.design import CatalogDesign

#: FLIR Blackfly S, 2x2 binned IMX265 behind a 35 mm lens: 1024 x 768 px of 6.9 um, no distortion
DATASHEET_CAMERA = CameraModel.from_focal(1024, 768, 35.0, 6.9)


def catalog_design() -> CatalogDesign:
    """The catalog for the frames' field: V <= 6.5, pairs 0.05-15 deg, epoch of the frames (2019.6)."""
    return CatalogDesign(
        theta_fov_deg=4.33,
        sensor_width_px=1024,
        sensor_height_px=768,
        m_thresh=6.5,
        phi_min_deg=0.05,
        phi_max_deg=15.0,
        epoch=2019.6,
    )
