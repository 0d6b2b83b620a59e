"""Learning each catalog star's colour ratios from its matched observations (docs/learned_colours.md).

Enright & McVittie close with "an adaptive, on-line algorithm in which the sensor gradually
learned the specific color ratios for each cataloged star". Here, per star and per ratio
(``rg = S_r / S_g``, ``bg = S_b / S_g``, dimensionless):

* **prior**: Gaussian, centred on the catalog value, with sigma ``prior_rel`` x that value (the
  colour model's error, default 5 %);
* **likelihood**: the star's matched observations, each Gaussian with its measured sigma times
  one run-wide ``sigma_scale`` (the measured sigmas count photon noise only; scintillation and
  the atmosphere add more), floored at ``sigma_floor``;
* **outliers** (a wrong match, a blend): the star's estimate starts at the median of its
  observations; an observation whose 2-D normalised distance from the star's running
  data-only weighted mean exceeds ``clip`` is rejected, repeated until nothing changes;
* **minimum**: a star with fewer than ``min_obs`` observations left keeps its catalog colours.

The posterior is the precision-weighted mean of prior and kept observations. A star without a
catalog colour (NaN) has no prior and is left alone. If no star reaches the minimum, nothing
changes and :attr:`LearnedColours.reason` says why in one line. The observations must be in the
colour space the matcher compares: raw measured ratios through the eq. 24 correction in use.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from firmware_model.pipeline.frame_identification import apply_colour_correction
from protocol.catalog_image import parse_image, with_star_colours

PRIOR_REL = 0.05  #: prior sigma of a catalog colour ratio, relative to the ratio
CLIP = 3.0  #: outlier threshold, 2-D normalised distance (chi-square 2 dof: 1.1 % of good data)
MIN_OBS = 3  #: fewest kept observations that update a star
SIGMA_FLOOR = 0.005  #: smallest observation sigma used (a ratio)
MAX_ITER = 10


@dataclass(frozen=True)
class Observations:
    """Matched observations: catalog star id, measured rg, bg and their 1-sigma (arrays of one length)."""

    star_id: np.ndarray
    rg: np.ndarray
    bg: np.ndarray
    sigma_rg: np.ndarray
    sigma_bg: np.ndarray

    @classmethod
    def from_rows(cls, rows) -> Observations:
        """From ``(star_id, rg, bg, sigma_rg, sigma_bg)`` tuples."""
        a = np.asarray(list(rows), dtype=float).reshape(-1, 5)
        return cls(a[:, 0].astype(np.int64), a[:, 1], a[:, 2], a[:, 3], a[:, 4])

    def __len__(self) -> int:
        return len(self.star_id)

    def usable(self) -> np.ndarray:
        """Rows with finite positive ratios and finite positive sigmas."""
        vals = np.stack([self.rg, self.bg, self.sigma_rg, self.sigma_bg])
        return np.all(np.isfinite(vals) & (vals > 0), axis=0)


@dataclass(frozen=True)
class StarUpdate:
    """What one star's observations did: counts, catalog, learned and posterior 1-sigma values,
    and the change in posterior sigmas (``(learned - catalog) / sigma``)."""

    star_id: int
    row: int  #: row of the catalog's star table
    n_obs: int
    n_used: int
    n_rejected: int
    catalog: tuple[float, float]  #: (rg, bg)
    learned: tuple[float, float]
    sigma: tuple[float, float]  #: posterior 1-sigma; the prior's where unchanged
    shift_sigma: tuple[float, float]
    updated: bool
    note: str = ""  #: why a star with observations was not updated

    def to_dict(self) -> dict:
        return {
            "star_id": self.star_id,
            "n_obs": self.n_obs,
            "n_used": self.n_used,
            "n_rejected": self.n_rejected,
            "catalog_rg": self.catalog[0],
            "catalog_bg": self.catalog[1],
            "learned_rg": self.learned[0],
            "learned_bg": self.learned[1],
            "sigma_rg": self.sigma[0],
            "sigma_bg": self.sigma[1],
            "shift_sigma_rg": self.shift_sigma[0],
            "shift_sigma_bg": self.shift_sigma[1],
            "updated": self.updated,
            "note": self.note,
        }


@dataclass
class LearnedColours:
    """The catalog's colours after learning (``rg``, ``bg``: float32, catalog row order) and the
    report: one :class:`StarUpdate` per observed star, the run-wide ``sigma_scale``, and
    ``reason`` (one line) when nothing changed."""

    rg: np.ndarray
    bg: np.ndarray
    stars: list[StarUpdate] = field(default_factory=list)
    sigma_scale: float = 1.0
    n_observations: int = 0
    n_unknown_id: int = 0  #: observations of ids not in the catalog
    n_invalid: int = 0  #: observations without finite positive colours and sigmas
    reason: str | None = None

    @property
    def updated(self) -> list[StarUpdate]:
        return [s for s in self.stars if s.updated]

    def summary(self) -> dict:
        """The learned corrections against the catalog model: counts and the relative change."""
        up = self.updated
        out: dict = {
            "observations": self.n_observations,
            "unknown_ids": self.n_unknown_id,
            "invalid": self.n_invalid,
            "stars_observed": len(self.stars),
            "stars_updated": len(up),
            "observations_used": sum(s.n_used for s in up),
            "observations_rejected": sum(s.n_rejected for s in up),
            "sigma_scale": round(self.sigma_scale, 3),
        }
        if self.reason:
            out["unchanged"] = self.reason
        for k, name in enumerate(("rg", "bg")):
            if up:
                rel = np.array([s.learned[k] / s.catalog[k] - 1.0 for s in up])
                out[f"{name}_change_median_pct"] = round(100 * float(np.median(rel)), 2)
                out[f"{name}_change_rms_pct"] = round(100 * float(np.sqrt(np.mean(rel**2))), 2)
                out[f"{name}_beyond_3sigma"] = sum(abs(s.shift_sigma[k]) > 3 for s in up)
        return out


def observations_from_records(
    records, beta=None, statuses=("OK",), default_sigma: tuple[float, float] | None = None
) -> Observations:
    """The matched observations of solve records (``results.jsonl`` lines, ``solve --json``).

    Only records whose ``status`` is in ``statuses`` (default: high-confidence answers) count;
    a star counts when matched (``catalog_id``), not saturated and not on a planet. ``beta`` (the
    eq. 24 correction the matcher used) maps the raw ratios, and their sigmas to first order, into
    the space the catalog is compared in. Records written before the sigmas were logged take
    ``default_sigma`` (rg, bg), or their stars are left with NaN sigmas (counted as invalid).
    """
    rows = []
    for rec in records:
        if rec.get("status") not in statuses:
            continue
        for s in rec.get("stars") or []:
            if s.get("catalog_id") is None or s.get("saturated") or s.get("body"):
                continue
            sig = (s.get("rg_sigma"), s.get("bg_sigma"))
            if None in sig and default_sigma is not None:
                sig = default_sigma
            rows.append((s["catalog_id"], *(np.nan if v is None else v for v in (s.get("rg"), s.get("bg"), *sig))))
    obs = Observations.from_rows(rows)
    if beta is None or not len(obs):
        return obs
    b = np.asarray(beta, dtype=float)
    rg, bg = apply_colour_correction(obs.rg, obs.bg, b)
    srg = np.hypot(b[0] * obs.sigma_rg, b[1] * obs.sigma_bg)
    sbg = np.hypot(b[2] * obs.sigma_rg, b[3] * obs.sigma_bg)
    return Observations(obs.star_id, rg, bg, srg, sbg)


def _weighted_mean(x: np.ndarray, w: np.ndarray) -> float:
    return float(np.sum(w * x) / np.sum(w))


def _clip(xy: np.ndarray, sig: np.ndarray, clip: float, max_iter: int) -> np.ndarray:
    """Kept rows of one star's (n, 2) observations: iterative rejection about the data's weighted
    mean, started from the median."""
    centre = np.median(xy, axis=0)
    keep = np.zeros(len(xy), bool)
    for _ in range(max_iter):
        d = np.sqrt(np.sum(((xy - centre) / sig) ** 2, axis=1))
        new = d <= clip
        if not new.any():  # everything far from the median: keep the closest half
            new = d <= np.median(d)
        if np.array_equal(new, keep):
            break
        keep = new
        w = 1.0 / sig[keep] ** 2
        centre = np.array([_weighted_mean(xy[keep, k], w[:, k]) for k in range(2)])
    return keep


def _run_sigma_scale(groups: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """One factor for the run's observation sigmas: the robust spread of the normalised residuals
    about each star's median (1.4826 MAD), floored at 1 (measured sigmas are taken as lower bounds)."""
    z = [((xy - np.median(xy, axis=0)) / sig).ravel() for xy, sig in groups if len(xy) >= 3]
    if not z:
        return 1.0
    zz = np.concatenate(z)
    return max(1.0, 1.4826 * float(np.median(np.abs(zz))))


def learn_colours(
    catalog_id,
    catalog_rg,
    catalog_bg,
    obs: Observations,
    *,
    prior_rel: float = PRIOR_REL,
    clip: float = CLIP,
    min_obs: int = MIN_OBS,
    sigma_floor: float = SIGMA_FLOOR,
    sigma_scale: float | None = None,
    max_iter: int = MAX_ITER,
) -> LearnedColours:
    """Bayesian per-star update of the catalog colours (module docstring) from ``obs``.

    ``catalog_id``/``catalog_rg``/``catalog_bg`` are the catalog's star table; ``sigma_scale``
    None estimates it from the run. Raises ValueError for bad settings or arrays of unequal length.
    """
    ids = np.asarray(catalog_id, dtype=np.int64)
    crg, cbg = np.asarray(catalog_rg, float), np.asarray(catalog_bg, float)
    if not len(ids) == len(crg) == len(cbg):
        raise ValueError(f"catalog arrays differ in length: {len(ids)} ids, {len(crg)} rg, {len(cbg)} bg")
    cat = np.column_stack([crg, cbg])
    if not (prior_rel > 0 and clip > 0 and min_obs >= 1 and sigma_floor > 0 and max_iter >= 1):
        raise ValueError(
            f"need prior_rel > 0, clip > 0, min_obs >= 1, sigma_floor > 0, max_iter >= 1 "
            f"(got {prior_rel}, {clip}, {min_obs}, {sigma_floor}, {max_iter})"
        )
    if sigma_scale is not None and not sigma_scale > 0:
        raise ValueError(f"sigma_scale must be positive, got {sigma_scale}")
    out = LearnedColours(rg=cat[:, 0].astype(np.float32), bg=cat[:, 1].astype(np.float32), n_observations=len(obs))
    row_of = {int(s): k for k, s in enumerate(ids)}
    ok = obs.usable()
    out.n_invalid = int((~ok).sum())
    rows = np.array([row_of.get(int(s), -1) for s in obs.star_id], dtype=np.int64)
    out.n_unknown_id = int((ok & (rows < 0)).sum())
    ok &= rows >= 0
    xy_all = np.column_stack([obs.rg, obs.bg])
    sig_all = np.maximum(np.column_stack([obs.sigma_rg, obs.sigma_bg]), sigma_floor)
    groups = {int(r): np.flatnonzero(ok & (rows == r)) for r in np.unique(rows[ok])}
    if sigma_scale is None:
        sigma_scale = _run_sigma_scale([(xy_all[g], sig_all[g]) for g in groups.values()])
    out.sigma_scale = float(sigma_scale)
    for r, g in sorted(groups.items()):
        out.stars.append(
            _update_star(
                int(ids[r]), r, cat[r], xy_all[g], sig_all[g] * sigma_scale, prior_rel, clip, min_obs, max_iter
            )
        )
    for s in out.updated:
        out.rg[s.row], out.bg[s.row] = s.learned
    out.reason = _why_unchanged(out, len(obs), min_obs)
    return out


def _update_star(
    star_id: int,
    row: int,
    prior: np.ndarray,
    xy: np.ndarray,
    sig: np.ndarray,
    prior_rel: float,
    clip: float,
    min_obs: int,
    max_iter: int,
) -> StarUpdate:
    n = len(xy)
    prior_sd = prior_rel * prior
    catalog = (float(prior[0]), float(prior[1]))

    def unchanged(used: int, sd, note: str) -> StarUpdate:
        return StarUpdate(star_id, row, n, used, n - used, catalog, catalog, sd, (0.0, 0.0), False, note)

    if not np.isfinite(prior).all():
        return unchanged(0, (float("nan"), float("nan")), "no catalog colour (no prior)")
    keep = _clip(xy, sig, clip, max_iter) if n >= min_obs else np.ones(n, bool)
    used = int(keep.sum())
    if used < min_obs:
        return unchanged(
            used, (float(prior_sd[0]), float(prior_sd[1])), f"{used} usable observation(s), fewer than {min_obs}"
        )
    w = 1.0 / sig[keep] ** 2
    precision = 1.0 / prior_sd**2 + w.sum(axis=0)
    mean = (prior / prior_sd**2 + (w * xy[keep]).sum(axis=0)) / precision
    sd = 1.0 / np.sqrt(precision)
    learned = mean.astype(np.float32).astype(float)  # what the image stores
    shift = (learned - prior) / sd
    return StarUpdate(
        star_id,
        row,
        n,
        used,
        n - used,
        catalog,
        (float(learned[0]), float(learned[1])),
        (float(sd[0]), float(sd[1])),
        (float(shift[0]), float(shift[1])),
        True,
    )


def _why_unchanged(out: LearnedColours, n_obs: int, min_obs: int) -> str | None:
    if out.updated:
        return None
    if n_obs == 0:
        return "no matched observations: catalog colours unchanged"
    usable = n_obs - out.n_invalid - out.n_unknown_id
    if not out.stars:
        return f"none of {n_obs} observations usable ({out.n_invalid} without colours, {out.n_unknown_id} not in the catalog): catalog colours unchanged"
    most = max(s.n_used for s in out.stars)
    return (
        f"no star has {min_obs} usable observations ({usable} over {len(out.stars)} stars, at most {most} per star): "
        "catalog colours unchanged"
    )


def learn_image(image: bytes, obs: Observations, **kw) -> tuple[LearnedColours, bytes | None]:
    """Learn from ``obs`` against the catalog image ``image`` (keyword settings of
    :func:`learn_colours`); the re-signed image with the learned colours, or None when nothing changed
    (``CatalogImageError`` for an image that is not valid)."""
    img = parse_image(image)
    learned = learn_colours(img.stars["star_id"], img.stars["rg"], img.stars["bg"], obs, **kw)
    if learned.reason is not None:
        return learned, None
    return learned, with_star_colours(image, learned.rg, learned.bg)


def plot_learned(learned: LearnedColours, path, title: str = "") -> None:
    """PNG of learned against catalog rg and bg (posterior 1-sigma bars) for the updated stars."""
    from ground.atomic_write import save_figure
    from ground.optional import pyplot

    plt = pyplot()
    up = learned.updated
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    for k, (ax, name) in enumerate(zip(axes, ("rg", "bg"))):
        cat = np.array([s.catalog[k] for s in up])
        new = np.array([s.learned[k] for s in up])
        sd = np.array([s.sigma[k] for s in up])
        ax.errorbar(cat, new, yerr=sd, fmt="o", ms=3, lw=0.8)
        if len(cat):
            lo, hi = min(cat.min(), new.min()), max(cat.max(), new.max())
            ax.plot([lo, hi], [lo, hi], "k--", lw=0.8, label="catalog = learned")
            ax.legend(loc="upper left")
        ax.set_xlabel(f"catalog {name}")
        ax.set_ylabel(f"learned {name}")
        ax.grid(True, alpha=0.3)
    fig.suptitle(title or f"Learned colours of {len(up)} stars")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
