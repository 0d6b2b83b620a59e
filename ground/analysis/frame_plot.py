"""Overlay of detections (and optional truth) on a raw frame, as a PNG (matplotlib, Agg).

The raw CFA frame is shown as 2x2 super-pixel sums (colour-blind luminance) so the Bayer
mosaic does not dominate; axes are in raw pixel coordinates (docs/CONVENTIONS.md).
Detections are circles labelled by rank: green when trusted, orange when flagged. Truth
stars, when given, are small blue crosses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from firmware_model.pipeline.extract import StarList
from firmware_model.pipeline.raw_frame import Frame
from ground.atomic_write import save_figure


def plot_detections(frame: Frame, stars: StarList, path, truth: dict | None = None, title: str = "") -> Path:
    from ground.optional import pyplot

    plt = pyplot()

    sig = frame.signal()
    h2, w2 = frame.height // 2, frame.width // 2
    lum = sig[: 2 * h2, : 2 * w2].reshape(h2, 2, w2, 2).sum(axis=(1, 3))
    lo = float(np.median(lum))
    noise = 1.4826 * float(np.median(np.abs(lum - lo)))
    hi = max(float(np.percentile(lum, 99.99)), lo + 30.0 * max(noise, 1.0))
    fig, ax = plt.subplots(figsize=(12, 12 * frame.height / frame.width + 0.6), dpi=110)
    ax.imshow(
        np.clip((lum - lo) / max(hi - lo, 1e-9), 0, 1) ** 0.5,
        cmap="gray",
        origin="upper",
        extent=(-0.5, 2 * w2 - 0.5, 2 * h2 - 0.5, -0.5),
        interpolation="nearest",
    )
    trusted = stars.trusted
    for i in range(len(stars)):
        colour = "lime" if trusted[i] else "orange"
        ax.add_patch(plt.Circle((stars.x[i], stars.y[i]), 12, fill=False, color=colour, lw=0.8))
        label = f"{i}" if np.isnan(stars.rg[i]) else f"{i} ({stars.rg[i]:.2f},{stars.bg[i]:.2f})"
        ax.annotate(label, (stars.x[i] + 14, stars.y[i] - 14), color=colour, fontsize=6)
    if truth:
        tx = [s["x"] for s in truth.get("stars", [])]
        ty = [s["y"] for s in truth.get("stars", [])]
        ax.plot(tx, ty, "+", color="deepskyblue", ms=6, mew=0.8, label="truth")
        ax.legend(loc="upper right", fontsize=7)
    ax.set_xlim(-0.5, frame.width - 0.5)
    ax.set_ylim(frame.height - 0.5, -0.5)
    ax.set_xlabel("x (column, px)")
    ax.set_ylabel("y (row, px)")
    ax.set_title(
        title
        or f"{len(stars)} detections ({int(trusted.sum())} trusted), pattern {frame.pattern}; labels: rank (rg, bg)",
        fontsize=9,
    )
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path)
    plt.close(fig)
    return path
