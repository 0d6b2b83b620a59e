"""A detector's temporal noise drawn once and served shifted: exposures at a device's cadence.

Fresh full-frame draws (Poisson background and Gaussian read noise over the reference design's
5 Mpx) cost about 220 ms a frame, most of the device's GO -> result budget (docs/hil.md). A
:class:`NoiseBank` draws ``n`` padded frames of background shot noise plus read noise once, at
start-up, and gives each exposure a window of one of them at a seed-chosen offset and flip; the
star signal (Poisson in the pixels it covers) and the hot pixels (Poisson) are drawn per exposure.
Means and distributions are those of ``sensor_sim.render_frame`` (the bank's shot noise uses the
mean background rate, off by the PRNU's 1 % in variance); values differ from it for the same seed,
and exposures share noise fields moved by random offsets (nothing correlates inside one frame).
A saturated pixel reads exactly full well (``render_frame`` adds read noise after clipping; the
DN clip hides the difference for the default detector).

The bank's draws are the slow part (most of a second for the reference design); with
``cache_dir`` they are drawn once per detector, shape, seed and numpy version, kept there as one
``.npy`` file and loaded afterwards (the same values as a fresh draw: the cache is keyed by
everything the draw depends on, this module's code included). A cache that cannot be read or
written is passed over: the bank is then drawn, never wrong.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
from pathlib import Path

import numpy as np

from ground.atomic_write import atomic_path
from ground.sim.sensor_sim import DetectorModel, fixed_pattern

log = logging.getLogger(__name__)

PAD_PX = 128  #: the bank's margin: offsets 0..PAD_PX in rows and columns
#: Bank files kept in a cache folder (the newest by modification time; each is n x 22 MB for the
#: reference design).
CACHE_FILES_KEPT = 4


class NoiseBank:
    """Noise of ``det`` for frames of ``shape`` (rows, cols); ``n`` bank frames from ``seed``."""

    def __init__(
        self, det: DetectorModel, shape: tuple[int, int], n: int = 2, seed: int = 0, cache_dir: Path | None = None
    ):
        self.det = det
        self.shape = shape
        prnu, dsnu, hot = fixed_pattern(det, shape)
        self.prnu = prnu
        self.hot = hot
        t = det.exposure_s
        sky, dark = det.sky_e_per_s * t, det.dark_e_per_s * t
        base = sky * prnu + dark + dsnu
        base.ravel()[hot] += det.hot_pixel_e_per_s * t
        self.base = base.astype(np.float32)
        lam = sky * float(np.mean(prnu)) + dark
        banks = None if cache_dir is None else _cached(cache_dir, det, shape, n, seed, lam)
        if banks is None:
            banks = _draw(det, shape, n, seed, lam)
            if cache_dir is not None:
                _store(cache_dir, det, shape, n, seed, lam, banks)
        self.banks = list(banks)

    def electrons(self, signal: np.ndarray, seed: int) -> np.ndarray:
        """e- per pixel (float32) for the noise-free star ``signal`` (e-, ``shape``), clipped to full well."""
        if signal.shape != self.shape:
            raise ValueError(f"signal is {signal.shape}, the bank's frames are {self.shape}")
        det, (h, w) = self.det, self.shape
        rng = np.random.default_rng(seed)
        bank = self.banks[int(rng.integers(len(self.banks)))]
        r0, c0 = (int(v) for v in rng.integers(0, PAD_PX + 1, size=2))
        window = bank[r0 : r0 + h, c0 : c0 + w]
        flip_rows, flip_cols = rng.integers(0, 2, size=2)
        window = window[:: -1 if flip_rows else 1, :: -1 if flip_cols else 1]
        out = self.base + window
        flat = out.ravel()
        lit = np.flatnonzero(signal)
        flat[lit] += rng.poisson(signal.ravel()[lit] * self.prnu.ravel()[lit])
        hot_mean = det.hot_pixel_e_per_s * det.exposure_s
        flat[self.hot] += rng.poisson(hot_mean, len(self.hot)) - hot_mean
        return np.minimum(out, np.float32(det.full_well_e), out=out)


def _draw(det: DetectorModel, shape: tuple[int, int], n: int, seed: int, lam: float) -> np.ndarray:
    """``n`` padded frames of background shot noise (mean ``lam`` e-, removed) plus read noise, float32."""
    rng = np.random.default_rng(seed)
    h, w = shape
    banks = np.empty((n, h + PAD_PX, w + PAD_PX), dtype=np.float32)
    for b in banks:
        b[...] = rng.poisson(lam, b.shape).astype(np.float32) - np.float32(lam)
        b += np.float32(det.read_noise_e) * rng.standard_normal(b.shape, dtype=np.float32)
    return banks


def _cache_file(cache_dir: Path, det: DetectorModel, shape, n: int, seed: int, lam: float) -> Path:
    """The bank's file: named by a hash of everything its values depend on."""
    key = {
        "detector": dataclasses.asdict(det),
        "shape": list(shape),
        "n": n,
        "seed": seed,
        "lam": lam.hex(),
        "numpy": np.__version__,
        "code": hashlib.sha256(Path(__file__).read_bytes()).hexdigest(),
    }
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:32]
    return Path(cache_dir) / f"bank-{digest}.npy"


def _cached(cache_dir: Path, det: DetectorModel, shape, n: int, seed: int, lam: float) -> np.ndarray | None:
    """The bank kept in ``cache_dir``, or None (none kept, unreadable, or not of the bank's shape)."""
    path = _cache_file(cache_dir, det, shape, n, seed, lam)
    try:
        banks = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError):
        return None
    if banks.dtype != np.float32 or banks.shape != (n, shape[0] + PAD_PX, shape[1] + PAD_PX):
        return None
    with contextlib.suppress(OSError):
        path.touch()  # recently used: kept by the pruning
    return banks


def _store(cache_dir: Path, det: DetectorModel, shape, n: int, seed: int, lam: float, banks: np.ndarray) -> None:
    """Keep ``banks`` in ``cache_dir`` (written whole or not at all), and only the
    :data:`CACHE_FILES_KEPT` newest bank files there; a folder that cannot take it is said once in the log."""
    path = _cache_file(cache_dir, det, shape, n, seed, lam)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            np.save(tmp, banks, allow_pickle=False)
    except OSError as exc:
        log.warning("noise bank not cached in %s: %s", cache_dir, exc)
        return
    ages = {}
    for other in path.parent.glob("bank-*.npy"):
        with contextlib.suppress(OSError):  # another device may prune the same folder
            ages[other] = other.stat().st_mtime
    for old in sorted(ages, key=ages.__getitem__, reverse=True)[CACHE_FILES_KEPT:]:
        with contextlib.suppress(OSError):
            old.unlink()
