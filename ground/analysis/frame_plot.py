"""Overlay of detections (and optional truth) on a raw frame, as a PNG (matplotlib, Agg).

The raw CFA frame is shown as 2x2 super-pixel sums (colour-blind luminance) so the Bayer
mosaic does not dominate; axes are in raw pixel coordinates (docs/CONVENTIONS.md).
Detections are circles labelled by rank: green when trusted, orange when flagged. Truth
stars, when given, are small blue crosses. ``plot_identified`` labels the identified stars of a
solve with their catalog numbers, in colours and shapes colour-blind readers tell apart, the
labels placed clear of each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
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


def _show_frame(plt, frame: Frame, legend_rows: int = 0):
    """(figure, axes) with the frame as 2x2 super-pixel luminance, square-root stretched (and room
    for ``legend_rows`` rows of a legend below)."""
    sig = frame.signal()
    h2, w2 = frame.height // 2, frame.width // 2
    lum = sig[: 2 * h2, : 2 * w2].reshape(h2, 2, w2, 2).sum(axis=(1, 3))
    lo = float(np.median(lum))
    noise = 1.4826 * float(np.median(np.abs(lum - lo)))
    hi = max(float(np.percentile(lum, 99.99)), lo + 30.0 * max(noise, 1.0))
    fig, ax = plt.subplots(figsize=(12, 12 * frame.height / frame.width + 0.6 + 0.3 * legend_rows), dpi=110)
    ax.imshow(
        np.clip((lum - lo) / max(hi - lo, 1e-9), 0, 1) ** 0.5,
        cmap="gray",
        origin="upper",
        extent=(-0.5, 2 * w2 - 0.5, 2 * h2 - 0.5, -0.5),
        interpolation="nearest",
    )
    return fig, ax


#: Okabe & Ito's colour-blind-safe palette: identified stars sky blue, planets and the moon orange,
#: unmatched detections grey; the shapes differ too (circle, diamond, small circle).
IDENTIFIED_COLOUR = "#56B4E9"
PLANET_COLOUR = "#E69F00"
UNMATCHED_COLOUR = "#BBBBBB"
MARKER_PT = {"identified": 15.0, "planet": 15.0, "unmatched": 9.0}  #: marker diameters (points)
LABEL_RADII_PX = (6.0, 20.0, 40.0, 70.0)  #: label distances tried from a marker's edge (display px)
LABEL_ANGLES = (45, 135, -45, -135, 0, 180, 90, -90)  #: directions tried at each distance (deg, y up)


@dataclass
class Overlay:
    """What :func:`overlay_figure` drew: the counts its legend gives (those of the record's
    ``stars``) and each label's box in display pixels."""

    identified: int
    unmatched: int
    planets: int
    label_boxes: list = field(default_factory=list)
    legend: list[str] = field(default_factory=list)


def plot_identified(frame: Frame, record: dict, path, label: str = "HIP", title: str = "") -> Path:
    """The frame with each identified star circled and labelled ``label`` + its catalog number
    (``record``: a solve record, ``st16-ground solve --json``'s fields), unmatched detections as
    small grey circles and planets as orange diamonds named; labels placed clear of each other and
    of the markers (:func:`overlay_figure`); a legend with the counts of the record's ``stars``."""
    from ground.optional import pyplot

    plt = pyplot()
    fig, _, _ = overlay_figure(plt, frame, record, label, title)
    path = Path(path)
    save_figure(fig, path)
    plt.close(fig)
    return path


def overlay_figure(plt, frame: Frame, record: dict, label: str = "HIP", title: str = ""):
    """(figure, axes, :class:`Overlay`) of :func:`plot_identified`."""
    from matplotlib.lines import Line2D

    stars = [s for s in record.get("stars", []) if s["x"] is not None and s["y"] is not None]
    kinds: dict[str, list[dict]] = {"identified": [], "unmatched": [], "planet": []}
    for s in stars:
        kinds["planet" if s.get("body") else "identified" if s["catalog_id"] is not None else "unmatched"].append(s)
    fig, ax = _show_frame(plt, frame, legend_rows=1)
    ax.set_xlim(-0.5, frame.width - 0.5)
    ax.set_ylim(frame.height - 0.5, -0.5)
    ax.set_xlabel("x (column, px)")
    ax.set_ylabel("y (row, px)")
    style = {
        "identified": ("o", IDENTIFIED_COLOUR, 1.3),
        "planet": ("D", PLANET_COLOUR, 1.3),
        "unmatched": ("o", UNMATCHED_COLOUR, 1.1),
    }
    for kind, group in kinds.items():
        marker, colour, lw = style[kind]
        if group:
            ax.scatter(
                [s["x"] for s in group],
                [s["y"] for s in group],
                s=MARKER_PT[kind] ** 2,
                marker=marker,
                facecolors="none",
                edgecolors=colour,
                linewidths=lw,
                zorder=3,
            )
    ra, dec, roll = record.get("ra_deg"), record.get("dec_deg"), record.get("roll_deg")
    where = f"RA {ra:.4f} Dec {dec:+.4f} roll {roll:.2f} deg" if ra is not None else "no attitude"
    n_det = record.get("n_detected", len(stars))
    counts = f"{len(kinds['identified'])} of {n_det} detections identified"
    if len(record.get("stars", [])) < n_det:  # a device's result record: its brightest only
        counts += (
            f" (the result lists the {len(record['stars'])} brightest; {record.get('n_matched')} matched in the solve)"
        )
    ax.set_title(title or f"{record.get('status', '')}: {where}; {counts}", fontsize=9)
    legend = [
        f"identified ({label} n): {len(kinds['identified'])}",
        f"unmatched detections: {len(kinds['unmatched'])}",
        f"planets, moon: {len(kinds['planet'])}",
    ]
    handles = [
        Line2D([], [], ls="", marker=style[k][0], mfc="none", mec=style[k][1], mew=style[k][2], ms=MARKER_PT[k] * 0.7)
        for k in ("identified", "unmatched", "planet")
    ]
    fig.legend(handles, legend, loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.04, 1, 1))  # the layout is fixed before the labels are placed
    texts = [(s, f"{label} {s['catalog_id']}", IDENTIFIED_COLOUR, "identified") for s in kinds["identified"]]
    texts += [(s, str(s["body"]).capitalize(), PLANET_COLOUR, "planet") for s in kinds["planet"]]
    texts.sort(key=lambda t: -(t[0].get("flux") or 0.0))  # the brightest choose first
    markers = [(s["x"], s["y"], MARKER_PT[k]) for k, group in kinds.items() for s in group]
    boxes = _place_labels(fig, ax, texts, markers)
    return fig, ax, Overlay(len(kinds["identified"]), len(kinds["unmatched"]), len(kinds["planet"]), boxes, legend)


def _place_labels(fig, ax, texts, markers) -> list:
    """Greedy label placement: each label (brightest star first) takes the first of
    :data:`LABEL_RADII_PX` x :data:`LABEL_ANGLES` positions around its marker where its box stays
    inside the axes and meets no label placed before and no marker; failing that, the position
    meeting the fewest. A label away from its marker gets a thin leader line. Returns the boxes
    (display px)."""
    import matplotlib.patheffects as pe
    from matplotlib.transforms import Bbox

    renderer = fig.canvas.get_renderer()
    to_px = fig.dpi / 72.0
    frame_box = ax.get_window_extent(renderer)
    marker_boxes = []
    for x, y, size in markers:
        px, py = ax.transData.transform((x, y))
        r = size * to_px / 2
        marker_boxes.append(Bbox.from_extents(px - r, py - r, px + r, py + r))
    placed: list = []
    for star, text, colour, kind in texts:
        t = ax.text(
            0,
            0,
            text,
            color=colour,
            fontsize=7,
            ha="left",
            va="bottom",
            zorder=4,
            path_effects=[pe.withStroke(linewidth=2.2, foreground="black")],
        )
        w, h = t.get_window_extent(renderer).size
        px, py = ax.transData.transform((star["x"], star["y"]))
        edge = MARKER_PT[kind] * to_px / 2
        best = None
        for ri, radius in enumerate(LABEL_RADII_PX):
            for angle in LABEL_ANGLES:
                cos, sin = np.cos(np.radians(angle)), np.sin(np.radians(angle))
                ax_, ay_ = px + (edge + radius) * cos, py + (edge + radius) * sin
                x0 = ax_ - w / 2 + np.sign(round(cos, 6)) * w / 2  # the box on the far side of its anchor
                y0 = ay_ - h / 2 + np.sign(round(sin, 6)) * h / 2
                box = Bbox.from_bounds(x0, y0, w, h)
                inside = frame_box.containsx(x0) and frame_box.containsx(x0 + w)
                inside = inside and frame_box.containsy(y0) and frame_box.containsy(y0 + h)
                hits = sum(box.overlaps(b) for b in placed) * 100 + sum(box.overlaps(b) for b in marker_boxes)
                cost = (not inside, hits, ri)
                if best is None or cost < best[0]:
                    best = (cost, box, radius)
            if best is not None and best[0][:2] == (False, 0):
                break
        assert best is not None
        _, box, radius = best
        t.set_position(ax.transData.inverted().transform((box.x0, box.y0)))
        placed.append(box)
        if radius > LABEL_RADII_PX[0]:  # a leader line from the marker's edge to the label
            cx, cy = np.clip(px, box.x0, box.x1), np.clip(py, box.y0, box.y1)
            d = np.hypot(cx - px, cy - py)
            sx, sy = px + (cx - px) * edge / d, py + (cy - py) * edge / d
            (x1, y1), (x2, y2) = ax.transData.inverted().transform([(sx, sy), (cx, cy)])
            ax.plot([x1, x2], [y1, y2], color=colour, lw=0.6, alpha=0.8, zorder=3)
    return placed
