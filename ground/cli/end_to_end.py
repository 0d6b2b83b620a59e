"""The end-to-end demo (README's first command): a real device process on a pty, a catalog
built from the bundled Hipparcos data and uploaded over the link, raw frames rendered at known
attitudes, lost-in-space solves commanded over the link, and a table of the results.

Everything it writes (catalog image, frames with truth, results log, summary, plots) goes to
the output folder it names; the device's state directory is a temporary folder.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.image_io import catalog_to_image
from ground.analysis.replay import replay
from ground.atomic_write import write_bytes
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.link_solver import LinkSolver
from ground.sim.device_process import pick_attitudes, start_device, stop_device
from ground.sim.frame_writer import write_rendered
from ground.sim.sensor_sim import DetectorModel, render_frame
from ground.sim.sky_model import sky_stars
from protocol.commands import Slot

DEMO_EPOCH = "2026-01-01T00:00:00Z"  #: the demo frames' timestamp


def run_demo(out, n_frames: int = 6, seed: int = 2026, progress: bool = True) -> dict:
    """Run the demo, its steps said on stdout as they end; the results (:func:`print_demo` prints
    them for a reader, ``--json`` as they are)."""
    from ground.link.client import Client

    out = Path(out).resolve()
    if out.exists() and any(out.iterdir()):  # a fresh folder per run: runs never mix
        out = out / time.strftime("run-%Y%m%dT%H%M%SZ", time.gmtime())
    frames_dir = out / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    print(f"st16 demo: output folder {out}", flush=True)
    t0 = time.perf_counter()
    design = CatalogDesign()
    catalog = build_catalog(design)
    image = catalog_to_image(catalog)
    write_bytes(out / "catalog.st16cat", image)
    print(
        f"catalog: Hipparcos V <= {design.m_thresh}, theta_FOV {design.theta_fov_deg} deg: {catalog.n_stars} stars, "
        f"{catalog.n_pairs} pairs, {len(image)} bytes, built in {time.perf_counter() - t0:.1f} s",
        flush=True,
    )

    camera = CameraModel.reference_design()
    rng = np.random.default_rng(seed)
    stars = sky_stars()
    n_mono = max(1, n_frames // 3) if n_frames >= 2 else 0
    # the frames' time: the device checks the Sun and the Moon at it, so the attitudes keep clear of them
    for k, a in enumerate(pick_attitudes(catalog, camera, n_frames, rng, epoch=DEMO_EPOCH)):
        pattern = "MONO" if k >= n_frames - n_mono else "RGGB"
        rendered = render_frame(stars, a, camera, DetectorModel(pattern=pattern), seed=seed + k, timestamp=DEMO_EPOCH)
        write_rendered(rendered, frames_dir / f"frame_{k:02d}_{pattern.lower()}.dng")
    print(
        f"frames: {n_frames} rendered at known attitudes ({n_frames - n_mono} colour RGGB, {n_mono} mono), "
        f"sky to V {6.5}, in {frames_dir}",
        flush=True,
    )

    with tempfile.TemporaryDirectory(prefix="st16-state-") as state:
        proc, pty = start_device(Path(state))
        print(f"device: st16-device --pty on {pty} (state in {state})", flush=True)
        try:
            with Client(pty) as client:
                print(f"  {client.ping()}", flush=True)
                client.init()
                print(f"  {client.ping()}", flush=True)
                report = client.upload(Slot.CATALOG, image, progress=progress)
                info = client.slot_info(Slot.CATALOG)
                print(
                    f"catalog uploaded: {report.sent} bytes, device CRC-32 0x{info.crc32:08X} "
                    f"({'verified' if info.active else 'NOT ACTIVE'})",
                    flush=True,
                )
            solver = LinkSolver(pty)
            try:
                summary = replay(frames_dir, solver, out, progress=progress)
            finally:
                solver.close()
        finally:
            stop_device(proc)

    from ground.analysis.results_log import ResultsLog

    counts = summary["counts"]
    return {
        "output": str(out),
        "frames": summary["frames"],
        "counts": {k: counts.get(k, 0) for k in ("correct", "wrong", "no_match")} | counts,
        "results": [
            {
                "frame": rec["frame"],
                "method": rec.get("method"),
                "status": rec.get("status", rec["outcome"]),
                "matched": rec.get("n_matched", 0),
                "error_arcsec": None if rec.get("attitude_error_deg") is None else rec["attitude_error_deg"] * 3600,
                "device_ms": (rec.get("solve_s") or 0) * 1e3,
                "exchange_s": rec.get("exchange_s", 0),
            }
            for rec in ResultsLog(out).records()
        ],
        "written": {
            "catalog": str(out / "catalog.st16cat"),
            "frames": str(frames_dir),
            "log": str(out / "results.jsonl"),
            "summary": str(out / "summary.json"),
            "plots": list(summary["plots"]),
        },
    }


#: The demo's summary line when there are no plots: the core install leaves out matplotlib.
NO_PLOTS = "plots skipped (matplotlib not installed: pip install 'colour-st16[plots]')"


def print_demo(result: dict) -> None:
    """The demo's answer for a reader: a table of the frames and the summary line (.ci/run reads
    its start, ``N of N frames solved correctly (wrong 0, no match 0)``)."""
    print()
    print(
        f"{'frame':<22}{'method':<11}{'status':<16}{'matched':>8}{'error (arcsec)':>16}{'device (ms)':>13}"
        f"{'exchange (s)':>14}"
    )
    for row in result["results"]:
        err = row["error_arcsec"]
        print(
            f"{row['frame']:<22}{row['method'] or '-':<11}{row['status']:<16}"
            f"{row['matched']:>8}{'-' if err is None else f'{err:.2f}':>16}"
            f"{row['device_ms']:>13.1f}{row['exchange_s']:>14.2f}"
        )
    counts, written = result["counts"], result["written"]
    plots = written["plots"]
    print(
        f"\n{counts['correct']} of {result['frames']} frames solved correctly "
        f"(wrong {counts['wrong']}, no match {counts['no_match']}); log {written['log']}, "
        + (f"plots {', '.join(Path(p).name for p in plots)} in {result['output']}" if plots else NO_PLOTS)
    )


def demo_exit_code(result: dict) -> int:
    """0 when no frame was solved wrongly, else 1."""
    return 0 if result["counts"]["wrong"] == 0 else 1
