"""Star catalogs for fields of view met off the device, one per field: built once from the bundled
Hipparcos (``CatalogDesign.for_field``, what ``st16-ground catalog build --fov-deg`` makes), kept
as catalog images in the user's cache directory and for the life of the process (every field a
script uses: none evicted). A solve matches them against the whole-sky pattern database
(``sky_database``) instead of a pattern index of their own: the solver passes that index to the
pipeline as an argument, and the kept catalog is never written to."""

from __future__ import annotations

import hashlib
import logging
import math
from pathlib import Path

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog

_log = logging.getLogger(__name__)


#: Fields of view whose catalogs are one (relative step of a logarithmic grid): the focal lengths a
#: search fits to one camera's frames differ by ~0.1 %, so they share a catalog.
CATALOG_FOV_STEP = 0.02


def catalog_for_camera(camera: CameraModel) -> OnboardCatalog:
    """The catalog for the camera's field: :func:`catalog_for_field` of its array and horizontal
    field of view on a :data:`CATALOG_FOV_STEP` grid."""
    hfov = float(np.degrees(2.0 * np.arctan(camera.width / 2.0 / camera.f)))
    step = math.log(1.0 + CATALOG_FOV_STEP)
    return catalog_for_field(camera.width, camera.height, round(math.exp(round(math.log(hfov) / step) * step), 2))


#: Modules of ``ground.catalog`` that do not build catalogs: their edits keep the kept ones.
_NOT_BUILDING = {"field_catalogs.py", "sky_database.py", "analyze.py", "colour_plot.py"}

_FIELD_CATALOGS: dict[tuple[int, int, float], OnboardCatalog] = {}


def catalog_for_field(width: int, height: int, fov_deg: float) -> OnboardCatalog:
    """The catalog ``st16-ground catalog build --fov-deg`` makes for this field (bundled Hipparcos):
    built once (a debug line says so), then loaded from the user's cache directory (the
    catalog image in ``field-catalogs/``, named by :func:`_field_key`), and kept for the process."""
    key = (width, height, fov_deg)
    if key not in _FIELD_CATALOGS:
        _FIELD_CATALOGS[key] = _field_catalog(width, height, fov_deg)
    return _FIELD_CATALOGS[key]


def _field_catalog(width: int, height: int, fov_deg: float) -> OnboardCatalog:
    from firmware_model import user_cache_dir
    from firmware_model.catalog.image_io import catalog_from_image, catalog_to_image
    from ground.atomic_write import write_bytes
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    design = CatalogDesign.for_field(width, height, fov_deg)
    folder = user_cache_dir() / "field-catalogs"
    path = folder / f"{_field_key(design)}.st16cat"
    try:
        return catalog_from_image(path.read_bytes())
    except (OSError, ValueError) as exc:  # not kept yet (or damaged): built now
        if not isinstance(exc, FileNotFoundError):
            _log.debug("field catalog %s not used: %s", path, exc)
    _log.debug("building a star catalog for a %.2f deg field of %d x %d px, kept in %s", fov_deg, width, height, folder)
    image = catalog_to_image(build_catalog(design))
    cat = catalog_from_image(image)  # as it will load from the cache: the same answers every time
    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_bytes(path, image)
    except OSError as exc:
        _log.warning("field catalog not kept in %s: %s", folder, exc)
    return cat


def _field_key(design) -> str:
    """A name for a field's cached catalog: a hash of its design, the package version and the
    code that builds the catalog and its image."""
    import protocol

    root = Path(__file__).resolve().parents[2]
    digest = hashlib.sha256(f"{protocol.__version__} {design!r}".encode())
    sources = [
        *sorted(p for p in (root / "ground" / "catalog").glob("*.py") if p.name not in _NOT_BUILDING),
        *sorted((root / "firmware_model" / "catalog").glob("*.py")),
        root / "protocol" / "catalog_image.py",
    ]  # the pattern index is kept apart, under its own hash (scale_free.cached_pattern_index)
    for source in sources:
        digest.update(source.read_bytes())
    return digest.hexdigest()[:20]
