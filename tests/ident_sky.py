"""Small random skies with known truth for the identification tests (helpers, no tests)."""

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.reference_frames import attitude_from_radec_roll


def random_catalog(n=1600, seed=0, phi_max_deg=15.0, phi_min_deg=0.015, colour=True):
    """Uniform random sky of ``n`` stars (about the Mv <= 5 density for n = 1600) with colours
    drawn uniformly from the range of real stars (rg 0.3-1.3, bg 0.3-1.4)."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    rg = rng.uniform(0.3, 1.3, n) if colour else None
    bg = rng.uniform(0.3, 1.4, n) if colour else None
    return OnboardCatalog.build(
        np.arange(n) + 10000,
        v,
        rng.uniform(0.0, 5.0, n),
        rg,
        bg,
        phi_min=np.radians(phi_min_deg),
        phi_max=np.radians(phi_max_deg),
    )


def random_attitude(rng):
    return attitude_from_radec_roll(rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi))


def scene(catalog, a, rng, camera=None, sigma_vec=None, sigma_colour=0.05, min_stars=0):
    """Noisy detections of the catalog stars on the reference array, brightest first:
    (vectors, rg, bg, truth catalog indices)."""
    camera = camera or CameraModel.reference_design()
    sigma_vec = 0.2 / camera.f if sigma_vec is None else sigma_vec
    s = catalog.vec @ a.T
    x, y = camera.vector_to_pixel(s)
    on = np.nonzero((s[:, 2] > 0) & (x >= -0.5) & (x < camera.width - 0.5) & (y >= -0.5) & (y < camera.height - 0.5))[0]
    on = on[np.argsort(catalog.mag[on])]
    b = s[on] + rng.normal(scale=sigma_vec, size=(len(on), 3))
    b /= np.linalg.norm(b, axis=1)[:, None]
    rg = catalog.rg[on] + rng.normal(scale=sigma_colour, size=len(on))
    bg = catalog.bg[on] + rng.normal(scale=sigma_colour, size=len(on))
    return b, rg, bg, on
