"""Detector effects over a mission: radiation hits, hot pixels that grow with dose, dark current
with temperature (docs/pipeline.md, "Detector effects over a mission", has the defaults, their
sources and the assumptions).

* :class:`CosmicRays`: hits per frame drawn Poisson with mean ``flux x area x exposure`` (flux in
  particles cm^-2 s^-1, area the array's, ``width x height x pixel_pitch_um^2``) or a fixed mean
  ``hits_per_frame``; inside a coarse :class:`SouthAtlanticAnomaly` of the sub-satellite point the
  flux rises to the anomaly's. Each hit is a track: isotropic incidence (crossings of a plane, so
  ``cos(theta)`` has density ``2 cos(theta)``) through a sensitive depth ``depth_um``, projected
  length ``depth tan(theta) / pitch`` (px), charge ``e_per_um x path`` times a Landau fluctuation,
  shared along the track and diffused to neighbours (``sensor_sim.FalseObject`` with
  ``diffusion_px``).
* :func:`hot_pixel_fraction`, :func:`dose_hot_pixels`: hot pixels added linearly with total dose
  (krad), nested (a pixel hot at 1 krad stays hot at 2 krad): pixel ``i`` turns hot once the
  fraction passes its own threshold ``u_i ~ U(0, 1)``, drawn from the sensor seed.
* :func:`dark_e_per_s`: dark current doubling every :data:`DARK_DOUBLING_C` from the
  DetectorModel's value at :data:`REFERENCE_C`; :func:`detector_temperature_c`: the detector's
  temperature from the housekeeping model's DETECTOR thermal node at a duty cycle.
* :class:`MissionEffects`: all of them for one frame, ``render_inputs(attitude, camera, detector,
  rng) -> RenderInputs`` (what ``sensor_sim.render_frame`` takes).

Units: e- over the exposure unless a name says ``_per_s``; px; um; degC; krad(Si); POSIX UTC s.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from firmware_model.device.housekeeping import AMBIENT_C, DETECTOR, ThermalNode
from ground.sim.orbit import CircularOrbit
from ground.sim.sensor_sim import DetectorModel, FalseObject

#: Most probable ionisation charge of a minimum-ionising particle in silicon (e- per um of path):
#: ~80 e-h pairs/um (G. Hall, NIM 220 (1984) 356, thin-silicon energy loss; PDG "Passage of
#: particles through matter": 3.88 MeV/cm mean over 3.6 eV per pair is 108 e-/um, the most
#: probable about three quarters of it).
MIP_E_PER_UM = 80.0
#: Sensitive (charge-collecting) depth of the pixel, um: assumption (front-side CMOS epitaxial
#: layers are a few um; no public MT9P031 figure).
SENSITIVE_DEPTH_UM = 5.0
#: Landau spread of the charge: full width at half maximum as a fraction of the most probable
#: value; assumption (thin silicon's distribution is wider than 300 um's, Hall 1984).
CHARGE_FWHM_FRACTION = 0.5
#: The charge of one track is capped at this many times its most probable value (the Landau tail
#: has no mean; the full well clips any pixel long before): 1.5 % of tracks reach it, and the mean
#: charge is 1.62 times the most probable (130 e-/um, above the 108 e-/um mean: conservative).
CHARGE_CAP = 10.0
#: Lateral charge diffusion, Gaussian sigma (px): assumption for a 2.2 um pixel.
DIFFUSION_PX = 0.5
#: Mode and FWHM of scipy's standard Landau density (computed from ``scipy.stats.landau``; a test
#: keeps them equal).
LANDAU_MODE, LANDAU_FWHM = -0.42931, 2.5583
#: Dark current doubles every this many degC: Theuwissen (harvestimaging.com, 2009): "the dark
#: current can double for every 5 C ... 8 C"; the middle of that range.
DARK_DOUBLING_C = 6.5
#: Temperature (degC) at which ``DetectorModel.dark_e_per_s`` holds: the housekeeping model's idle
#: detector temperature (ambient plus the DETECTOR node's idle rise). Assumption: the default's
#: 25 e-/s is read as the value at this temperature.
REFERENCE_C = AMBIENT_C + DETECTOR.idle_rise_c
#: Range (degC) of detector temperatures the doubling law is used over: assumption (industrial
#: -40 to 85 degC; the law is an empirical fit, not a model of freeze-out or of the hottest parts).
TEMPERATURE_RANGE_C = (-40.0, 85.0)
#: Radiation-induced hot pixels per krad(Si) of total dose, as a fraction of the array: assumption
#: (linear; each krad adds half the DetectorModel's fixed 2e-5).
HOT_FRACTION_PER_KRAD = 1e-5


@dataclass(frozen=True)
class SouthAtlanticAnomaly:
    """A coarse South Atlantic Anomaly: an ellipse in geodetic latitude/longitude (deg) of the
    sub-satellite point, inside which the particle flux is at least ``flux_cm2_s``. Coarse on
    purpose: the real anomaly's flux falls off smoothly, grows with altitude and drifts west.

    Defaults (assumption, stated): centre 25 S 45 W (the field minimum lies off Brazil; the SAA
    covers about 2800 x 2800 km at the ground, tupi.if.uff.br/saa_region.htm, wider in longitude at
    LEO altitudes, Campana et al. 2014, BeppoSAX at 500-600 km); half-axes 15 deg of latitude and
    35 deg of longitude; 1000 protons cm^-2 s^-1, the order of the >10 MeV trapped-proton peak at
    ~500 km in AP-8 maps (Ginet et al. 2007, "Energetic proton maps for the SAA"; not re-derived)."""

    centre_lat_deg: float = -25.0
    centre_lon_deg: float = -45.0
    half_lat_deg: float = 15.0
    half_lon_deg: float = 35.0
    flux_cm2_s: float = 1000.0

    def contains(self, lat_deg: float, lon_deg: float) -> bool:
        """Whether the point (geodetic deg) lies inside the ellipse (longitude wrapped)."""
        dlon = (lon_deg - self.centre_lon_deg + 180.0) % 360.0 - 180.0
        return ((lat_deg - self.centre_lat_deg) / self.half_lat_deg) ** 2 + (dlon / self.half_lon_deg) ** 2 <= 1.0

    def flux_at(self, lat_deg: float, lon_deg: float, base_cm2_s: float) -> float:
        """Particle flux (cm^-2 s^-1) at the sub-satellite point: ``base_cm2_s`` outside, raised to
        the anomaly's inside."""
        return max(base_cm2_s, self.flux_cm2_s) if self.contains(lat_deg, lon_deg) else base_cm2_s


def subsatellite_point(position_gcrs_km, t_posix: float) -> tuple[float, float, float]:
    """(geodetic latitude deg, longitude deg, height km) under a GCRS position (km) at POSIX UTC
    ``t_posix``: GCRS -> ITRS -> WGS84 with the project's Earth orientation
    (``ground.sim.earth_orientation``: any date, no download, no wall clock)."""
    from ground.sim import earth_orientation

    return earth_orientation.subsatellite_point(position_gcrs_km, t_posix)


def sensitive_area_cm2(detector: DetectorModel, camera) -> float:
    """Area of the pixel array (cm^2): ``width x height`` px of ``detector.pixel_pitch_um``."""
    pitch_cm = detector.pixel_pitch_um * 1e-4
    return camera.width * pitch_cm * camera.height * pitch_cm


@dataclass(frozen=True)
class CosmicRays:
    """Radiation hits: ``flux_cm2_s`` (particles cm^-2 s^-1) or a fixed mean ``hits_per_frame``
    (which wins when given); ``saa`` raises the flux inside the anomaly. Track model parameters as
    the module constants (um, e-/um, px)."""

    flux_cm2_s: float = 0.0
    hits_per_frame: float | None = None
    saa: SouthAtlanticAnomaly | None = None
    depth_um: float = SENSITIVE_DEPTH_UM
    e_per_um: float = MIP_E_PER_UM
    charge_fwhm_fraction: float = CHARGE_FWHM_FRACTION
    diffusion_px: float = DIFFUSION_PX

    def __post_init__(self):
        if not self.flux_cm2_s >= 0:  # NaN too
            raise ValueError(f"a cosmic-ray flux must be at least 0 per cm^2 per s, got {self.flux_cm2_s}")
        if not self.flux_cm2_s <= MAX_COSMIC_RATE:
            raise ValueError(
                f"a cosmic-ray flux must be at most {MAX_COSMIC_RATE:g} per cm^2 per s, got {self.flux_cm2_s}"
            )
        if self.hits_per_frame is not None and not 0 <= self.hits_per_frame <= MAX_HITS_PER_FRAME:
            raise ValueError(f"hits per frame must be from 0 to {MAX_HITS_PER_FRAME:g}, got {self.hits_per_frame}")
        if not (self.depth_um > 0 and self.e_per_um > 0 and self.charge_fwhm_fraction >= 0 and self.diffusion_px >= 0):
            raise ValueError("a track needs depth > 0, charge per um > 0, spread >= 0 and diffusion >= 0")

    def mean_hits(self, detector: DetectorModel, camera, where: tuple[float, float] | None = None) -> float:
        """Expected hits in one exposure; ``where`` = sub-satellite (lat, lon) deg for the SAA."""
        area_s = sensitive_area_cm2(detector, camera) * detector.exposure_s
        mean = self.flux_cm2_s * area_s if self.hits_per_frame is None else self.hits_per_frame
        if self.saa is not None and where is not None and self.saa.contains(*where):
            mean = max(mean, self.saa.flux_cm2_s * area_s)
        return float(mean)

    def tracks(
        self, detector: DetectorModel, camera, rng: np.random.Generator, where: tuple[float, float] | None = None
    ) -> tuple[list[FalseObject], list[dict]]:
        """The hits of one exposure: (false objects for ``render_frame``, truth rows)."""
        from scipy.stats import landau  # scipy.stats is slow to import: only when hits are drawn

        n = int(rng.poisson(self.mean_hits(detector, camera, where)))
        w, h = camera.width, camera.height
        x, y = rng.uniform(-0.5, w - 0.5, n), rng.uniform(-0.5, h - 0.5, n)
        cos_t = np.sqrt(1.0 - rng.random(n))  # in (0, 1]: density 2 cos(theta) of plane crossings
        phi = rng.uniform(0.0, 2.0 * np.pi, n)
        lam = landau.rvs(size=n, random_state=rng)
        path_um = self.depth_um / cos_t
        length_px = self.depth_um * np.sqrt(1.0 - cos_t**2) / cos_t / detector.pixel_pitch_um
        kept = np.minimum(length_px, np.hypot(w, h)) / np.maximum(length_px, 1e-12)  # beyond the array: lost
        spread = 1.0 + self.charge_fwhm_fraction * (lam - LANDAU_MODE) / LANDAU_FWHM
        charge = self.e_per_um * path_um * np.clip(spread, 0.0, CHARGE_CAP) * np.where(length_px > 0, kept, 1.0)
        length_px = np.minimum(length_px, np.hypot(w, h))
        x2, y2 = x + length_px * np.cos(phi), y + length_px * np.sin(phi)
        objs, rows = [], []
        for i in range(n):
            objs.append(
                FalseObject(
                    "cosmic",
                    float(x[i]),
                    float(y[i]),
                    float(charge[i]),
                    x2=float(x2[i]),
                    y2=float(y2[i]),
                    diffusion_px=self.diffusion_px,
                )
            )
            rows.append(
                {
                    "x": float(x[i]),
                    "y": float(y[i]),
                    "x2": float(x2[i]),
                    "y2": float(y2[i]),
                    "electrons": float(charge[i]),
                    "path_um": float(path_um[i]),
                    "incidence_deg": float(np.degrees(np.arccos(cos_t[i]))),
                }
            )
        return objs, rows


def hot_pixel_fraction(dose_krad: float, per_krad: float = HOT_FRACTION_PER_KRAD) -> float:
    """Fraction of the array made hot by a total dose (krad(Si)): linear, capped at 1."""
    if not dose_krad >= 0:
        raise ValueError(f"a dose must be at least 0 krad, got {dose_krad}")
    return min(per_krad * dose_krad, 1.0)


_THRESHOLDS: dict = {}  #: last sensor's per-pixel hot thresholds, keyed by (seed, shape)


def dose_hot_pixels(detector: DetectorModel, shape: tuple[int, int], dose_krad: float) -> np.ndarray:
    """Flat indices of the pixels hot at ``dose_krad`` beyond the DetectorModel's fixed ones:
    pixel ``i`` is hot once :func:`hot_pixel_fraction` exceeds its threshold ``u_i ~ U(0, 1)``
    drawn from ``detector.sensor_seed`` (its own stream), so the set only grows with dose."""
    from ground.sim.sensor_sim import fixed_pattern

    key = (detector.sensor_seed, tuple(shape))
    if key not in _THRESHOLDS:
        _THRESHOLDS.clear()  # one sensor at a time: 20 MB for a full frame
        _THRESHOLDS[key] = np.random.default_rng([detector.sensor_seed, 0xD05E]).random(shape, dtype=np.float32)
    hot = np.flatnonzero(_THRESHOLDS[key].ravel() < hot_pixel_fraction(dose_krad))
    return np.setdiff1d(hot, fixed_pattern(detector, shape)[2], assume_unique=True)


def dark_e_per_s(temperature_c: float, at_reference_e_per_s: float = DetectorModel().dark_e_per_s) -> float:
    """Dark current (e-/s per pixel) at ``temperature_c``: doubling every :data:`DARK_DOUBLING_C`
    from ``at_reference_e_per_s`` at :data:`REFERENCE_C`."""
    return float(at_reference_e_per_s * 2.0 ** ((temperature_c - REFERENCE_C) / DARK_DOUBLING_C))


def detector_temperature_c(duty: float, elapsed_s: float | None = None) -> float:
    """Detector temperature (degC) from the housekeeping model's DETECTOR node when sequences run a
    fraction ``duty`` (0-1) of the time: the mean of the periodic steady state (``elapsed_s``
    None), or the mean after ``elapsed_s`` from idle. The node is linear and first-order, so its
    mean follows the mean drive: the node's busy rise times the duty cycle."""
    if not 0.0 <= duty <= 1.0:
        raise ValueError(f"a duty cycle must be from 0 to 1, got {duty}")
    rise = DETECTOR.idle_rise_c + duty * (DETECTOR.busy_rise_c - DETECTOR.idle_rise_c)
    mean_node = ThermalNode(DETECTOR.idle_rise_c, rise, DETECTOR.tau_s)
    return mean_node.step(AMBIENT_C + DETECTOR.idle_rise_c, True, math.inf if elapsed_s is None else elapsed_s)


@dataclass
class RenderInputs:
    """What ``render_frame`` takes from the effects of one frame: the detector to render with,
    false objects (tracks), extra e- per pixel over the exposure (or None), the effects' truth,
    the frame's ISO-8601 UTC timestamp (or None) and metadata for the Frame."""

    detector: DetectorModel
    false_objects: list[FalseObject]
    extra_e: np.ndarray | None
    truth: dict
    timestamp: str | None = None
    metadata: dict = field(default_factory=dict)


@dataclass(frozen=True)
class MissionEffects:
    """A mission's detector effects for one frame: ``cosmic`` hits, total ``dose_krad``, and the
    detector at ``temperature_c`` or at the housekeeping temperature of a ``duty`` cycle (neither:
    the DetectorModel as given). With ``orbit`` and ``t_posix`` the frame carries its time and the
    SAA sees the sub-satellite point; the spacecraft's GCRS position goes to the truth only, not to
    the Frame's metadata (``sc_position_km`` there makes the pipeline exclude the Earth, which these
    effects do not render: the glare effect's job)."""

    cosmic: CosmicRays | None = None
    dose_krad: float = 0.0
    temperature_c: float | None = None
    duty: float | None = None
    orbit: CircularOrbit | None = None
    t_posix: float | None = None  #: the exposure's mid-time (POSIX UTC s)

    def __post_init__(self):
        hot_pixel_fraction(self.dose_krad)  # refuses a negative dose
        if not self.dose_krad <= MAX_DOSE_KRAD:
            raise ValueError(f"a dose must be at most {MAX_DOSE_KRAD:g} krad, got {self.dose_krad}")
        lo, hi = TEMPERATURE_RANGE_C
        if self.temperature_c is not None and not lo <= self.temperature_c <= hi:
            raise ValueError(f"a detector temperature must be from {lo:g} to {hi:g} degC, got {self.temperature_c}")
        if self.temperature_c is not None and self.duty is not None:
            raise ValueError("give a detector temperature or a duty cycle, not both")
        if self.duty is not None:
            detector_temperature_c(self.duty)  # refuses a duty outside 0-1

    def at_time(self, t_posix: float) -> MissionEffects:
        """The same effects at POSIX UTC ``t_posix`` (a run gives each frame its time)."""
        return dataclasses.replace(self, t_posix=float(t_posix))

    def temperature(self) -> float | None:
        """The detector temperature (degC) these effects render at, or None (as the DetectorModel)."""
        return detector_temperature_c(self.duty) if self.duty is not None else self.temperature_c

    def detector_for(self, detector: DetectorModel) -> DetectorModel:
        """``detector`` with its dark current (and its hot pixels' rate) at :meth:`temperature`."""
        temp = self.temperature()
        if temp is None:
            return detector
        scale = dark_e_per_s(temp, 1.0)  # the factor from the reference temperature
        return dataclasses.replace(
            detector, dark_e_per_s=detector.dark_e_per_s * scale, hot_pixel_e_per_s=detector.hot_pixel_e_per_s * scale
        )

    def render_inputs(self, attitude, camera, detector: DetectorModel, rng: np.random.Generator) -> RenderInputs:
        """Inputs of ``render_frame`` for one exposure (``attitude`` unused: these effects do not
        depend on where the sensor points); hits drawn from ``rng``."""
        det = self.detector_for(detector)
        truth: dict = {"temperature_c": self.temperature(), "dark_e_per_s": det.dark_e_per_s}
        timestamp, where = None, None
        if self.orbit is not None and self.t_posix is not None:
            from astropy.time import Time

            pos = self.orbit.position_gcrs_km(self.t_posix)
            lat, lon, _ = subsatellite_point(pos, self.t_posix)
            where = (lat, lon)
            # ``t_posix`` is the exposure's mid-time; the frame's timestamp its start (docs/CONVENTIONS.md)
            timestamp = Time(self.t_posix - det.exposure_s / 2.0, format="unix", scale="utc").isot + "Z"
            truth["sc_position_km"] = [float(v) for v in pos]
            truth["subsatellite_deg"] = [lat, lon]
        objs: list[FalseObject] = []
        if self.cosmic is not None:
            mean = self.cosmic.mean_hits(det, camera, where)
            objs, rows = self.cosmic.tracks(det, camera, rng, where)
            in_saa = where is not None and self.cosmic.saa is not None and self.cosmic.saa.contains(*where)
            truth["cosmic"] = {"mean_hits": mean, "in_saa": in_saa, "tracks": rows}
        extra = None
        if self.dose_krad > 0:
            shape = (camera.height, camera.width)
            hot = dose_hot_pixels(det, shape, self.dose_krad)
            extra = np.zeros(shape)
            extra.ravel()[hot] = det.hot_pixel_e_per_s * det.exposure_s
            truth["dose"] = {"dose_krad": self.dose_krad, "new_hot_pixels": int(len(hot))}
        return RenderInputs(det, objs, extra, truth, timestamp)


#: The largest cosmic-ray flux an effect option or ``--cosmic-rate`` takes (particles per cm^2 per s):
#: 1000 times the coarse anomaly's peak (``SouthAtlanticAnomaly.flux_cm2_s``); equal to
#: ``ground.arg_types.FLUX_PER_CM2_S``'s (a test keeps them equal).
MAX_COSMIC_RATE = 1e6
#: The largest total dose (krad(Si)): a tenth of the array hot (:data:`HOT_FRACTION_PER_KRAD`);
#: equal to ``ground.arg_types.DOSE_KRAD``'s.
MAX_DOSE_KRAD = 1e4
#: The most radiation hits (mean per frame, from ``hits_per_frame`` or from the flux over the
#: exposure and the array, the anomaly's included) a device source renders: each track costs
#: ~0.6 ms of render (measured on the 2-core machine: 10 000 hits 6.6 s), so a GO stays within
#: ~3 s; 200 times the 24 hits of the anomaly's flux on the reference array in 0.1 s.
MAX_SOURCE_HITS_PER_FRAME = 5000.0
#: The most hits per frame ``sim availability`` renders (its ``--hits-per-frame`` ceiling,
#: ``ground.arg_types.HITS_PER_FRAME``): a batch run, ~60 s a frame at the ceiling.
MAX_HITS_PER_FRAME = 1e5

_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def _flag(text: str) -> bool:
    if text.lower() in _TRUE:
        return True
    if text.lower() in _FALSE:
        return False
    raise ValueError(f"is not one of {'/'.join(_TRUE)} or {'/'.join(_FALSE)}")


#: The device sources' effect options (``--attitude-feed URL?cosmic_rate=4&saa=1``, a schedule's
#: ``# effects: cosmic_rate=4 dose_krad=10``): name -> (converter, meaning, (smallest, largest)
#: value or None for a flag). Checked at start-up: every value finite and in its range, each key
#: once, and the mean hits per frame at most :data:`MAX_SOURCE_HITS_PER_FRAME`
#: (:func:`check_source_effects`).
SOURCE_OPTIONS: dict[str, tuple[Callable[[str], Any], str, tuple[float, float] | None]] = {
    "cosmic_rate": (float, "cosmic-ray flux, particles per cm^2 per s", (0.0, MAX_COSMIC_RATE)),
    "hits_per_frame": (float, "a fixed mean of hits per frame instead of the flux", (0.0, MAX_SOURCE_HITS_PER_FRAME)),
    "saa": (_flag, "the South Atlantic Anomaly (needs an orbit): 1/0, true/false, yes/no, on/off", None),
    "dose_krad": (float, "total dose, krad: hot pixels grow with it", (0.0, MAX_DOSE_KRAD)),
    "temperature_c": (float, "detector temperature, degC: dark current", TEMPERATURE_RANGE_C),
    "duty": (float, "the housekeeping model's duty cycle 0-1 sets the detector temperature", (0.0, 1.0)),
}


def parse_option_pairs(text: str) -> dict[str, str]:
    """``KEY=VALUE`` items (spaces or commas between them) as a dict; ValueError for an item
    without ``=`` or a key given twice."""
    out: dict[str, str] = {}
    for item in text.replace(",", " ").split():
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError("expected KEY=VALUE items")
        key = key.strip()
        if key in out:
            raise ValueError(f"effect option {key} given twice")
        out[key] = value.strip()
    return out


def effects_from_options(options: dict[str, str], orbit=None) -> MissionEffects | None:
    """The :class:`MissionEffects` a device source's options ask for (:data:`SOURCE_OPTIONS`), with
    the source's ``orbit`` for the SAA; None when none is given; ValueError with a one-line reason
    for an unknown key, a value that is not a number (or not a flag), infinite, NaN or out of its
    range."""
    unknown = sorted(set(options) - set(SOURCE_OPTIONS))
    if unknown:
        raise ValueError(f"unknown effect option(s) {unknown}; known: {sorted(SOURCE_OPTIONS)}")
    if not options:
        return None
    values: dict = {}
    for key, text in options.items():
        convert, _, bounds = SOURCE_OPTIONS[key]
        shown = text if len(text) <= 40 else f"{text[:37]}... ({len(text)} characters)"
        try:
            values[key] = convert(text)
        except ValueError as exc:
            why = str(exc) if bounds is None else "is not a number"
            raise ValueError(f"effect option {key}={shown!r} {why}") from None
        if bounds is not None and not bounds[0] <= values[key] <= bounds[1]:  # NaN too
            raise ValueError(f"effect option {key}={shown} is outside {bounds[0]:g} to {bounds[1]:g}")
    if values.get("saa") and orbit is None:
        raise ValueError("effect option saa needs an orbit to know when the spacecraft is in the anomaly")
    cosmic = None
    if values.get("cosmic_rate", 0.0) or values.get("hits_per_frame") is not None or values.get("saa"):
        cosmic = CosmicRays(
            flux_cm2_s=values.get("cosmic_rate", 0.0),
            hits_per_frame=values.get("hits_per_frame"),
            saa=SouthAtlanticAnomaly() if values.get("saa") else None,
        )
    return MissionEffects(
        cosmic=cosmic,
        dose_krad=values.get("dose_krad", 0.0),
        temperature_c=values.get("temperature_c"),
        duty=values.get("duty"),
        orbit=orbit,
    )


def most_hits(effects: MissionEffects | None, detector: DetectorModel, camera) -> float:
    """The most radiation hits per frame ``effects`` may ask for on ``camera`` in ``detector``'s
    exposure (inside the anomaly when it has one)."""
    if effects is None or effects.cosmic is None:
        return 0.0
    c = effects.cosmic
    mean = c.mean_hits(detector, camera)
    if c.saa is not None:
        mean = max(mean, c.saa.flux_cm2_s * sensitive_area_cm2(detector, camera) * detector.exposure_s)
    return mean


def check_hits(effects: MissionEffects | None, detector: DetectorModel, camera, limit: float) -> None:
    """ValueError with one line when ``effects`` would put more than ``limit`` hits in a frame."""
    mean = most_hits(effects, detector, camera)
    if mean > limit:
        raise ValueError(
            f"effects ask for {mean:.3g} radiation hits per frame ({camera.width} x {camera.height} px, "
            f"{detector.exposure_s:g} s exposure), more than the {limit:g} a frame may hold"
        )
