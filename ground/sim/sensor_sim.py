"""Sensor simulator: render a raw CFA (or mono) frame from stars, an attitude, a camera
model and a detector model, with the truth beside it. Deterministic for a given seed.

Signal model (docs/pipeline.md has the defaults and their rationale):

* Green channel total for a star of V magnitude ``V`` (photo-electrons)::

      S_g = PHI_V0 * dlambda_g * A_aperture * tau_optics * qe_green * t_exp * 10**(-0.4 V)

  with ``PHI_V0 = 1004 photons s^-1 cm^-2 A^-1`` (Johnson V zero point, 3.63e-9
  erg s^-1 cm^-2 A^-1 at 5500 A) and ``dlambda_g`` the effective width of the green
  filter. ``S_r = rg * S_g`` and ``S_b = bg * S_g``, so the catalog colour ratios are the
  truth ratios exactly. ``S_c`` is the *channel total*: the electrons a sensor made only of
  channel-c pixels would collect (docs/CONVENTIONS.md, colour ratios); a CFA site of
  channel c at pixel (r, c) receives ``S_c * P(r, c)`` with ``P`` the pixel-integrated PSF.
  A mono sensor receives ``mono_response * (S_r + S_g + S_b)`` per unit PSF.
* PSF: Gaussian of standard deviation ``psf_sigma_px`` integrated exactly over each pixel
  (error functions), or a defocus disc of radius ``defocus_radius_px`` convolved with the
  Gaussian, integrated by 8x8 sub-pixel sampling.
* Detector: sky background and dark current (Poisson), photo-response non-uniformity
  (multiplicative, fixed per sensor), dark-signal non-uniformity (additive, fixed per
  sensor), hot pixels (fixed positions, high dark rate), full-well clipping, read noise
  (Gaussian, e-), gain (e-/DN), black level (DN), quantisation and clipping to
  ``2**bit_depth - 1``. Fixed-pattern maps come from ``sensor_seed`` so every frame of one
  simulated sensor shares them; temporal noise comes from the frame ``seed``.
* Optional ``render_frame`` arguments bring in what the solver does not model (another PSF,
  extra background, per-channel gains, another camera mapping): ``ground/sim/openloop.py``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.special import erf

from firmware_model.camera import CameraModel
from firmware_model.pipeline.raw_frame import Frame, normalise_pattern, pattern_codes
from firmware_model.reference_frames import matrix_to_quat

#: Johnson V zero-point photon flux density, photons s^-1 cm^-2 A^-1 (3.63e-9 erg/s/cm^2/A at 5500 A).
PHI_V0 = 1004.0


@dataclass(frozen=True)
class DetectorModel:
    """Optics + detector parameters; defaults are the Enright & McVittie reference design with an
    MT9P031-class colour CMOS (docs/pipeline.md)."""

    pattern: str = "RGGB"
    aperture_mm: float = 12.0
    tau_optics: float = 0.8
    qe_green: float = 0.45
    band_green_A: float = 1000.0
    mono_response: float = 1.0
    exposure_s: float = 0.1
    psf_sigma_px: float = 1.0
    defocus_radius_px: float = 0.0
    sky_e_per_s: float = 10.0
    dark_e_per_s: float = 25.0
    read_noise_e: float = 3.0
    prnu: float = 0.01
    dsnu_e: float = 1.0
    hot_pixel_fraction: float = 2e-5
    hot_pixel_e_per_s: float = 5000.0
    full_well_e: float = 6500.0
    gain_e_per_dn: float = 1.6
    bit_depth: int = 12
    black_level_dn: float = 64.0
    sensor_seed: int = 1
    #: pixel pitch (um): the MT9P031's 2.2 um square pixels (its product brief; seed 000 section 2.1)
    pixel_pitch_um: float = 2.2

    def __post_init__(self):
        object.__setattr__(self, "pattern", normalise_pattern(self.pattern))
        for name in (
            "aperture_mm",
            "tau_optics",
            "qe_green",
            "band_green_A",
            "gain_e_per_dn",
            "full_well_e",
            "pixel_pitch_um",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"detector {name} must be positive")
        if self.psf_sigma_px <= 0 and self.defocus_radius_px <= 0:
            raise ValueError("PSF needs a positive Gaussian sigma or defocus radius")
        if not 8 <= self.bit_depth <= 16:
            raise ValueError("bit depth must be 8..16")

    @property
    def white_level_dn(self) -> int:
        return 2**self.bit_depth - 1

    def green_electrons(self, vmag) -> np.ndarray:
        """Green channel total S_g (e-) for V magnitude(s) over one exposure."""
        area_cm2 = np.pi * (self.aperture_mm / 20.0) ** 2
        s0 = PHI_V0 * self.band_green_A * area_cm2 * self.tau_optics * self.qe_green * self.exposure_s
        return s0 * 10.0 ** (-0.4 * np.asarray(vmag, dtype=float))

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Stars:
    """Stars to render: catalog ids, ICRS unit vectors (N, 3), V magnitudes, colour ratios."""

    ids: np.ndarray
    vectors: np.ndarray
    vmag: np.ndarray
    rg: np.ndarray
    bg: np.ndarray

    def __post_init__(self):
        self.ids = np.asarray(self.ids, dtype=np.int64).ravel()
        self.vectors = np.asarray(self.vectors, dtype=float).reshape(-1, 3)
        self.vmag = np.asarray(self.vmag, dtype=float).ravel()
        self.rg = np.asarray(self.rg, dtype=float).ravel()
        self.bg = np.asarray(self.bg, dtype=float).ravel()
        n = len(self.ids)
        if not all(len(a) == n for a in (self.vectors, self.vmag, self.rg, self.bg)):
            raise ValueError("star arrays must all have the same length")


@dataclass
class FalseObject:
    """A non-catalog source: ``kind`` 'planet' (PSF source with its own flux and colour),
    'satellite' (streak from (x, y) to (x2, y2)) or 'cosmic' (sharp hit from (x, y) to (x2, y2),
    ``electrons_g`` e- in all, not filtered by the CFA). A cosmic hit with ``diffusion_px`` set is a
    particle track (``ground.sim.detector_effects``): its charge shared by path length along the
    segment and spread by a pixel-integrated Gaussian of that sigma (px; 0: no spread)."""

    kind: str
    x: float
    y: float
    electrons_g: float
    rg: float = 1.0
    bg: float = 1.0
    x2: float | None = None
    y2: float | None = None
    diffusion_px: float | None = None


@dataclass
class RenderResult:
    frame: Frame
    truth: dict
    electrons: np.ndarray = field(repr=False)  # noise-free expected e- per pixel (signal only)


def pixel_integrated_gaussian(x0: float, y0: float, sigma: float, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Fraction of a unit Gaussian centred at (x0, y0) falling in each pixel of the grid
    ``rows x cols`` (pixel centres at integer coordinates)."""
    s = np.sqrt(2.0) * sigma
    ex = 0.5 * (erf((cols + 0.5 - x0) / s) - erf((cols - 0.5 - x0) / s))
    ey = 0.5 * (erf((rows + 0.5 - y0) / s) - erf((rows - 0.5 - y0) / s))
    return ey[:, None] * ex[None, :]


def _psf_stamp(det: DetectorModel, x0: float, y0: float, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    if det.defocus_radius_px <= 0:
        return pixel_integrated_gaussian(x0, y0, det.psf_sigma_px, cols, rows)
    n = 8  # sub-samples per pixel axis
    sub = (np.arange(n) + 0.5) / n - 0.5
    xs = (cols[:, None] + sub[None, :]).ravel()
    ys = (rows[:, None] + sub[None, :]).ravel()
    dx, dy = xs[None, :] - x0, ys[:, None] - y0
    disc = (dx * dx + dy * dy <= det.defocus_radius_px**2).astype(float)
    if det.psf_sigma_px > 0:
        from scipy.ndimage import gaussian_filter

        disc = gaussian_filter(disc, det.psf_sigma_px * n, mode="constant")
    total = disc.sum()
    stamp = disc.reshape(len(rows), n, len(cols), n).sum(axis=(1, 3))
    return stamp / total if total > 0 else stamp


def stamp_half_width(det: DetectorModel) -> int:
    """Half-width (px) of the detector PSF's stamp."""
    return int(np.ceil(5.0 * det.psf_sigma_px + det.defocus_radius_px + 2))


def _add_source(img, chan_map, det, x0, y0, s_rgb, mono, psf=None):
    h, w = img.shape
    hw = stamp_half_width(det) if psf is None else psf.half_width(x0, y0)
    c0, c1 = max(int(np.floor(x0)) - hw, 0), min(int(np.floor(x0)) + hw + 1, w)
    r0, r1 = max(int(np.floor(y0)) - hw, 0), min(int(np.floor(y0)) + hw + 1, h)
    if c0 >= c1 or r0 >= r1:
        return
    cols, rows = np.arange(c0, c1, dtype=float), np.arange(r0, r1, dtype=float)
    stamp = _psf_stamp(det, x0, y0, cols, rows) if psf is None else psf.stamp(x0, y0, cols, rows)
    if mono:
        img[r0:r1, c0:c1] += det.mono_response * sum(s_rgb) * stamp
    else:
        amp = np.asarray(s_rgb, dtype=float)[chan_map[r0:r1, c0:c1]]
        img[r0:r1, c0:c1] += amp * stamp


def _add_streak(img, chan_map, det, obj, mono, psf=None):
    length = np.hypot(obj.x2 - obj.x, obj.y2 - obj.y)
    n = max(int(np.ceil(length / 0.5)), 2)
    s = np.array([obj.rg, 1.0, obj.bg]) * obj.electrons_g / n
    for t in np.linspace(0.0, 1.0, n):
        _add_source(img, chan_map, det, obj.x + t * (obj.x2 - obj.x), obj.y + t * (obj.y2 - obj.y), s, mono, psf)


_TRACK_STEP_PX = 0.1  #: spacing (px) of a track's charge samples
_TRACK_CHUNK = 256  #: samples per stamp (25.6 px of track), so a grazing track never makes one huge stamp


def _add_track(img: np.ndarray, obj: FalseObject) -> None:
    """A particle track's charge (e-) added to ``img``: ``obj.electrons_g`` shared equally over
    points every :data:`_TRACK_STEP_PX` along (x, y)-(x2, y2), each spread by a pixel-integrated
    Gaussian of ``obj.diffusion_px`` (or into its own pixel when 0); charge off the array is lost."""
    h, w = img.shape
    x2 = obj.x if obj.x2 is None else obj.x2
    y2 = obj.y if obj.y2 is None else obj.y2
    n = max(int(np.ceil(np.hypot(x2 - obj.x, y2 - obj.y) / _TRACK_STEP_PX)), 1)
    t = (np.arange(n) + 0.5) / n
    xs, ys = obj.x + t * (x2 - obj.x), obj.y + t * (y2 - obj.y)
    q = obj.electrons_g / n
    sigma = float(obj.diffusion_px or 0.0)
    if sigma <= 0:
        ci, ri = np.floor(xs + 0.5).astype(int), np.floor(ys + 0.5).astype(int)
        inside = (ci >= 0) & (ci < w) & (ri >= 0) & (ri < h)
        np.add.at(img, (ri[inside], ci[inside]), q)
        return
    hw, s = int(np.ceil(4.0 * sigma)) + 1, np.sqrt(2.0) * sigma
    for k in range(0, n, _TRACK_CHUNK):
        cx, cy = xs[k : k + _TRACK_CHUNK], ys[k : k + _TRACK_CHUNK]
        c0, c1 = max(int(np.floor(cx.min() + 0.5)) - hw, 0), min(int(np.floor(cx.max() + 0.5)) + hw + 1, w)
        r0, r1 = max(int(np.floor(cy.min() + 0.5)) - hw, 0), min(int(np.floor(cy.max() + 0.5)) + hw + 1, h)
        if c0 >= c1 or r0 >= r1:
            continue
        cols, rows = np.arange(c0, c1, dtype=float), np.arange(r0, r1, dtype=float)
        ex = 0.5 * (erf((cols[None, :] + 0.5 - cx[:, None]) / s) - erf((cols[None, :] - 0.5 - cx[:, None]) / s))
        ey = 0.5 * (erf((rows[None, :] + 0.5 - cy[:, None]) / s) - erf((rows[None, :] - 0.5 - cy[:, None]) / s))
        img[r0:r1, c0:c1] += q * (ey.T @ ex)


_FIXED_CACHE: dict = {}  #: last fixed-pattern maps (read-only arrays), keyed by what draws them


def fixed_pattern(det: DetectorModel, shape):
    """(PRNU gain map, DSNU e- map, flat indices of hot pixels) of the simulated sensor; cached."""
    key = (det.sensor_seed, det.prnu, det.dsnu_e, det.hot_pixel_fraction, tuple(shape))
    if key in _FIXED_CACHE:
        return _FIXED_CACHE[key]
    rng = np.random.default_rng(det.sensor_seed)
    prnu = 1.0 + det.prnu * rng.standard_normal(shape)
    dsnu = det.dsnu_e * rng.standard_normal(shape)
    n_hot = rng.binomial(shape[0] * shape[1], det.hot_pixel_fraction)
    hot = rng.choice(shape[0] * shape[1], size=n_hot, replace=False)
    for arr in (prnu, dsnu, hot):
        arr.setflags(write=False)
    _FIXED_CACHE.clear()  # one sensor at a time: the maps of a full frame are ~80 MB
    _FIXED_CACHE[key] = (prnu, dsnu, hot)
    return prnu, dsnu, hot


def _fresh_noise(det, signal, chan_map, mono, seed, extra_e, channel_gain) -> np.ndarray:
    """Electrons per pixel (before quantisation) with every noise term drawn afresh from ``seed``;
    scales ``signal`` in place by ``channel_gain``."""
    h, w = signal.shape
    prnu, dsnu, hot = fixed_pattern(det, (h, w))
    rng = np.random.default_rng(seed)
    dark = np.full((h, w), det.dark_e_per_s * det.exposure_s)
    dark.ravel()[hot] += det.hot_pixel_e_per_s * det.exposure_s
    sky = det.sky_e_per_s * det.exposure_s
    if channel_gain is not None and not mono:
        gmap = np.asarray(channel_gain, dtype=float)[chan_map]
        signal *= gmap
        sky = sky * gmap
    expected = (signal + sky) * prnu + dark
    if extra_e is not None:
        if np.shape(extra_e) != (h, w):
            raise ValueError(f"extra_e must have shape {(h, w)}, got {np.shape(extra_e)}")
        expected = expected + np.asarray(extra_e, dtype=float)
    electrons = rng.poisson(expected).astype(float) + dsnu
    electrons = np.minimum(electrons, det.full_well_e)
    electrons += det.read_noise_e * rng.standard_normal((h, w))
    return electrons


def render_frame(
    stars: Stars,
    attitude: np.ndarray,
    camera: CameraModel,
    detector: DetectorModel = DetectorModel(),
    seed: int = 0,
    false_objects: Sequence[FalseObject] = (),
    timestamp: str | None = None,
    psf=None,
    extra_e: np.ndarray | None = None,
    channel_gain: tuple[float, float, float] | None = None,
    noise=None,
    background_e: np.ndarray | None = None,
) -> RenderResult:
    """Render one frame. ``attitude`` is A (v_sensor = A @ v_icrs). Returns the frame, the
    truth dict (JSON-serialisable) and the noise-free expected signal electrons.

    Optional impairments (defaults leave the frame exactly as without them):

    * ``psf``: an object with ``half_width(x0, y0) -> int`` (px), ``max_half_width`` (px),
      ``stamp(x0, y0, cols, rows) -> array`` (fraction of a unit source per pixel) and
      ``to_dict()``, used instead of the detector's Gaussian/defocus PSF for every source
      (``ground.sim.openloop`` has Moffat, donut and field-dependent coma PSFs);
    * ``extra_e``: noise-free e- per pixel over the exposure (shape ``(height, width)``) added
      to the Poisson mean after PRNU (sky gradients, hot-pixel clusters);
    * ``channel_gain``: ``(g_r, g_g, g_b)`` multipliers on the signal and sky electrons of the
      R, G, B sites (per-channel QE/gain error; ignored for MONO);
    * ``noise``: an object with ``electrons(signal, seed) -> array`` (e- per pixel before
      quantisation) that draws the detector noise instead of fresh full-frame draws
      (``ground.sim.noise_bank.NoiseBank``: the device's capture sources); the same
      distributions, other values; not with ``extra_e`` or ``channel_gain``;
    * ``background_e``: noise-free signal e- per pixel over the exposure (shape ``(height, width)``,
      per CFA site: channel colours already applied) added to the star signal before the noise is
      drawn, so its shot noise, PRNU and full-well clipping follow; unlike ``extra_e`` it works with
      ``noise`` (``ground.sim.glare``: the Sun, the Moon and the Earth). The returned
      ``electrons`` include it.

    ``camera`` may be any object with ``width``, ``height``, ``vector_to_pixel``, ``in_frame``
    and ``to_dict`` (``ground.sim.openloop.RadialMappedCamera`` renders non-Brown-Conrady optics)."""
    det = detector
    h, w = camera.height, camera.width
    mono = det.pattern == "MONO"
    chan_map = np.tile(pattern_codes(det.pattern), (h // 2 + 1, w // 2 + 1))[:h, :w]
    if not mono and (h % 2 or w % 2):
        raise ValueError(f"a {det.pattern} sensor needs even dimensions, got {w} x {h}")
    a = np.asarray(attitude, dtype=float)
    v_sensor = stars.vectors @ a.T
    x, y = camera.vector_to_pixel(v_sensor)
    margin = stamp_half_width(det) if psf is None else psf.max_half_width
    near = np.isfinite(x) & camera.in_frame(x, y, margin=-margin)
    s_g = det.green_electrons(stars.vmag)
    signal = np.zeros((h, w))
    star_rows = []
    for i in np.flatnonzero(near):
        s_rgb = (stars.rg[i] * s_g[i], s_g[i], stars.bg[i] * s_g[i])
        _add_source(signal, chan_map, det, x[i], y[i], s_rgb, mono, psf)
        if camera.in_frame(x[i], y[i]):
            star_rows.append(
                {
                    "id": int(stars.ids[i]),
                    "x": float(x[i]),
                    "y": float(y[i]),
                    "vmag": float(stars.vmag[i]),
                    "rg": float(stars.rg[i]),
                    "bg": float(stars.bg[i]),
                    "electrons": (
                        {"mono": float(det.mono_response * sum(s_rgb))}
                        if mono
                        else {"r": float(s_rgb[0]), "g": float(s_rgb[1]), "b": float(s_rgb[2])}
                    ),
                }
            )
    false_rows = []
    for obj in false_objects:
        if obj.kind == "planet":
            _add_source(
                signal,
                chan_map,
                det,
                obj.x,
                obj.y,
                (obj.rg * obj.electrons_g, obj.electrons_g, obj.bg * obj.electrons_g),
                mono,
                psf,
            )
        elif obj.kind == "satellite":
            if obj.x2 is None or obj.y2 is None:
                raise ValueError("a satellite streak needs x2, y2")
            _add_streak(signal, chan_map, det, obj, mono, psf)
        elif obj.kind == "cosmic" and obj.diffusion_px is not None:
            _add_track(signal, obj)
        elif obj.kind == "cosmic":
            x2 = obj.x if obj.x2 is None else obj.x2
            y2 = obj.y if obj.y2 is None else obj.y2
            n = int(max(abs(x2 - obj.x), abs(y2 - obj.y))) + 1
            rr = np.clip(np.round(np.linspace(obj.y, y2, n)).astype(int), 0, h - 1)
            cc = np.clip(np.round(np.linspace(obj.x, x2, n)).astype(int), 0, w - 1)
            signal[rr, cc] += obj.electrons_g / n
        else:
            raise ValueError(f"unknown false object kind {obj.kind!r}")
        row = asdict(obj)
        if obj.diffusion_px is None:  # the rows of plain objects as before tracks existed
            del row["diffusion_px"]
        false_rows.append(row)

    if background_e is not None:
        if np.shape(background_e) != (h, w):
            raise ValueError(f"background_e must have shape {(h, w)}, got {np.shape(background_e)}")
        signal += np.asarray(background_e, dtype=float)
    hot = fixed_pattern(det, (h, w))[2]
    if noise is not None:
        if extra_e is not None or channel_gain is not None:
            raise ValueError("a noise bank does not take extra_e or channel_gain")
        electrons = noise.electrons(signal, seed)
    else:
        electrons = _fresh_noise(det, signal, chan_map, mono, seed, extra_e, channel_gain)
    dn = np.round(det.black_level_dn + electrons / det.gain_e_per_dn)
    dn = np.clip(dn, 0, det.white_level_dn).astype(np.uint16)

    frame = Frame(
        pixels=dn,
        pattern=det.pattern,
        black_level=det.black_level_dn,
        white_level=det.white_level_dn,
        exposure_s=det.exposure_s,
        timestamp=timestamp,
        camera=camera.to_dict(),
        metadata={"simulated": True, "seed": int(seed), "gain_e_per_dn": det.gain_e_per_dn},
    )
    truth = {
        "format": "st16-render-truth",
        "seed": int(seed),
        "attitude_quaternion": [float(q) for q in matrix_to_quat(a)],
        "attitude_convention": "scalar-first, ICRS->sensor (v_sensor = A @ v_icrs)",
        "camera": camera.to_dict(),
        "detector": det.to_dict(),
        "electrons_convention": "channel totals S_c (e-) per docs/CONVENTIONS.md; CFA site gets S_c * PSF",
        "hot_pixels": [[int(i // w), int(i % w)] for i in hot],
        "stars": star_rows,
        "false_objects": false_rows,
    }
    if psf is not None:
        truth["psf"] = psf.to_dict()
    if channel_gain is not None and not mono:
        truth["channel_gain"] = [float(g) for g in channel_gain]
    return RenderResult(frame=frame, truth=truth, electrons=signal)


def random_star_field(
    camera: CameraModel,
    attitude: np.ndarray,
    n: int,
    vmag_range: tuple[float, float] = (2.0, 7.0),
    seed: int = 0,
    margin_px: float = 20.0,
    min_separation_px: float = 0.0,
) -> Stars:
    """``n`` synthetic stars uniformly placed in the camera's field (``margin_px`` from the
    edges), magnitudes uniform in ``vmag_range``, colour ratios rg in [0.3, 1.6] and bg in
    [0.2, 1.4] (the spread of real stars through a Bayer CMOS), as ICRS vectors for
    ``attitude``. Ids are 1..n. ``min_separation_px`` rejects crowded placements."""
    rng = np.random.default_rng(seed)
    xs: list[float] = []
    ys: list[float] = []
    while len(xs) < n:
        xc = rng.uniform(margin_px, camera.width - 1 - margin_px)
        yc = rng.uniform(margin_px, camera.height - 1 - margin_px)
        if min_separation_px > 0 and xs and np.min(np.hypot(np.array(xs) - xc, np.array(ys) - yc)) < min_separation_px:
            continue
        xs.append(xc)
        ys.append(yc)
    v_sensor = camera.pixel_to_vector(np.array(xs), np.array(ys))
    v_icrs = v_sensor @ np.asarray(attitude, dtype=float)
    return Stars(
        ids=np.arange(1, n + 1),
        vectors=v_icrs,
        vmag=rng.uniform(*vmag_range, size=n),
        rg=rng.uniform(0.3, 1.6, size=n),
        bg=rng.uniform(0.2, 1.4, size=n),
    )
