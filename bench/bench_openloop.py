"""Open-loop validation bench: frames rendered with optics, detector, sky and
star colours the solver does NOT assume, solved with only what a user has.

Rendering: the real sky (Hipparcos to V 6.5) through ``ground.sim.sensor_sim.render_frame`` with the
impairment models of ``ground.sim.openloop``, one axis per cell, then all together (docs/openloop.md
lists every cell's exact parameters). Solving: the public ``run_pipeline(frame, nominal_camera,
catalog)`` with default ``PipelineParams()``, the datasheet camera
(``CameraModel.reference_design()``, distortion-free) and the default catalog (V <= 5); the
frame carries no camera. Frames alternate RGGB (even index) and MONO (odd index).

    .venv/bin/python bench/bench_openloop.py [--frames 20] [--workers 1] [--seed 9300]
        [--cells moffat,coma] [--out out/bench_openloop] [--figure docs/figures/openloop.png]
    .venv/bin/python bench/bench_openloop.py --from-json out/bench_openloop/rows.json   # table + figure only
    .venv/bin/python bench/bench_openloop.py --blind --figure ''   # no camera: the field of view searched
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: Cells in print order: name -> one-line description (docs/openloop.md has the detail).
CELLS = {
    "baseline": "closed loop: Gaussian sigma 1 px, nominal camera (control)",
    "moffat": "Moffat PSF, beta U[2.5, 4], FWHM U[1.8, 3.5] px",
    "donut": "defocus annulus r_out U[2, 4] px, r_in 0.5 r_out, blur sigma 0.5 px",
    "coma": "Gaussian sigma 1 px + coma C U[0.5, 1.5] px at the corner, linear in field radius",
    "sigma_0.4": "Gaussian sigma 0.4 px (undersampled)",
    "sigma_3": "Gaussian sigma 3 px",
    "focal_-3%": "true f = 0.97 f_nominal",
    "focal_+3%": "true f = 1.03 f_nominal",
    "division": "division-model distortion, corner shift +-5 px (sign random)",
    "equisolid": "pinhole/equisolid blend, corner shift -5 px (barrel)",
    "pp_offset": "principal point offset 20 px, random direction",
    "defects": "20 hot-pixel clusters (2x2/3x3, 100-3000 e-/px) + 3 bad columns (stuck, dead, +300 DN)",
    "sky_gradient": "sky ramp from 1 to U[30, 300] e-/px (10 to 300-3000 e-/s), random direction",
    "streaks": "one long (300-2000 px, 30-500 e-/px) and one short (20-60 px, 500-3000 e-/px) trail",
    "planets_false": "1 planet V U[-2.5, 1.5] + 5 false stars V U[3, 6], random colours",
    "missed_stars": "U[10, 20] % of the stars in view not rendered",
    "colour_blackbody": "star colours from a Planck spectrum at T(B-V) (Ballesteros) instead of the catalog model",
    "channel_gain": "per-channel gains g_r, g_g, g_b each 1 +- 0.05 (random sign)",
    "scintillation": "per-star log-normal flux jitter sigma 0.2",
    "geometry": "f U[-3, 3] % + distortion (division or equisolid, corner shift U[-5, 5] px) + pp offset U[0, 20] px",
    "all_but_geometry": "PSF one of Moffat/donut/coma + defects, sky gradient, streaks, planets and false stars, "
    "missed stars, blackbody colours, channel gains, scintillation",
    "all": "geometry + all_but_geometry at once",
}

#: Axes of the combined cells (the single cells are their own axis); the PSF model is drawn per frame.
GEOMETRY_AXES = {"f_any", "distortion_any", "pp_offset"}
SCENE_AXES = {
    "defects",
    "sky_gradient",
    "streaks",
    "planets_false",
    "missed_stars",
    "colour_blackbody",
    "channel_gain",
    "scintillation",
}


def _axes(cell: str, rng: np.random.Generator) -> set:
    if cell not in ("geometry", "all_but_geometry", "all"):
        return {cell}
    axes = set(GEOMETRY_AXES) if cell != "all_but_geometry" else set()
    if cell != "geometry":
        axes |= SCENE_AXES | {str(rng.choice(["moffat", "donut", "coma"]))}
    return axes


CATALOG_V = 5.0


def _uniform_dir(rng) -> tuple[float, float]:
    a = rng.uniform(0, 2 * np.pi)
    return float(np.cos(a)), float(np.sin(a))


def build_scene(cell: str, pattern: str, rng: np.random.Generator, nominal, det_electrons):
    """Impairments of one frame of ``cell``: (render kwargs, bad columns, star transforms, params)."""
    from ground.sim import openloop as ol
    from ground.sim.sensor_sim import DetectorModel

    axes = _axes(cell, rng)
    p: dict = {}
    det = DetectorModel(pattern=pattern)
    cam = nominal
    kw: dict = {}
    h, w = nominal.height, nominal.width
    if "sigma_0.4" in axes:
        det = DetectorModel(pattern=pattern, psf_sigma_px=0.4)
        p["psf"] = "gaussian sigma 0.4"
    if "sigma_3" in axes:
        det = DetectorModel(pattern=pattern, psf_sigma_px=3.0)
        p["psf"] = "gaussian sigma 3"
    # geometry first: the coma PSF needs the true principal point
    f_scale = {"focal_-3%": 0.97, "focal_+3%": 1.03}.get(cell, 1.0)
    if "f_any" in axes:
        f_scale = float(rng.uniform(0.97, 1.03))
    pp = (0.0, 0.0)
    if "pp_offset" in axes:
        d = _uniform_dir(rng)
        mag = 20.0 if cell == "pp_offset" else float(rng.uniform(0, 20))
        pp = (mag * d[0], mag * d[1])
    if f_scale != 1.0 or pp != (0.0, 0.0):
        cam = ol.true_camera(nominal, f_scale, pp)
        p.update(f_scale=f_scale, pp_offset_px=list(pp))
    model, shift = None, 0.0
    if "division" in axes:
        model, shift = "division", float(rng.choice([-5.0, 5.0]))
    if "equisolid" in axes:
        model, shift = "equisolid", -5.0
    if "distortion_any" in axes:
        model, shift = str(rng.choice(["division", "equisolid"])), float(rng.uniform(-5, 5))
    if model:
        cam = ol.RadialMappedCamera(cam, model, shift)
        p.update(distortion=model, corner_shift_px=shift)
    base = cam.base if model else cam
    if "moffat" in axes:
        kw["psf"] = ol.MoffatPSF(float(rng.uniform(1.8, 3.5)), float(rng.uniform(2.5, 4.0)))
    if "donut" in axes:
        r_out = float(rng.uniform(2.0, 4.0))
        kw["psf"] = ol.DonutPSF(r_out, 0.5 * r_out, 0.5)
    if "coma" in axes:
        kw["psf"] = ol.ComaPSF(1.0, float(rng.uniform(0.5, 1.5)), base.cx, base.cy, ol.corner_radius_px(base))
    if "psf" in kw:
        p["psf"] = kw["psf"].to_dict()
    extra = np.zeros((h, w)) if {"defects", "sky_gradient"} & axes else None
    columns = []
    if "defects" in axes:
        hot, where = ol.hot_clusters_e((h, w), 20, rng)
        extra += hot
        cols = rng.choice(w, size=3, replace=False)
        columns = [(int(c), k) for c, k in zip(cols, ("stuck", "dead", "hot"))]
        p.update(hot_clusters=where, bad_columns=columns)
    if "sky_gradient" in axes:
        hi = float(rng.uniform(30.0, 300.0))
        ang = float(rng.uniform(0, 2 * np.pi))
        extra += ol.sky_gradient_e((h, w), 0.0, hi - det.sky_e_per_s * det.exposure_s, ang)
        p.update(sky_hi_e=hi, sky_angle_rad=ang)
    if extra is not None:
        kw["extra_e"] = extra
    false = []
    if "streaks" in axes:
        x, y = rng.uniform(0, w), rng.uniform(0, h)
        ang, length = rng.uniform(0, 2 * np.pi), rng.uniform(300, 2000)
        false.append(ol.streak(x, y, x + length * np.cos(ang), y + length * np.sin(ang), rng.uniform(30, 500)))
        x, y = rng.uniform(50, w - 50), rng.uniform(50, h - 50)
        ang, length = rng.uniform(0, 2 * np.pi), rng.uniform(20, 60)
        false.append(
            ol.streak(
                x,
                y,
                x + length * np.cos(ang),
                y + length * np.sin(ang),
                rng.uniform(500, 3000),
                rng.uniform(0.6, 1.4),
                rng.uniform(0.4, 1.2),
            )
        )
    if "planets_false" in axes:
        false.append(
            ol.planet(
                rng.uniform(20, w - 20),
                rng.uniform(20, h - 20),
                det_electrons(rng.uniform(-2.5, 1.5)),
                rng.uniform(0.8, 1.6),
                rng.uniform(0.4, 1.0),
            )
        )
        for _ in range(5):
            false.append(
                ol.false_star(
                    rng.uniform(20, w - 20),
                    rng.uniform(20, h - 20),
                    det_electrons(rng.uniform(3, 6)),
                    rng.uniform(0.3, 1.6),
                    rng.uniform(0.2, 1.4),
                )
            )
    if false:
        kw["false_objects"] = false
        p["false_objects"] = [{k: v for k, v in vars(o).items() if v is not None} for o in false]
    if "channel_gain" in axes:
        g = tuple(float(1.0 + 0.05 * rng.choice([-1, 1])) for _ in range(3))
        kw["channel_gain"] = g
        p["channel_gain"] = list(g)
    stars_tf = {
        "drop": float(rng.uniform(0.10, 0.20)) if "missed_stars" in axes else 0.0,
        "scint": 0.2 if "scintillation" in axes else 0.0,
        "blackbody": "colour_blackbody" in axes,
    }
    p.update({k: v for k, v in stars_tf.items() if v})
    kw["detector"] = det
    kw["camera"] = cam
    return kw, columns, stars_tf, p


def _one(job):
    cell, k, seed, blind = job
    from dataclasses import replace

    from firmware_model.pipeline.run import run_pipeline
    from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat, quat_to_matrix, rotation_angle
    from ground.analysis.replay import MATCH_RADIUS_PX, Truth, score
    from ground.link.solve_report import record_from_output
    from ground.sim import openloop as ol
    from ground.sim.availability import reference_scene
    from ground.sim.sensor_sim import DetectorModel, render_frame

    cat, nominal, sky, cat_ids = reference_scene()
    cat_row = {int(i): n for n, i in enumerate(cat_ids)}
    pattern = "RGGB" if k % 2 == 0 else "MONO"
    cell_index = list(CELLS).index(cell)
    rng = np.random.default_rng([seed, cell_index, k])
    a = attitude_from_radec_roll(rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi))
    kw, columns, tf, params = build_scene(cell, pattern, rng, nominal, DetectorModel().green_electrons)
    src = _blackbody_sky() if tf["blackbody"] else sky
    stars = ol.stars_in_cone(src, a, nominal.fov_half_angle_diagonal + np.radians(1.0))
    if tf["drop"]:
        stars, dropped = ol.drop_stars(stars, tf["drop"], rng)
        params["n_dropped"] = int(len(dropped))
    if tf["scint"]:
        stars = ol.scintillate(stars, tf["scint"], rng)
    t0 = time.perf_counter()
    r = render_frame(stars, a, seed=int(rng.integers(2**31)), **kw)
    frame = r.frame
    if columns:
        frame = ol.apply_bad_columns(frame, columns)
    frame = replace(frame, camera=None)  # a user's frame does not carry the true lens
    t1 = time.perf_counter()
    if blind:  # no camera: the field of view searched over 5-60 deg, the same catalog
        from firmware_model.pipeline.sky_run import run_pipeline_sky
        from firmware_model.pipeline.sky_search import FieldRange
        from firmware_model.pipeline.solve_types import PipelineParams
        from ground.catalog.sky_database import sky_database

        db = sky_database()
        out, _ = run_pipeline_sky(
            frame, FieldRange.blind(), db.search, lambda camera: cat, PipelineParams(), patterns=db.index
        )
    else:
        out = run_pipeline(frame, nominal, cat)
    t2 = time.perf_counter()
    rec = record_from_output(out)
    ts = r.truth["stars"]
    ids = np.array([s["id"] for s in ts], dtype=np.int64)
    tx, ty = np.array([s["x"] for s in ts]), np.array([s["y"] for s in ts])
    a_ref = best_nominal_attitude(kw["camera"], nominal, a)
    truth = Truth(matrix_to_quat(a_ref), ids, tx, ty)
    in_cat = np.isin(ids, cat_ids)
    # stage diagnostics: catalog stars detected (within MATCH_RADIUS_PX) and their centroid / colour errors
    n_cat_det, cerr, rgerr = 0, [], []
    st = out.stars
    if st is not None and len(st) and in_cat.any():
        for i in np.flatnonzero(in_cat):
            d = np.hypot(st.x - tx[i], st.y - ty[i])
            j = int(np.argmin(d))
            if d[j] <= MATCH_RADIUS_PX:
                n_cat_det += 1
                cerr.append(float(d[j]))
                c = cat_row[ids[i]]
                if np.isfinite(st.rg[j]) and np.isfinite(cat.rg[c]):
                    rgerr.append(float(st.rg[j] / cat.rg[c] - 1.0))
    sol = out.solution
    return {
        "cell": cell,
        "k": k,
        "pattern": pattern,
        "status": rec["status"],
        "method": rec["method"],
        "reason": out.reason or (sol.reason if sol is not None else ""),
        "n_catalog_in_view": int(in_cat.sum()),
        "n_catalog_detected": n_cat_det,
        "n_detected": rec["n_detected"],
        "n_matched": rec["n_matched"],
        "centroid_err_px_median": float(np.median(cerr)) if cerr else None,
        "rg_rel_err_median": float(np.median(np.abs(rgerr))) if rgerr else None,
        "psf_sigma_used_px": float(getattr(st, "psf_sigma_px", np.nan)) if st is not None else None,
        "render_s": t1 - t0,
        "solve_s": t2 - t1,
        "params": params,
        "camera_bias_deg": float(np.degrees(rotation_angle(a_ref, a))),
        "attitude_error_truth_deg": (
            float(np.degrees(rotation_angle(quat_to_matrix(rec["q_icrs_to_sensor"]), a)))
            if rec["q_icrs_to_sensor"] is not None
            else None
        ),
        **score(rec, truth),
    }


def best_nominal_attitude(camera, nominal, a_true) -> np.ndarray:
    """The attitude a perfect solver using the nominal principal point would return. A
    principal-point offset is, to first order, a tilt of the boresight that no star pattern
    reveals: the nominal array centre ``(cx, cy)`` sees the true sensor direction ``d``, and the
    reference frame is the true one turned (no roll) so that ``d`` is +z. Other camera errors
    (focal length, distortion) are observable and count against the solver."""
    base = getattr(camera, "base", camera)
    if (base.cx, base.cy) == (nominal.cx, nominal.cy):
        return a_true
    d = np.array([(nominal.cx - base.cx) / base.f, (nominal.cy - base.cy) / base.f, 1.0])
    d /= np.linalg.norm(d)
    axis = np.cross(d, [0.0, 0.0, 1.0])
    s, c = np.linalg.norm(axis), d[2]
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]) / s
    rot = np.eye(3) + s * k + (1 - c) * k @ k  # Rodrigues: rot @ d = +z
    return rot @ a_true


_BB = None


def _blackbody_sky():
    global _BB
    if _BB is None:
        from ground.sim.openloop import blackbody_sky_stars

        _BB = blackbody_sky_stars()
    return _BB


def summarise(rows: list[dict], cells: list[str]) -> list[dict]:
    """One summary row per (cell, pattern) and per cell (pattern 'both')."""
    out = []
    for cell in cells:
        for pattern in ("RGGB", "MONO", "both"):
            rs = [r for r in rows if r["cell"] == cell and (pattern == "both" or r["pattern"] == pattern)]
            if not rs:
                continue
            elig = [r for r in rs if r["n_catalog_in_view"] >= 4]
            errs = np.array([r["attitude_error_truth_deg"] for r in rs if r["outcome"] == "correct"]) * 3600
            eref = np.array([r["attitude_error_deg"] for r in rs if r["outcome"] == "correct"]) * 3600
            hc = [r for r in rs if r["status"] == "OK"]
            out.append(
                {
                    "cell": cell,
                    "pattern": pattern,
                    "frames": len(rs),
                    "eligible": len(elig),
                    "correct": sum(r["outcome"] == "correct" for r in rs),
                    "wrong": sum(r["outcome"] == "wrong" for r in rs),
                    "no_solution": sum(r["outcome"] == "no_match" for r in rs),
                    "eligible_solved": sum(r["outcome"] == "correct" for r in elig),
                    "high_conf": len(hc),
                    "high_conf_wrong": sum(r["outcome"] == "wrong" for r in hc),
                    "err_p50_arcsec": float(np.median(errs)) if len(errs) else None,
                    "err_p90_arcsec": float(np.percentile(errs, 90)) if len(errs) else None,
                    "err_vs_nominal_p50_arcsec": float(np.median(eref)) if len(eref) else None,
                    "camera_bias_p50_arcsec": float(np.median([r["camera_bias_deg"] for r in rs]) * 3600),
                }
            )
    return out


def _fmt(v, spec=".1f") -> str:
    return "-" if v is None else format(v, spec)


def print_table(summary: list[dict], file=sys.stdout) -> None:
    """Rows per (cell, pattern); the target column judges the cell over both patterns."""
    print(
        f"{'cell':<17}{'pat':<5}{'frames':>7}{'>=4cat':>7}{'correct':>8}{'wrong':>6}{'no sol':>7}"
        f"{'solved/>=4':>11}{'HC':>4}{'HC wrong':>9}{'err p50':>9}{'p90':>8}{'vs nom':>8}{'bias':>7}  target",
        file=file,
    )
    for s in summary:
        if s["pattern"] == "both":
            continue
        rate = s["eligible_solved"] / s["eligible"] if s["eligible"] else float("nan")
        both = next(b for b in summary if b["cell"] == s["cell"] and b["pattern"] == "both")
        brate = both["eligible_solved"] / both["eligible"] if both["eligible"] else 1.0
        met = ("met" if brate >= 0.99 and both["high_conf_wrong"] == 0 else "MISSED") if s["pattern"] == "RGGB" else ""
        print(
            f"{s['cell']:<17}{s['pattern']:<5}{s['frames']:>7}{s['eligible']:>7}{s['correct']:>8}{s['wrong']:>6}"
            f"{s['no_solution']:>7}{rate:>11.0%}{s['high_conf']:>4}{s['high_conf_wrong']:>9}"
            f"{_fmt(s['err_p50_arcsec']):>9}{_fmt(s['err_p90_arcsec']):>8}{_fmt(s['err_vs_nominal_p50_arcsec']):>8}"
            f"{_fmt(s['camera_bias_p50_arcsec'], '.0f'):>7}  {met}",
            file=file,
        )
    print(
        "errors in arcsec over correct solves: 'err p50/p90' from the true attitude, 'vs nom' from the best "
        "attitude the nominal camera allows ('bias' = median angle between the two: the principal-point offset seen as a boresight tilt)",
        file=file,
    )


def plot(summary: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = list(dict.fromkeys(s["cell"] for s in summary))
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(12, 7), sharex=True)
    xs = np.arange(len(cells))
    for off, pattern, colour in ((-0.2, "RGGB", "tab:red"), (0.2, "MONO", "tab:gray")):
        rs = [next((s for s in summary if s["cell"] == c and s["pattern"] == pattern), None) for c in cells]
        rate = [s["eligible_solved"] / s["eligible"] * 100 if s and s["eligible"] else np.nan for s in rs]
        hcw = [s["high_conf_wrong"] if s else 0 for s in rs]
        ax1.bar(xs + off, rate, 0.4, color=colour, label=f"{pattern}: solved / frames with >= 4 catalog stars")
        for x, n in zip(xs + off, hcw):
            if n:
                ax1.text(x, 2, f"{n} HC\nwrong", ha="center", fontsize=7, color="k")
        p50 = [s["err_p50_arcsec"] if s and s["err_p50_arcsec"] is not None else np.nan for s in rs]
        p90 = [s["err_p90_arcsec"] if s and s["err_p90_arcsec"] is not None else np.nan for s in rs]
        ax2.plot(xs + off, p50, "o", color=colour, label=f"{pattern} p50")
        ax2.plot(xs + off, p90, "^", color=colour, mfc="none", label=f"{pattern} p90")
        nom = [
            s["err_vs_nominal_p50_arcsec"] if s and s["err_vs_nominal_p50_arcsec"] is not None else np.nan for s in rs
        ]
        ax2.plot(xs + off, nom, "x", color=colour, label=f"{pattern} p50 vs nominal-pp attitude")
    ax1.axhline(99, color="k", lw=0.8, ls="--")
    ax1.set_ylim(0, 105)
    ax1.set_ylabel("solved (%)")
    ax1.legend(fontsize=8, loc="lower left")
    ax2.set_yscale("log")
    ax2.set_ylim(0.3, 2e4)  # room for the legend above the principal-point cells
    ax2.set_ylabel("attitude error of correct solves (arcsec)")
    ax2.legend(fontsize=7, ncol=3)
    ax2.set_xticks(xs, cells, rotation=40, ha="right")
    fig.suptitle("Open-loop bench: rendering and solver models disagree (nominal camera, default catalog and params)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def _code_version() -> str:
    """``git describe --always --dirty`` of the working tree (the pipeline under test), or 'unknown'."""
    import subprocess

    try:
        return (
            subprocess.run(
                ["git", "describe", "--always", "--dirty"],
                capture_output=True,
                text=True,
                cwd=Path(__file__).resolve().parents[1],
                timeout=10,
            ).stdout.strip()
            or "unknown"
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="frames per cell (alternating RGGB / MONO)")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--seed", type=int, default=9300)
    ap.add_argument(
        "--blind",
        action="store_true",
        help="solve with no camera: the field of view searched over 5-60 deg against the whole-sky "
        "database (sky_run.run_pipeline_sky), the same catalog",
    )
    ap.add_argument(
        "--cells", default=",".join(CELLS), help="comma-separated subset of: " + ", ".join(CELLS).replace("%", "%%")
    )
    ap.add_argument("--out", default="out/bench_openloop")
    ap.add_argument("--figure", default="docs/figures/openloop.png", help="plot path ('' for none)")
    ap.add_argument("--from-json", help="reprint the table and redraw the figure from a rows.json; no run")
    args = ap.parse_args(argv)
    if args.from_json:
        data = json.loads(Path(args.from_json).read_text())
        print_table(data["summary"])
        if args.figure:
            plot(data["summary"], Path(args.figure))
        return 0
    cells = [c for c in args.cells.split(",") if c]
    unknown = set(cells) - set(CELLS)
    if unknown:
        ap.error(f"unknown cells {sorted(unknown)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(c, k, args.seed, args.blind) for c in cells for k in range(args.frames)]
    t0 = time.perf_counter()
    if args.workers <= 1:
        rows = []
        for i, job in enumerate(jobs):
            rows.append(_one(job))
            print(f"\r{i + 1}/{len(jobs)} {job[0]:<17}", end="", file=sys.stderr, flush=True)
        print(file=sys.stderr)
    else:
        with ProcessPoolExecutor(args.workers) as ex:
            rows = list(ex.map(_one, jobs, chunksize=2))
    summary = summarise(rows, cells)
    (out / "rows.json").write_text(
        json.dumps({"args": vars(args), "code": _code_version(), "frames": rows, "summary": summary}, indent=1)
    )
    print(
        f"Open-loop bench: {args.frames} frames per cell (even RGGB, odd MONO), seed {args.seed}; solver = "
        + (
            f"run_pipeline_sky(frame, FieldRange.blind(), sky database, catalog V <= {CATALOG_V:g}) "
            if args.blind
            else f"run_pipeline(frame, reference_design(), catalog V <= {CATALOG_V:g}) "
        )
        + "with default PipelineParams; "
        f"code {_code_version()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    )
    print_table(summary)
    print(
        "target per cell (both patterns): >= 99 % of frames with >= 4 catalog stars solved correctly and 0 "
        "high-confidence (HC) wrong"
    )
    print(f"wall {time.perf_counter() - t0:.0f} s; rows in {out / 'rows.json'}")
    if args.figure:
        plot(summary, Path(args.figure))
        print(f"figure {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
