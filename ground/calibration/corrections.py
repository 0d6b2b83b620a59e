"""Field-test corrections of Enright & McVittie section 5.3: bilinear colour calibration and refraction.

* :class:`ColourCorrection` is the six-parameter bilinear map of eq. 24,
  ``[rg', bg'] = B @ [rg, bg] + c``, fitted by least squares on matched stars with iterative
  outlier rejection (bounded, and with a weak pull of ``B`` towards the identity). RMS figures are over both ratios of every star used:
  ``sqrt(mean((rg' - rg_cat)^2 + (bg' - bg_cat)^2) / 2)``.
* :func:`correct_refraction` removes atmospheric refraction from observed sensor-frame star
  vectors, given an approximate attitude (within about a degree, as in eq. 25), the site, the
  time and the weather, using astropy's AltAz frame with and without pressure, with the project's
  Earth orientation (``ground.sim.earth_orientation``: any date, no download, no global setting).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from firmware_model.pipeline.frame_identification import apply_colour_correction
from ground.atomic_write import write_text
from ground.sim import earth_orientation

PARAMETER_KIND = "colour_correction"


def _rms(pred: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(np.mean((pred - ref) ** 2))) if len(pred) else float("nan")


@dataclass
class ColourCorrection:
    """Eq. 24: ``beta = [b1, b2, b3, b4, b5, b6]``; identity by default."""

    beta: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 1.0, 0.0, 0.0]))
    rms_before: float = float("nan")
    rms_after: float = float("nan")
    n_used: int = 0
    n_rejected: int = 0

    @property
    def matrix(self) -> np.ndarray:
        return np.asarray(self.beta[:4], dtype=float).reshape(2, 2)

    @property
    def offset(self) -> np.ndarray:
        return np.asarray(self.beta[4:6], dtype=float)

    def apply(self, rg, bg):
        """Corrected (rg', bg') for observed ratios (arrays or scalars), as the device applies it."""
        return apply_colour_correction(np.asarray(rg, float), np.asarray(bg, float), self.beta)

    @classmethod
    def fit(
        cls,
        observed,
        catalog,
        clip: float = 3.0,
        max_iter: int = 10,
        min_stars: int = 4,
        min_sigma: float = 0.01,
        max_reject: float = 0.2,
        prior_weight: float = 0.01,
    ):
        """Least-squares fit of eq. 24 with iterative rejection of outliers.

        ``observed`` and ``catalog`` are (N, 2) arrays of (rg, bg). The residual scale is
        estimated robustly (``median |r| / 1.1774``, the Rayleigh median, floored at
        ``min_sigma``) and stars beyond ``clip`` scales are rejected, never more than
        ``max_reject`` of them. Star colours lie near a one-dimensional locus and a field may
        hold few distinct spectra, so the matrix is weakly pulled towards the identity
        (``prior_weight`` x N pseudo-observations): directions the data do not constrain stay
        as they are instead of collapsing.
        """
        if max_iter < 1:
            raise ValueError(f"max_iter must be at least 1, got {max_iter}")
        obs = np.asarray(observed, dtype=float)
        cat = np.asarray(catalog, dtype=float)
        if obs.shape != cat.shape or obs.ndim != 2 or obs.shape[1] != 2:
            raise ValueError(f"observed and catalog must both be (N, 2); got {obs.shape} and {cat.shape}")
        finite = np.isfinite(obs).all(axis=1) & np.isfinite(cat).all(axis=1)
        n_finite = int(finite.sum())
        if n_finite < min_stars:
            raise ValueError(f"need at least {min_stars} stars with finite colours to fit 6 parameters, got {n_finite}")
        design = np.hstack([obs, np.ones((len(obs), 1))])
        use = finite.copy()
        coef = np.zeros((3, 2))  # replaced by the first iteration's fit (max_iter >= 1)
        for _ in range(max_iter):
            w = np.sqrt(prior_weight * use.sum())
            prior_x = np.array([[w, 0.0, 0.0], [0.0, w, 0.0]])
            prior_y = np.array([[w, 0.0], [0.0, w]])
            coef, *_ = np.linalg.lstsq(np.vstack([design[use], prior_x]), np.vstack([cat[use], prior_y]), rcond=None)
            resid = np.linalg.norm(design @ coef - cat, axis=1)
            scale = max(float(np.median(resid[use])) / 1.1774, min_sigma)
            keep = finite & (resid <= clip * scale)
            if keep.sum() < max(min_stars, (1 - max_reject) * n_finite):
                worst = np.argsort(np.where(finite, resid, np.inf))  # keep the best (1 - max_reject)
                keep = np.zeros_like(finite)
                keep[worst[: int(np.ceil((1 - max_reject) * n_finite))]] = True
            if np.array_equal(keep, use):
                break
            use = keep
        beta = np.array([coef[0, 0], coef[1, 0], coef[0, 1], coef[1, 1], coef[2, 0], coef[2, 1]])
        corr = cls(beta=beta)
        rg2, bg2 = corr.apply(obs[use, 0], obs[use, 1])
        corr.rms_before = _rms(obs[use], cat[use])
        corr.rms_after = _rms(np.stack([rg2, bg2], axis=1), cat[use])
        corr.n_used = int(use.sum())
        corr.n_rejected = n_finite - corr.n_used
        return corr

    def to_json(self) -> str:
        return json.dumps(
            {
                "kind": PARAMETER_KIND,
                "beta": [float(b) for b in self.beta],
                "rms_before": self.rms_before,
                "rms_after": self.rms_after,
                "n_used": self.n_used,
                "n_rejected": self.n_rejected,
            },
            indent=2,
        )

    @classmethod
    def from_json(cls, text: str) -> ColourCorrection:
        data = json.loads(text)
        if data.get("kind") != PARAMETER_KIND:
            raise ValueError(f"not a colour correction parameter set (kind={data.get('kind')!r})")
        beta = np.asarray(data["beta"], dtype=float)
        if beta.shape != (6,) or not np.isfinite(beta).all():
            raise ValueError(f"colour correction needs 6 finite coefficients, got {data['beta']!r}")
        return cls(
            beta=beta,
            rms_before=data.get("rms_before", float("nan")),
            rms_after=data.get("rms_after", float("nan")),
            n_used=int(data.get("n_used", 0)),
            n_rejected=int(data.get("n_rejected", 0)),
        )

    def save(self, path) -> Path:
        path = Path(path)
        write_text(path, self.to_json())
        return path


@dataclass(frozen=True)
class Site:
    """Observing site and weather: degrees, metres, hPa, deg C, relative humidity 0-1, microns."""

    lat_deg: float
    lon_deg: float
    height_m: float = 0.0
    pressure_hpa: float = 1013.25
    temperature_c: float = 10.0
    relative_humidity: float = 0.5
    wavelength_um: float = 0.55

    def location(self):
        import astropy.units as u
        from astropy.coordinates import EarthLocation

        return EarthLocation(lat=self.lat_deg * u.deg, lon=self.lon_deg * u.deg, height=self.height_m * u.m)


def _altaz_frames(site: Site, time):
    import astropy.units as u
    from astropy.coordinates import AltAz

    loc = site.location()
    vacuum = AltAz(obstime=time, location=loc, pressure=0 * u.hPa)
    air = AltAz(
        obstime=time,
        location=loc,
        pressure=site.pressure_hpa * u.hPa,
        temperature=site.temperature_c * u.deg_C,
        relative_humidity=site.relative_humidity,
        obswl=site.wavelength_um * u.micron,
    )
    return vacuum, air


def refraction_angle(alt_true_rad, site: Site, time, az_rad=None):
    """Refraction (apparent minus true altitude, radians) at true altitudes, from astropy."""
    import astropy.units as u
    from astropy.coordinates import SkyCoord

    alt = np.atleast_1d(np.asarray(alt_true_rad, dtype=float))
    az = np.zeros_like(alt) if az_rad is None else np.atleast_1d(np.asarray(az_rad, dtype=float))
    with earth_orientation.tables():
        vacuum, air = _altaz_frames(site, time)
        true = SkyCoord(az=az * u.rad, alt=alt * u.rad, frame=vacuum)
        return true.transform_to(air).alt.rad - alt


def correct_refraction(vec_sensor, a_icrs_to_sensor, site: Site, time, iterations: int = 3):
    """Refraction-free sensor-frame unit vectors for observed (refracted) ones.

    ``a_icrs_to_sensor`` may be approximate (a raw solve or a manual match): the correction
    depends only on each star's altitude. ``time`` is an astropy ``Time``.
    """
    import astropy.units as u
    from astropy.coordinates import ICRS, CartesianRepresentation, SkyCoord

    v = np.atleast_2d(np.asarray(vec_sensor, dtype=float))
    a = np.asarray(a_icrs_to_sensor, dtype=float)
    v_icrs = v @ a  # rows: A^T s
    with earth_orientation.tables():
        vacuum, air = _altaz_frames(site, time)
        observed = SkyCoord(CartesianRepresentation(v_icrs.T * u.one), frame=ICRS()).transform_to(vacuum)
        alt_obs, az = observed.alt.rad, observed.az.rad
        alt_true = alt_obs.copy()
        for _ in range(iterations):
            r = SkyCoord(az=az * u.rad, alt=alt_true * u.rad, frame=vacuum).transform_to(air).alt.rad - alt_true
            alt_true = alt_obs - r
        fixed = SkyCoord(az=az * u.rad, alt=alt_true * u.rad, frame=vacuum).transform_to(ICRS())
    xyz = fixed.cartesian.xyz.value.T
    xyz /= np.linalg.norm(xyz, axis=1)[:, None]
    return xyz @ a.T


def bennett_refraction_deg(alt_apparent_deg, pressure_hpa=1010.0, temperature_c=10.0):
    """Bennett (1982) refraction in degrees for apparent altitude in degrees (reference check)."""
    h = np.asarray(alt_apparent_deg, dtype=float)
    r_arcmin = 1.0 / np.tan(np.radians(h + 7.31 / (h + 4.4)))
    return r_arcmin / 60.0 * (pressure_hpa / 1010.0) * (283.0 / (273.0 + temperature_c))
