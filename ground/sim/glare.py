"""The light of the Sun, the Moon and the Earth on the detector: noise-free photo-electrons per
pixel over one exposure, which ``sensor_sim.render_frame(background_e=...)`` adds to the star
signal before the noise is drawn (so shot noise, PRNU and full-well clipping follow).

Models (docs/pipeline.md, "Bright bodies: glare and stray light", has the numbers and sources):

* **Irradiance at the aperture**, as the green-channel e- of a point source of V magnitude
  ``V`` (``DetectorModel.green_electrons``): the Sun ``V = -26.74``; the Moon Allen's phase law
  ``V = -12.73 + 0.026 a + 4e-9 a^4`` (``a`` the phase angle, deg) at its mean distance, scaled
  by the inverse square of its distance; the Earth's daylit disc a Lambertian surface of albedo
  :data:`EARTH_ALBEDO` under the Sun (radiance ``albedo E_sun cos(i) / pi``) integrated over its
  apparent disc. Colours: the Sun's and the Earth's those of a blackbody at the Sun's B-V, the
  Moon's at its B-V (``openloop.blackbody_colours``).
* **Stray light** from every body: its irradiance times the baffle's point-source transmittance
  :class:`PST` at each pixel's own angle to the body (a gradient across the field), times the
  pixel area over the aperture area: e- per pixel. Evaluated on a grid every
  :data:`GRID_PX` pixels and interpolated in log (it changes over degrees, a pixel is 28 arcsec).
* **A body in the field**: its disc, pixel-integrated (:data:`SUBSAMPLES` per axis), lit where
  the surface faces the Sun (the Moon's terminator from the Sun's direction; the Sun all lit),
  its light spread uniformly over the lit part, blurred by the detector's Gaussian PSF; the
  Earth's bright limb is its daylit surface out to ``sky_bodies.ATMOSPHERE_KM``, evaluated every
  :data:`EARTH_STEP_PX` pixels.
* **Eclipse**: with the spacecraft's position known and inside the Earth's cylindrical shadow
  (``orbit.in_earth_shadow``, umbra only), the Sun adds no light; a lunar eclipse is not modelled.

Everything here depends on the geometry only (epoch, position, attitude, camera, detector): a
:class:`Glare` keeps the last two maps it made, and the grid's directions per camera. Written by
hand: no library among the dependencies renders bodies' discs or a baffle's stray light.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.ndimage import gaussian_filter

from firmware_model.camera import CameraModel
from firmware_model.pipeline.raw_frame import pattern_codes
from firmware_model.pipeline.sky_bodies import SkyBody, sky_bodies
from ground.sim.detector_effects import RenderInputs
from ground.sim.orbit import CircularOrbit, in_earth_shadow, utc_iso
from ground.sim.sensor_sim import DetectorModel

V_SUN = -26.74  #: the Sun's apparent V magnitude at 1 au (Allen's Astrophysical Quantities)
AU_KM = 149_597_870.7  #: IAU 2012
BV_SUN = 0.65  #: the Sun's B-V (Ramirez et al. 2012: 0.653)
V_MOON_FULL = -12.73  #: the full Moon at its mean distance (Allen 1973, p. 144)
MOON_MEAN_KM = 384_400.0  #: the distance Allen's law refers to
BV_MOON = 0.92  #: the Moon's B-V (Allen)
EARTH_ALBEDO = 0.30  #: the Earth's Bond albedo, 0.306 (NASA Earth fact sheet), as a grey Lambertian albedo
GRID_PX = 64  #: spacing (px) of the grid the stray light is evaluated on
SUBSAMPLES = 4  #: sub-samples per pixel axis of a disc in the field
FLOOR_E = 0.01  #: e- per pixel below which the stray light is left out (assumption: < 1 % of a DN)
EARTH_RINGS, EARTH_SECTORS = 16, 32  #: the Earth's disc as rings (denser toward the limb) x sectors for its stray light
EARTH_STEP_PX = 4  #: the Earth in the field is evaluated every this many pixels (its limb saturates anyway)


@dataclass(frozen=True)
class PST:
    """Point-source transmittance of the baffle and optics against the angle (deg) from a source:
    irradiance on the focal plane over irradiance at the aperture, interpolated linearly in
    log10 between knots. The default curve is an assumption (docs/pipeline.md): 1e-3 inside the
    field (the optics' own scatter), 1e-4 at 15 deg, 1e-6 at 25 deg, 1e-8 at 35 deg, 1e-9 at
    45 deg and 1e-10 beyond 90 deg, the span of nine orders that published star-tracker baffles
    reach (Marciniak et al. 2013, the ST-16's baffle; Donati 1990; Haghshenas & Johari 2014)."""

    angles_deg: tuple[float, ...] = (0.0, 10.0, 15.0, 25.0, 35.0, 45.0, 90.0, 180.0)
    values: tuple[float, ...] = (1e-3, 3e-4, 1e-4, 1e-6, 1e-8, 1e-9, 1e-10, 1e-10)

    def __post_init__(self):
        a, v = np.asarray(self.angles_deg, float), np.asarray(self.values, float)
        if len(a) != len(v) or len(a) < 2 or np.any(np.diff(a) <= 0) or np.any(v <= 0) or np.any(v > 1):
            raise ValueError("PST knots need increasing angles and values in (0, 1]")

    def __call__(self, theta_rad) -> np.ndarray:
        """PST at angles ``theta_rad`` (rad)."""
        deg = np.degrees(np.asarray(theta_rad, dtype=float))
        return 10.0 ** np.interp(deg, self.angles_deg, np.log10(self.values))


def moon_v_mag(phase_angle_rad: float, distance_km: float) -> float:
    """The Moon's V magnitude at phase angle (rad) and distance (km): Allen's law (valid to a
    phase angle of 150 deg; beyond it extrapolated, a thin crescent far fainter anyway)."""
    a = math.degrees(abs(phase_angle_rad))
    return V_MOON_FULL + 0.026 * a + 4e-9 * a**4 + 5.0 * math.log10(distance_km / MOON_MEAN_KM)


@lru_cache(maxsize=4)
def _colours(bv: float) -> tuple[float, float]:
    """(rg, bg) of a blackbody at B-V ``bv`` through the shipped detector QE."""
    from ground.sim.openloop import blackbody_colours

    rg, bg = blackbody_colours(np.array([bv]), np.ones(1), np.ones(1))
    return float(rg[0]), float(bg[0])


def colour_in_place(img: np.ndarray, det: DetectorModel, colour: tuple[float, float], r0: int = 0, c0: int = 0):
    """Scale ``img`` (green-channel e- of light of ``colour`` (rg, bg), its top-left pixel at row
    ``r0``, column ``c0`` of the frame) in place to the e- each site of ``det``'s CFA collects (a
    mono sensor: ``mono_response (rg + 1 + bg)``)."""
    if det.pattern == "MONO":
        img *= np.float32(det.mono_response * (colour[0] + 1.0 + colour[1]))
        return
    factor = (colour[0], 1.0, colour[1])
    codes = pattern_codes(det.pattern)
    for py in (0, 1):
        for px in (0, 1):
            f = factor[int(codes[(r0 + py) % 2, (c0 + px) % 2])]
            if f != 1.0:
                img[py::2, px::2] *= np.float32(f)


@lru_cache(maxsize=4)
def _grid(camera: CameraModel, step: int):
    """Grid columns and rows (px, the last pixel included) and their sensor-frame unit vectors."""
    cols = np.unique(np.append(np.arange(0, camera.width, step), camera.width - 1)).astype(float)
    rows = np.unique(np.append(np.arange(0, camera.height, step), camera.height - 1)).astype(float)
    xx, yy = np.meshgrid(cols, rows)
    return cols, rows, camera.pixel_to_vector(xx.ravel(), yy.ravel()).reshape(len(rows), len(cols), 3)


@lru_cache(maxsize=4)
def _axis_weights(grid: tuple[float, ...], size: int):
    """Lower grid index and upper weight for every pixel 0..size-1 along one axis."""
    g = np.asarray(grid)
    pos = np.arange(size, dtype=float)
    i0 = np.clip(np.searchsorted(g, pos, side="right") - 1, 0, len(g) - 2)
    t = ((pos - g[i0]) / (g[i0 + 1] - g[i0])).astype(np.float32)
    return i0, t


def _upsample_log(values: np.ndarray, cols, rows, shape) -> np.ndarray:
    """Bilinear interpolation in log of a positive grid to every pixel (float32)."""
    ix, tx = _axis_weights(tuple(cols), shape[1])
    iy, ty = _axis_weights(tuple(rows), shape[0])
    lg = np.log(values).astype(np.float32)
    along = lg[:, ix] * (1 - tx) + lg[:, ix + 1] * tx
    out = along[iy] * (1 - ty)[:, None] + along[iy + 1] * ty[:, None]
    return np.exp(out, out=out)


def _times(v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``v @ m`` for rows of 3-vectors ``v`` (..., 3) and a (3, 3) matrix or a 3-vector ``m``, by
    einsum: matmul with a last axis of 3 goes through BLAS, ~7 times slower on 10^5 rows here."""
    return np.einsum("...j,jk->...k" if m.ndim == 2 else "...j,j->...", v, m)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def exposure_start(mid_utc: str, exposure_s: float) -> str:
    """A frame's ``timestamp`` (the exposure's start, ISO-8601 UTC) for an exposure of ``exposure_s``
    seconds whose mid-time is ``mid_utc`` (docs/CONVENTIONS.md, frame time)."""
    from astropy import units as u

    from firmware_model.pipeline.planets import _as_time

    return (_as_time(mid_utc) - exposure_s / 2.0 * u.s).isot


@dataclass
class Glare:
    """The Sun, the Moon and (with ``sc_position_km``, GCRS km) the Earth at ``epoch_utc``
    (ISO-8601 UTC) as the detector sees them (module docstring); ``pst`` the baffle's curve;
    ``orbit`` places the spacecraft when :meth:`at_time` moves the epoch (the availability run's
    effect interface, ``ground.sim.availability``)."""

    epoch_utc: str
    sc_position_km: np.ndarray | None = None
    pst: PST = PST()
    earth_albedo: float = EARTH_ALBEDO
    orbit: CircularOrbit | None = None
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        if self.sc_position_km is not None:
            self.sc_position_km = np.asarray(self.sc_position_km, dtype=float).reshape(3)
        self.bodies: dict[str, SkyBody] = sky_bodies(self.epoch_utc, self.sc_position_km)

    def at_time(self, t_posix: float) -> Glare:
        """The same glare at POSIX UTC ``t_posix`` (s), the spacecraft on ``orbit`` when given."""
        pos = self.orbit.position_gcrs_km(t_posix) if self.orbit is not None else self.sc_position_km
        return Glare(utc_iso(t_posix), pos, self.pst, self.earth_albedo, self.orbit)

    def render_inputs(self, attitude, camera: CameraModel, detector: DetectorModel, rng) -> RenderInputs:
        """The effect interface of ``ground.sim.detector_effects``: the glare as ``extra_e`` (None
        when nothing reaches ``FLOOR_E``), the exposure's start (the epoch, its mid-time, less half
        the exposure: docs/CONVENTIONS.md) as the timestamp, the position in the metadata when known
        (``rng`` unused: the glare is noise-free)."""
        background = self.background_e(attitude, camera, detector)
        meta = {} if self.sc_position_km is None else {"sc_position_km": [float(v) for v in self.sc_position_km]}
        return RenderInputs(
            detector,
            [],
            background if background.any() else None,
            {"glare": self.truth(attitude, camera, detector)},
            exposure_start(self.epoch_utc, detector.exposure_s),
            meta,
        )

    # ------------------------------------------------------------------ geometry
    def _sun_from(self, body: SkyBody) -> np.ndarray:
        """Unit vector from ``body``'s centre to the Sun."""
        sun = self.bodies["sun"]
        return _unit(sun.direction * sun.distance_km - body.direction * body.distance_km)

    @property
    def eclipsed(self) -> bool:
        """The spacecraft is in the Earth's shadow (known only with its position): no sunlight
        reaches the baffle (``orbit.in_earth_shadow``, umbra only)."""
        return self.sc_position_km is not None and in_earth_shadow(self.sc_position_km, self.bodies["sun"].direction)

    def moon_phase_angle(self) -> float:
        """The Moon's phase angle (rad): Sun-Moon-observer."""
        moon = self.bodies["moon"]
        return math.acos(float(np.clip(np.dot(self._sun_from(moon), -moon.direction), -1.0, 1.0)))

    def _irradiance_e(self, det: DetectorModel) -> dict[str, float]:
        """Green-channel e- of the Sun and the Moon at the aperture over one exposure."""
        sun = self.bodies["sun"]
        v_sun = V_SUN + 5.0 * math.log10(sun.distance_km / AU_KM)
        moon = self.bodies["moon"]
        v_moon = moon_v_mag(self.moon_phase_angle(), moon.distance_km)
        return {"sun": float(det.green_electrons(v_sun)), "moon": float(det.green_electrons(v_moon))}

    def _earth_samples(self, det: DetectorModel):
        """Directions (N, 3) across the Earth's disc and the green e- at the aperture from each
        (its daylit Lambertian radiance times its solid angle)."""
        earth = self.bodies["earth"]
        rho = earth.angular_radius
        e = earth.direction
        u = _unit(np.cross(e, [0.0, 0.0, 1.0] if abs(e[2]) < 0.9 else [1.0, 0.0, 0.0]))
        v = np.cross(e, u)
        edges = rho * (1.0 - (1.0 - np.linspace(0.0, 1.0, EARTH_RINGS + 1)) ** 2)  # rings thin toward the limb
        t = 0.5 * (edges[1:] + edges[:-1])
        phi = (np.arange(EARTH_SECTORS) + 0.5) * 2.0 * np.pi / EARTH_SECTORS
        tt, pp = np.meshgrid(t, phi, indexing="ij")
        d = (
            np.cos(tt)[..., None] * e
            + (np.sin(tt) * np.cos(pp))[..., None] * u
            + (np.sin(tt) * np.sin(pp))[..., None] * v
        ).reshape(-1, 3)
        d_omega = np.repeat((np.cos(edges[:-1]) - np.cos(edges[1:])) * 2.0 * np.pi / EARTH_SECTORS, EARTH_SECTORS)
        return d, d_omega * self._earth_radiance(d, det)

    def _earth_radiance(self, d: np.ndarray, det: DetectorModel) -> np.ndarray:
        """Green e- per steradian at the aperture from the Earth's limb sphere along unit
        vectors ``d`` (ICRS axes) from the spacecraft; 0 where they miss it or it is in night."""
        earth = self.bodies["earth"]
        radius = earth.distance_km * math.sin(earth.angular_radius)
        centre = earth.direction * earth.distance_km  # from the spacecraft
        b = _times(d, centre)
        disc = b * b - earth.distance_km**2 + radius**2
        hit = disc > 0
        s = b - np.sqrt(np.where(hit, disc, 0.0))
        normal = (s[:, None] * d - centre) / radius
        cos_i = np.clip(_times(normal, self._sun_from(earth)), 0.0, None) * hit
        return self._irradiance_e(det)["sun"] * self.earth_albedo * cos_i / math.pi

    # ------------------------------------------------------------------ rendering
    def background_e(self, attitude: np.ndarray, camera: CameraModel, det: DetectorModel) -> np.ndarray:
        """Noise-free e- per pixel (float32, ``(height, width)``) the bodies put on the detector
        at ``attitude`` (A, ``v_sensor = A v_icrs``) over one exposure; kept, so read-only."""
        return self._render(attitude, camera, det)[0]

    def truth(self, attitude: np.ndarray, camera: CameraModel, det: DetectorModel) -> dict:
        """Per body: angle of its centre from the boresight (deg), in-field flag, peak e- per
        pixel it adds (disc or stray light); the Moon's phase angle (deg) and lit fraction."""
        return self._render(attitude, camera, det)[1]

    def _render(self, attitude, camera: CameraModel, det: DetectorModel):
        a = np.asarray(attitude, dtype=float)
        key = (a.tobytes(), camera, det)
        if key not in self._cache:
            if len(self._cache) >= 2:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = self._compute(a, camera, det)
        return self._cache[key]

    def _compute(self, a: np.ndarray, camera: CameraModel, det: DetectorModel):
        shape = (camera.height, camera.width)
        irr = self._irradiance_e(det)
        ratio = (det.pixel_pitch_um * 1e-3) ** 2 / (math.pi * (det.aperture_mm / 2.0) ** 2)  # pixel / aperture area
        cols, rows, grid_sensor = _grid(camera, GRID_PX)
        grid_icrs = _times(grid_sensor, a)  # v_icrs = A^T v_sensor
        boresight = a[2]
        colour = {"sun": _colours(BV_SUN), "moon": _colours(BV_MOON), "earth": _colours(BV_SUN)}
        stray: dict[str, np.ndarray] = {}
        eclipsed = self.eclipsed
        for name in ("sun", "moon"):
            body = self.bodies[name]
            ang = np.arccos(np.clip(grid_icrs @ body.direction, -1.0, 1.0))
            stray[name] = (0.0 if name == "sun" and eclipsed else irr[name]) * ratio * self.pst(ang)
        if "earth" in self.bodies:
            d, e_sample = self._earth_samples(det)
            lit = e_sample > 0
            ang = np.arccos(np.clip(grid_icrs.reshape(-1, 3) @ d[lit].T, -1.0, 1.0))
            stray["earth"] = (ratio * self.pst(ang) @ e_sample[lit]).reshape(grid_icrs.shape[:2])
        total = np.sum(list(stray.values()), axis=0)
        out: np.ndarray | None = None
        truth: dict = {}
        if float(total.max()) >= FLOOR_E:
            out = _upsample_log(np.maximum(total, 1e-30), cols, rows, shape)
            out[out < FLOOR_E] = 0.0
            # the stray light's colour: the mix of the bodies' colours at the boresight's grid point
            ci = int(np.argmin(np.linalg.norm(grid_icrs - boresight, axis=2)))
            w_ = {n: float(s.ravel()[ci]) for n, s in stray.items()}
            wsum = sum(w_.values()) or 1.0
            mix = (sum(w_[n] * colour[n][0] for n in w_) / wsum, sum(w_[n] * colour[n][1] for n in w_) / wsum)
            colour_in_place(out, det, mix)
        if out is None:
            out = np.zeros(shape, np.float32)
        for name, body in self.bodies.items():
            row = {
                "angle_deg": math.degrees(math.acos(float(np.clip(boresight @ body.direction, -1.0, 1.0)))),
                "angular_radius_deg": math.degrees(body.angular_radius),
                "stray_peak_e": float(stray[name].max()),
                "in_field": False,
                "disc_peak_e": 0.0,
            }
            truth[name] = row
        for name in ("sun", "moon"):
            body = self.bodies[name]
            if name == "sun" and eclipsed:
                truth[name]["eclipsed"] = True
                continue
            stamp = self._disc(body, irr[name], a, camera, det, lit_only=name == "moon")
            if stamp is not None:
                (r0, r1, c0, c1), img = stamp
                img = img.astype(np.float32)
                colour_in_place(img, det, colour[name], r0, c0)
                out[r0:r1, c0:c1] += img
                truth[name]["in_field"] = True
                truth[name]["disc_peak_e"] = float(img.max())
        if "earth" in self.bodies:
            limb = self._earth_in_field(a, camera, det)
            if limb is not None:
                colour_in_place(limb, det, colour["earth"])
                out += limb
                truth["earth"]["in_field"] = True
                truth["earth"]["disc_peak_e"] = float(limb.max())
        alpha = self.moon_phase_angle()
        truth["moon"]["phase_angle_deg"] = math.degrees(alpha)
        truth["moon"]["lit_fraction"] = 0.5 * (1.0 + math.cos(alpha))
        truth["epoch_utc"] = self.epoch_utc
        if self.sc_position_km is not None:
            truth["sc_position_km"] = [float(v) for v in self.sc_position_km]
        return out, truth

    def _disc(self, body: SkyBody, total_e: float, a, camera: CameraModel, det: DetectorModel, lit_only: bool):
        """The body's disc on the detector: ((r0, r1, c0, c1), green e- per pixel), None when it
        misses the array. Its ``total_e`` spread uniformly over the lit part of the disc (all of
        it unless ``lit_only``), pixel-integrated, blurred by the Gaussian PSF."""
        x, y = camera.vector_to_pixel(a @ body.direction)
        if not (np.isfinite(x[0]) and np.isfinite(y[0])):
            return None
        sigma = max(det.psf_sigma_px, 0.0)
        rad = body.angular_radius * camera.f * 1.2 + 4.0 * sigma + 3.0
        c0, c1 = max(int(x[0] - rad), 0), min(int(x[0] + rad) + 2, camera.width)
        r0, r1 = max(int(y[0] - rad), 0), min(int(y[0] + rad) + 2, camera.height)
        if c0 >= c1 or r0 >= r1:
            return None
        n = SUBSAMPLES
        sub = (np.arange(n) + 0.5) / n - 0.5
        xs = (np.arange(c0, c1)[:, None] + sub[None, :]).ravel()
        ys = (np.arange(r0, r1)[:, None] + sub[None, :]).ravel()
        xx, yy = np.meshgrid(xs, ys)
        d = _times(camera.pixel_to_vector(xx.ravel(), yy.ravel()), a)
        centre = body.direction * body.distance_km
        radius = body.distance_km * math.sin(body.angular_radius)
        b = _times(d, centre)
        disc = b * b - body.distance_km**2 + radius**2
        inside = disc > 0
        if lit_only:
            s = b - np.sqrt(np.where(inside, disc, 0.0))
            normal = (s[:, None] * d - centre) / radius
            inside &= _times(normal, self._sun_from(body)) > 0
        frac = inside.reshape(r1 - r0, n, c1 - c0, n).mean(axis=(1, 3))
        if not frac.any():
            return None
        k = 0.5 * (1.0 + math.cos(self.moon_phase_angle())) if lit_only else 1.0
        omega_lit = k * 2.0 * math.pi * (1.0 - math.cos(body.angular_radius))
        img = frac * (total_e / (omega_lit * camera.f**2))
        if sigma > 0:
            img = gaussian_filter(img, sigma, mode="constant")
        return (r0, r1, c0, c1), img

    def _earth_in_field(self, a, camera: CameraModel, det: DetectorModel) -> np.ndarray | None:
        """The Earth's daylit disc where it falls in the field (green e- per pixel, evaluated every
        :data:`EARTH_STEP_PX` pixels and interpolated bilinearly, blurred by the PSF), None when the
        field misses it."""
        earth = self.bodies["earth"]
        diag = camera.fov_half_angle_diagonal
        if math.acos(float(np.clip(a[2] @ earth.direction, -1.0, 1.0))) > earth.angular_radius + diag:
            return None
        step = EARTH_STEP_PX
        cols = np.unique(np.append(np.arange(0, camera.width, step), camera.width - 1)).astype(float)
        rows = np.unique(np.append(np.arange(0, camera.height, step), camera.height - 1)).astype(float)
        xx, yy = np.meshgrid(cols, rows)
        d = _times(camera.pixel_to_vector(xx.ravel(), yy.ravel()), a)
        coarse = self._earth_radiance(d, det).reshape(len(rows), len(cols)) / camera.f**2
        if not coarse.any():
            return None
        ix, tx = _axis_weights(tuple(cols), camera.width)
        iy, ty = _axis_weights(tuple(rows), camera.height)
        c32 = coarse.astype(np.float32)
        along = c32[:, ix] * (1 - tx) + c32[:, ix + 1] * tx
        per_pixel = along[iy] * (1 - ty)[:, None] + along[iy + 1] * ty[:, None]
        if det.psf_sigma_px > 0:
            per_pixel = gaussian_filter(per_pixel, det.psf_sigma_px, mode="nearest")
        return per_pixel
