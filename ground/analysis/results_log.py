"""Solve results: append-only JSONL and CSV logs, run summaries, and their plots.

A record is a flat-ish dict (see ``docs/ground.md``): ``frame``, ``status``, ``outcome``
(``correct`` / ``wrong`` / ``no_match`` / ``unscored`` / ``unreadable`` / ``link_error``),
``q_icrs_to_sensor`` ([w, x, y, z]), ``ra_deg``, ``dec_deg``, ``roll_deg``, counts, per-stage
timings and, when truth is known, ``attitude_error_deg``. Each append is flushed and fsynced,
so a crash or a dead link never loses a logged result.
"""

from __future__ import annotations

import csv
import json
import logging
import os
from pathlib import Path

import numpy as np

from ground import json_text
from ground.atomic_write import save_figure

log = logging.getLogger(__name__)

CSV_FIELDS = (
    "time_utc",
    "frame",
    "method",
    "status",
    "outcome",
    "ra_deg",
    "dec_deg",
    "roll_deg",
    "qw",
    "qx",
    "qy",
    "qz",
    "n_detected",
    "n_matched",
    "confidence",
    "attitude_error_deg",
    "wrong_ids",
    "solve_s",
    "exchange_s",
    "reason",
)

#: Outcomes that count as an attitude returned by the solver.
SOLVED = ("correct", "wrong", "unscored")


class ResultsLog:
    """``results.jsonl`` and ``results.csv`` in ``directory``, appended one record at a time."""

    def __init__(self, directory):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.jsonl_path = self.directory / "results.jsonl"
        self.csv_path = self.directory / "results.csv"

    def append(self, record: dict) -> None:
        cut = False
        if self.jsonl_path.exists() and self.jsonl_path.stat().st_size:
            with open(self.jsonl_path, "rb") as fh:
                fh.seek(-1, os.SEEK_END)
                cut = fh.read(1) != b"\n"
        with open(self.jsonl_path, "a", encoding="utf-8") as fh:
            fh.write(("\n" if cut else "") + json_text.dumps(record) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        new = not self.csv_path.exists()
        with open(self.csv_path, "a", newline="", encoding="utf-8") as fh:
            writer = csv.DictWriter(fh, fieldnames=CSV_FIELDS, extrasaction="ignore")
            if new:
                writer.writeheader()
            writer.writerow(_csv_row(record))
            fh.flush()
            os.fsync(fh.fileno())
        log.debug("%s: %s logged", self.jsonl_path, record.get("frame", "a record"))

    def records(self) -> list[dict]:
        """The logged records; a line cut short (a crash or a full disk mid-write) is left out with a
        warning (the next append after it starts on a line of its own)."""
        if not self.jsonl_path.exists():
            return []
        lines = [
            line for line in self.jsonl_path.read_text(encoding="utf-8", errors="replace").splitlines() if line.strip()
        ]
        out = []
        for k, line in enumerate(lines):
            try:
                out.append(json.loads(line))
            except ValueError:
                log.warning("st16-ground: %s: line %d cut short; left out", self.jsonl_path, k + 1)
        return out


def _csv_row(record: dict) -> dict:
    row = {k: record.get(k, "") for k in CSV_FIELDS}
    q = record.get("q_icrs_to_sensor")
    if q is not None:
        row.update(qw=q[0], qx=q[1], qy=q[2], qz=q[3])
    timings = record.get("timings_s") or {}
    row["solve_s"] = record.get("solve_s", sum(timings.values()) if timings else "")
    return row


def summarize(records: list[dict]) -> dict:
    """Counts per outcome and attitude-error statistics (degrees) over scored solves."""
    outcomes = [r.get("outcome", "unscored") for r in records]
    counts = {k: outcomes.count(k) for k in sorted(set(outcomes))}
    errors = np.array(
        [
            r["attitude_error_deg"]
            for r in records
            if r.get("outcome") in ("correct", "wrong") and r.get("attitude_error_deg") is not None
        ]
    )
    statuses = [r.get("status", "?") for r in records]
    summary = {
        "frames": len(records),
        "counts": counts,
        "status": {k: statuses.count(k) for k in sorted(set(statuses))},
    }
    scored = counts.get("correct", 0) + counts.get("wrong", 0) + counts.get("no_match", 0)
    if scored:
        summary["success_rate"] = counts.get("correct", 0) / scored
        summary["wrong_rate"] = counts.get("wrong", 0) / scored
        summary["no_match_rate"] = counts.get("no_match", 0) / scored
    if len(errors):
        summary["attitude_error_deg"] = {
            "median": float(np.median(errors)),
            "p90": float(np.percentile(errors, 90)),
            "max": float(errors.max()),
            "within_0.01deg": float(np.mean(errors <= 0.01)),
        }
    times = np.array([r["solve_s"] for r in records if isinstance(r.get("solve_s"), (int, float))])
    if len(times):
        summary["solve_s"] = {
            "median": float(np.median(times)),
            "p95": float(np.percentile(times, 95)),
            "max": float(times.max()),
        }
    return summary


def plot_summary(records: list[dict], out_dir) -> list[Path]:
    """Error CDF and per-star residual histogram PNGs; returns the paths written."""
    from ground.optional import pyplot

    plt = pyplot()

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    errors = np.sort([r["attitude_error_deg"] for r in records if r.get("attitude_error_deg") is not None])
    if len(errors):
        fig, ax = plt.subplots(figsize=(6, 4))
        arcsec = np.maximum(errors * 3600.0, 1e-3)
        ax.step(arcsec, np.arange(1, len(arcsec) + 1) / len(arcsec), where="post")
        ax.set_xscale("log")
        ax.set_xlabel("attitude error (arcsec)")
        ax.set_ylabel("fraction of solves")
        ax.set_title(f"Attitude error CDF ({len(errors)} scored solves)")
        ax.grid(True, which="both", alpha=0.3)
        path = out_dir / "error_cdf.png"
        fig.tight_layout()
        save_figure(fig, path, dpi=120)
        plt.close(fig)
        written.append(path)
    residuals = [res for r in records for res in (r.get("residuals_arcsec") or [])]
    if residuals:
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.hist(residuals, bins=40)
        ax.set_xlabel("per-star residual after attitude fit (arcsec)")
        ax.set_ylabel("stars")
        ax.set_title(f"Star residuals ({len(residuals)} stars)")
        path = out_dir / "residuals.png"
        fig.tight_layout()
        save_figure(fig, path, dpi=120)
        plt.close(fig)
        written.append(path)
    return written
