"""Overlay of detections (and optional truth) on a raw frame, as a PNG (matplotlib, Agg).

The raw CFA frame is shown as 2x2 super-pixel sums (colour-blind luminance) so the Bayer
mosaic does not dominate; axes are in raw pixel coordinates (docs/CONVENTIONS.md).
Detections are circles labelled by rank: green when trusted, orange when flagged. Truth
stars, when given, are small blue crosses. ``plot_identified`` labels the identified stars of a
solve with their catalog numbers.
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

    fig, ax = _show_frame(plt, frame)
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


def _show_frame(plt, frame: Frame):
    """(figure, axes) with the frame as 2x2 super-pixel luminance, square-root stretched."""
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
    return fig, ax


def plot_identified(frame: Frame, record: dict, path, label: str = "HIP", title: str = "") -> Path:
    """The frame with each identified star circled and labelled ``label`` + its catalog number
    (``record``: a solve record, ``st16-ground solve --json``'s fields); unmatched detections
    are small grey circles."""
    from ground.optional import pyplot

    plt = pyplot()
    fig, ax = _show_frame(plt, frame)
    for s in record.get("stars", []):
        if s["x"] is None or s["y"] is None:
            continue
        if s["catalog_id"] is None:
            ax.add_patch(plt.Circle((s["x"], s["y"]), 8, fill=False, color="grey", lw=0.6))
            continue
        ax.add_patch(plt.Circle((s["x"], s["y"]), 14, fill=False, color="lime", lw=1.0))
        below, left = s["y"] < 30, s["x"] > frame.width - 120  # keep the label inside the frame
        ax.annotate(
            f"{label} {s['catalog_id']}",
            (s["x"] + (-16 if left else 16), s["y"] + (24 if below else -16)),
            color="lime",
            fontsize=7,
            ha="right" if left else "left",
        )
    ax.set_xlim(-0.5, frame.width - 0.5)
    ax.set_ylim(frame.height - 0.5, -0.5)
    ax.set_xlabel("x (column, px)")
    ax.set_ylabel("y (row, px)")
    ra, dec, roll = record.get("ra_deg"), record.get("dec_deg"), record.get("roll_deg")
    where = f"RA {ra:.4f} Dec {dec:+.4f} roll {roll:.2f} deg" if ra is not None else "no attitude"
    matched = sum(s["catalog_id"] is not None for s in record.get("stars", []))
    ax.set_title(title or f"{record.get('status', '')}: {where}; {matched} identified stars", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path)
    plt.close(fig)
    return path
