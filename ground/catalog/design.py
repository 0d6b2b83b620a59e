"""Catalog design parameters (Enright & McVittie sections 4-5.1), from code, the command line or TOML.

Angles are degrees at this interface (names end ``_deg``) and radians in the derived properties.
``theta_fov_deg`` is the half-angle of the field of view along the sensor's minor axis; the focal
length in pixels follows from it and the minor sensor dimension, and the pair-angle noise from
Enright & McVittie eq. 18: ``sigma_phi = 2 sigma_pix / f_px``.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

SOURCES = ("hipparcos", "bsc5")
#: Stars in view, pattern and verification-only together, of a :meth:`CatalogDesign.for_field`
#: design: six times the pattern stars, so a decided answer's attitude rests on every star the
#: frame shows down to about 1.5 mag below the pattern stars (measured: with 1 px centroid noise,
#: the roll from the ~15 pattern stars alone missed 0.1 deg on 8 % of the tetra3 inputs; with ~45
#: in view the sparse tetra3 fields matched 21-27 stars and missed it on 1 of 200, with ~90 they
#: match 42-63, as many as cedar-solve's database gives it).
VERIFY_STARS_IN_VIEW = 90.0
#: Pattern stars a :meth:`CatalogDesign.for_field` design keeps within the minor half-field of
#: every star, promoting the brightest verification-only ones where the sky is sparse.
SPARSE_PATTERN_STARS = 8


class DesignError(ValueError):
    """An impossible or unknown design parameter; the message names the parameter and value."""


@dataclass
class CatalogDesign:
    """Optical and catalog design; defaults are the Enright & McVittie baseline with M_thresh 5.0."""

    theta_fov_deg: float = 7.5
    sensor_width_px: int = 2592
    sensor_height_px: int = 1944
    m_thresh: float = 5.0
    m_verify: float | None = None  # verification-only stars m_thresh < V <= m_verify (no pairs); None: none
    min_pattern_stars: int = 0  # those of them promoted to pattern stars where fewer lie within theta_fov
    sigma_pix: float = 0.2
    sigma_rg: float = 0.02
    sigma_bg: float = 0.02
    p_correct: float = 0.99
    phi_min_deg: float | None = None  # default theta_fov / 500 (Enright & McVittie sec. 4.3)
    phi_max_deg: float | None = None  # default 2 theta_fov (Enright & McVittie eq. 13)
    n_h: int = 1024
    epoch: float = 2025.0  # Julian year of the catalog positions
    source: str = "hipparcos"
    source_path: str | None = None  # None: bundled Hipparcos / ../shared BSC5
    qe_path: str | None = None  # a shipped QE model's name (QE_MODELS) or a CSV path; None: mt9p031_like
    pickles_dir: str | None = None  # None: ../shared/data/pickles
    mk_types_path: str | None = None  # BSC5 catalog.dat lending MK types to Hipparcos stars (cross-match)
    resolve_deg: float | None = None  # double-star merge angle; default phi_min
    drop_variable: bool = False

    def __post_init__(self):
        self.validate()

    @classmethod
    def for_field(
        cls,
        width_px: int,
        height_px: int,
        fov_deg: float,
        stars_in_view: float = 15.0,
        verify_stars_in_view: float = VERIFY_STARS_IN_VIEW,
        **overrides,
    ) -> CatalogDesign:
        """A design for a camera known only by its array and horizontal field of view (deg, across
        the width): the minor half-angle from a pinhole, pairs up to the diagonal, the limiting
        magnitude that puts about ``stars_in_view`` pattern stars in the field and the one that
        puts about ``verify_stars_in_view`` stars in it with the verification-only ones (star
        counts of ``firmware_model.catalog.star_counts``; clamped to V 4-7.5 and 4-8).
        ``overrides`` are further CatalogDesign fields."""
        if not 0.0 < fov_deg < 180.0:
            raise DesignError(f"field of view must be in (0, 180) deg, got {fov_deg}")
        from firmware_model.camera import CameraModel
        from firmware_model.catalog.star_counts import magnitude_for_count

        camera = CameraModel.from_horizontal_fov(width_px, height_px, fov_deg)
        theta = math.degrees(camera.fov_half_angle_minor)
        diagonal = 2.0 * math.degrees(camera.fov_half_angle_diagonal)
        vertical = camera.fov_half_angle_minor if width_px >= height_px else camera.fov_half_angle_major
        area = fov_deg * 2.0 * math.degrees(vertical)  # deg^2, small-field

        def limit(stars: float, brightest: float, faintest: float) -> float:
            m = magnitude_for_count(stars, area)
            return math.ceil(min(max(m, brightest), faintest) * 10.0) / 10.0

        m_thresh = limit(stars_in_view, 4.0, 7.5)
        design: dict[str, Any] = {
            "theta_fov_deg": theta,
            "sensor_width_px": width_px,
            "sensor_height_px": height_px,
            "m_thresh": m_thresh,
            "m_verify": max(m_thresh, limit(verify_stars_in_view, 4.0, 8.0)),
            "min_pattern_stars": SPARSE_PATTERN_STARS,
            "phi_max_deg": diagonal,
            "phi_min_deg": theta / 100.0,
        }
        design.update(overrides)
        return cls(**design)

    # --- derived quantities (radians) ---------------------------------------------------------
    @property
    def theta_fov(self) -> float:
        return math.radians(self.theta_fov_deg)

    @property
    def phi_min(self) -> float:
        return math.radians(self.phi_min_deg) if self.phi_min_deg is not None else self.theta_fov / 500.0

    @property
    def phi_max(self) -> float:
        return math.radians(self.phi_max_deg) if self.phi_max_deg is not None else 2.0 * self.theta_fov

    @property
    def m_verify_limit(self) -> float:
        """Faintest star of the catalog: ``m_verify``, or ``m_thresh`` without verification-only stars."""
        return self.m_thresh if self.m_verify is None else max(self.m_thresh, self.m_verify)

    @property
    def resolve_angle(self) -> float:
        return math.radians(self.resolve_deg) if self.resolve_deg is not None else self.phi_min

    @property
    def focal_px(self) -> float:
        """Focal length in pixels putting the minor half-axis at ``theta_fov``."""
        return 0.5 * min(self.sensor_width_px, self.sensor_height_px) / math.tan(self.theta_fov)

    @property
    def sigma_phi(self) -> float:
        """Pair-angle noise (rad), Enright & McVittie eq. 18."""
        return 2.0 * self.sigma_pix / self.focal_px

    @property
    def delta_star(self) -> float:
        """Critical Mahalanobis distance, Enright & McVittie eq. 7 (4.65 for P_correct = 0.99)."""
        from scipy.special import erfinv  # here: the command line reads this module's defaults at start-up

        return float(-2.0 * math.sqrt(2.0) * erfinv(1.0 - 2.0 * self.p_correct))

    @property
    def dphi_star(self) -> float:
        """Angle window of the pair search, Enright & McVittie eq. 9: ``sigma_phi Delta* / 2``."""
        return self.sigma_phi * self.delta_star / 2.0

    # --- validation and I/O ------------------------------------------------------------------
    def validate(self) -> None:
        def need(ok: bool, name: str, why: str):
            if not ok:
                raise DesignError(f"{name} = {getattr(self, name)!r}: {why}")

        need(
            isinstance(self.theta_fov_deg, (int, float)) and 0 < self.theta_fov_deg < 45,
            "theta_fov_deg",
            "must be in (0, 45) degrees (half-angle)",
        )
        for name in ("sensor_width_px", "sensor_height_px"):
            need(isinstance(getattr(self, name), int) and getattr(self, name) >= 2, name, "must be an integer >= 2")
        need(math.isfinite(self.m_thresh) and -2 < self.m_thresh < 15, "m_thresh", "must be a magnitude in (-2, 15)")
        need(
            isinstance(self.min_pattern_stars, int) and 0 <= self.min_pattern_stars <= 1000,
            "min_pattern_stars",
            "must be an integer in [0, 1000]",
        )
        if self.m_verify is not None:
            need(
                isinstance(self.m_verify, (int, float)) and self.m_thresh <= self.m_verify < 15,
                "m_verify",
                f"must be a magnitude in [m_thresh = {self.m_thresh}, 15), or unset",
            )
        for name in ("sigma_pix", "sigma_rg", "sigma_bg"):
            need(math.isfinite(getattr(self, name)) and getattr(self, name) > 0, name, "must be > 0")
        need(0.5 < self.p_correct < 1, "p_correct", "must be in (0.5, 1)")
        need(isinstance(self.n_h, int) and 1 <= self.n_h <= 1 << 24, "n_h", "must be an integer in [1, 2^24]")
        need(1900 <= self.epoch <= 2200, "epoch", "must be a Julian year in [1900, 2200]")
        need(self.source in SOURCES, "source", f"must be one of {SOURCES}")
        if self.qe_path is not None:
            from ground.catalog.colour import QE_MODELS  # numpy/scipy: not at import (CLI start-up)

            need(
                self.qe_path in QE_MODELS or Path(self.qe_path).is_file(),
                "qe_path",
                f"must be a shipped QE model ({', '.join(QE_MODELS)}) or an existing CSV file",
            )
        if self.phi_min_deg is not None:
            need(self.phi_min_deg >= 0, "phi_min_deg", "must be >= 0")
        if self.phi_max_deg is not None:
            need(0 < self.phi_max_deg <= 180, "phi_max_deg", "must be in (0, 180]")
        if self.resolve_deg is not None:
            need(self.resolve_deg >= 0, "resolve_deg", "must be >= 0")
        if not self.phi_min < self.phi_max:
            raise DesignError(
                f"phi_min = {math.degrees(self.phi_min):.6g} deg must be below phi_max = {math.degrees(self.phi_max):.6g} deg "
                f"(2 theta_FOV unless set)"
            )

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict, origin: str = "design") -> CatalogDesign:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise DesignError(f"{origin}: unknown design parameter(s) {unknown}; known: {sorted(known)}")
        try:
            return cls(**data)
        except DesignError as exc:
            raise DesignError(f"{origin}: {exc}") from None
        except TypeError as exc:
            raise DesignError(f"{origin}: {exc}") from None

    @classmethod
    def from_toml(cls, path: str | Path) -> CatalogDesign:
        """Read a design file; parameters at top level or under a ``[design]`` table."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise DesignError(f"{path}: {exc}") from None
        return cls.from_dict(data.get("design", data), origin=str(path))
