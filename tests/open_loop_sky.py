"""The open-loop tests' camera, catalog and renderer (helpers, no tests): tetra3 geometry, the
real sky to V 7, frames rendered with optics the solver may not be told about."""

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.reference_frames import attitude_from_radec_roll
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.sim.sensor_sim import DetectorModel, render_frame
from ground.sim.sky_model import sky_stars

#: The tetra3 test camera's geometry (1024 x 768, ~41 arcsec/px, 11.4 x 8.6 deg).
NOMINAL = CameraModel.from_horizontal_fov(1024, 768, 11.4)
PIXEL_RAD = 1.0 / NOMINAL.f
#: Pointings with 10-20 catalog stars in view (RA, Dec, roll in deg).
POINTINGS = [(83.8, -5.4, 20.0), (201.3, -11.2, 100.0), (296.6, 10.6, 250.0)]


def open_loop_catalog():
    """The catalog for that field: V <= 6, pairs 0.05-15 deg."""
    return build_catalog(
        CatalogDesign(
            theta_fov_deg=4.3,
            sensor_width_px=1024,
            sensor_height_px=768,
            m_thresh=6.0,
            phi_min_deg=0.05,
            phi_max_deg=15.0,
        )
    )


def render(camera, pointing, seed=1, pattern="MONO", psf_sigma=1.0, **kw):
    """(true attitude, render result) of the real sky to V 7 at ``pointing`` (RA, Dec, roll deg)."""
    a = attitude_from_radec_roll(*np.radians(pointing))
    det = DetectorModel(pattern=pattern, psf_sigma_px=psf_sigma, aperture_mm=18.0)
    return a, render_frame(sky_stars(7.0), a, camera, det, seed=seed, **kw)
