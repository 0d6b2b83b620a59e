"""Open-loop star colours for the whole-sky run: where the observed colours come from.

The closed loop observes each star with the catalog's own colour ratios plus Gaussian noise. The
open loop observes colours the catalog did not predict:

* ``source`` (:data:`TRUE_COLOUR_SOURCES`): ``catalog`` (the catalog's ``rg``/``bg``, the closed
  loop) or ``blackbody`` (a Planck spectrum at the Ballesteros T(B-V) through the catalog's QE,
  :func:`ground.sim.openloop.blackbody_colours`; the catalog's ratios kept where B-V is missing);
* per-frame channel gain errors: ``g_r / g_g`` and ``g_b / g_g`` each ``1 + gain_error`` or
  ``1 - gain_error`` (sign random per frame and channel), multiplying every ``rg`` / ``bg`` of
  the frame;
* scintillation: each star's R, G and B signals times independent log-normal factors
  ``exp(sigma N(0,1) - sigma^2 / 2)`` (mean 1), so ``rg`` is multiplied by ``f_r / f_g``
  (``sqrt(2) sigma`` rms in log).

Ratios are dimensionless; ``gain_error`` and ``scintillation`` are fractions (0.05 = 5 %).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware_model.catalog.onboard import OnboardCatalog

TRUE_COLOUR_SOURCES = ("catalog", "blackbody")
#: Largest accepted gain error and scintillation sigma (fractions): beyond them a ratio can turn
#: negative (gain) or the log-normal is no longer "a few percent" of anything physical.
MAX_GAIN_ERROR = 0.5
MAX_SCINTILLATION = 1.0


@dataclass(frozen=True)
class TrueColours:
    """Where a whole-sky run's observed colours come from and the impairments on top of them
    (before the measurement noise ``ErrorModel.sigma_colour``)."""

    source: str = "catalog"
    gain_error: float = 0.0
    scintillation: float = 0.0

    def __post_init__(self):
        if self.source not in TRUE_COLOUR_SOURCES:
            raise ValueError(f"true colour source must be one of {TRUE_COLOUR_SOURCES}, got {self.source!r}")
        if not 0.0 <= self.gain_error <= MAX_GAIN_ERROR:
            raise ValueError(f"gain error must be from 0 to {MAX_GAIN_ERROR}, got {self.gain_error}")
        if not 0.0 <= self.scintillation <= MAX_SCINTILLATION:
            raise ValueError(f"scintillation must be from 0 to {MAX_SCINTILLATION}, got {self.scintillation}")

    @property
    def impaired(self) -> bool:
        """Whether frames draw gain errors or scintillation."""
        return self.gain_error > 0 or self.scintillation > 0


def catalog_qe(catalog: OnboardCatalog):
    """The QE the catalog's colours were computed with: its design's ``qe_path`` (a shipped model's
    name or a CSV), else the default model."""
    from ground.catalog.colour import load_qe

    return load_qe(catalog.meta.get("design", {}).get("qe_path"))


def true_colour_table(catalog: OnboardCatalog, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free (rg, bg) of every catalog star under ``source``, float64, catalog order."""
    rg, bg = catalog.rg.astype(float), catalog.bg.astype(float)
    if source == "catalog":
        return rg, bg
    if source == "blackbody":
        from ground.sim.openloop import blackbody_colours

        if "bv" not in catalog.meta:
            raise ValueError("blackbody true colours need the catalog's B-V (catalog.meta['bv'])")
        return blackbody_colours(catalog.meta["bv"], rg, bg, catalog_qe(catalog))
    raise ValueError(f"unknown true colour source {source!r}")


def channel_gains(gain_error: float, rng: np.random.Generator) -> tuple[float, float]:
    """One frame's (g_r / g_g, g_b / g_g): each ``1 +- gain_error``, sign drawn at random."""
    sign = rng.choice((-1.0, 1.0), size=2)
    return 1.0 + sign[0] * gain_error, 1.0 + sign[1] * gain_error


def scintillation_factors(sigma: float, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per-star (f_r / f_g, f_b / f_g) of independent mean-1 log-normal channel factors of ``sigma``."""
    f = np.exp(sigma * rng.standard_normal((3, n)) - 0.5 * sigma**2)
    return f[0] / f[1], f[2] / f[1]


def impair(rg: np.ndarray, bg: np.ndarray, model: TrueColours, rng: np.random.Generator):
    """(rg, bg) of one frame's detections after the channel gains and scintillation of ``model``.
    Draws nothing when ``model`` has neither."""
    if not model.impaired:
        return rg, bg
    if model.gain_error > 0:
        g_rg, g_bg = channel_gains(model.gain_error, rng)
        rg, bg = rg * g_rg, bg * g_bg
    if model.scintillation > 0:
        s_rg, s_bg = scintillation_factors(model.scintillation, len(rg), rng)
        rg, bg = rg * s_rg, bg * s_bg
    return rg, bg
