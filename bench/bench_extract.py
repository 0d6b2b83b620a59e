"""Benchmark of the raw-frame pipeline against rendered truth (Enright & McVittie reference design).

Prints, and plots under ``--out``:

1. Accuracy versus V magnitude and versus SNR (colour and mono sensors): centroid RMS
   error (px, radial), colour-ratio RMS errors (rg, bg, absolute), the fit's own predicted
   errors, completeness; the centre-of-gravity method as the in-run baseline.
2. Detection completeness and false detections versus magnitude (false detections binned
   by the V magnitude equivalent to their fitted green amplitude).
3. Speed of detection + fit on full 2592 x 1944 frames with ~20 stars: median time per
   stage (wall clock) and the process CPU time of the whole extraction (less sensitive to
   other jobs on a shared machine), and the PSF fit with the analytic Jacobian against
   finite differences (baseline). BLAS/OpenMP threads are limited to one.

SNR is the physical signal-to-noise ratio of the whole star from the truth: the star's
electrons on all its pixels N (mean channel total over the CFA, (S_r + 2 S_g + S_b) / 4,
or the mono total) over sqrt(N + 4 pi sigma_psf^2 (read^2 + dark t + sky t)).

Run: ``.venv/bin/python bench/bench_extract.py [--frames 12] [--out out/bench]``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

# one core, as the target asks: BLAS threads would only contend on a shared machine
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from firmware_model.camera import CameraModel  # noqa: E402
from firmware_model.pipeline.centroid import FitParams, fit_stars  # noqa: E402
from firmware_model.pipeline.detect import detect_stars  # noqa: E402
from firmware_model.pipeline.extract import extract_stars  # noqa: E402
from firmware_model.reference_frames import attitude_from_radec_roll  # noqa: E402
from ground.sim.sensor_sim import DetectorModel, random_star_field, render_frame  # noqa: E402

SEED_CENTROID_PX = 0.2  # Enright & McVittie section 2.2: companion-paper figures
SEED_COLOUR_RMS = 0.05
MAG_BINS = np.arange(0.0, 8.01, 0.5)
SNR_BANDS = [(200, np.inf), (100, 200), (50, 100), (20, 50), (10, 20), (5, 10), (0, 5)]
MATCH_PX = 2.0


def star_snr(t: dict, det: DetectorModel) -> float:
    e = t["electrons"]
    n = e["mono"] if "mono" in e else (e["r"] + 2 * e["g"] + e["b"]) / 4.0
    var_pix = det.read_noise_e**2 + (det.dark_e_per_s + det.sky_e_per_s) * det.exposure_s
    return n / np.sqrt(n + 4 * np.pi * det.psf_sigma_px**2 * var_pix)


def run_accuracy(det: DetectorModel, cam: CameraModel, n_frames: int, label: str, seed0: int):
    """Per true star: vmag, snr, found, dx, dy, drg, dbg, pred sigma_x, sigma_rg, cog dx, dy, drg, dbg, flags;
    per false detection: equivalent V."""
    rows, false_v = [], []
    zp = det.green_electrons(0.0) / det.gain_e_per_dn  # DN of a V=0 green channel total
    for k in tqdm(range(n_frames), desc=f"accuracy {label}", unit="frame"):
        rng = np.random.default_rng(seed0 + k)
        att = attitude_from_radec_roll(rng.uniform(0, 2 * np.pi), rng.uniform(-1.3, 1.3), rng.uniform(0, 2 * np.pi))
        stars = random_star_field(cam, att, 30, vmag_range=(1.0, 7.5), seed=seed0 + k, min_separation_px=30)
        res = render_frame(stars, att, cam, det, seed=seed0 + 1000 + k)
        d = detect_stars(res.frame)
        lm = fit_stars(res.frame, d, FitParams(psf_sigma_px=det.psf_sigma_px))
        cog = fit_stars(res.frame, d, FitParams(psf_sigma_px=det.psf_sigma_px, method="cog"))
        tx = np.array([t["x"] for t in res.truth["stars"]])
        ty = np.array([t["y"] for t in res.truth["stars"]])
        dist = (
            np.hypot(tx[:, None] - lm.x[None, :], ty[:, None] - lm.y[None, :])
            if len(lm.x)
            else np.full((len(tx), 0), np.inf)
        )
        for i, t in enumerate(res.truth["stars"]):
            j = int(np.argmin(dist[i])) if dist.shape[1] else -1
            found = j >= 0 and dist[i, j] < MATCH_PX
            r = [t["vmag"], star_snr(t, det), found]
            if found:
                r += [
                    lm.x[j] - t["x"],
                    lm.y[j] - t["y"],
                    lm.rg[j] - t["rg"],
                    lm.bg[j] - t["bg"],
                    np.sqrt(lm.cov_xy[j, 0, 0] + lm.cov_xy[j, 1, 1]),
                    np.sqrt(lm.cov_colour[j, 0, 0]),
                    cog.x[j] - t["x"],
                    cog.y[j] - t["y"],
                    cog.rg[j] - t["rg"],
                    cog.bg[j] - t["bg"],
                    lm.flags[j],
                ]
            else:
                r += [np.nan] * 10 + [-1]
            rows.append(r)
        unmatched = np.all(dist >= MATCH_PX, axis=0) if dist.size else np.ones(len(lm.x), bool)
        g = lm.amp[unmatched, 1]
        false_v += list(-2.5 * np.log10(np.maximum(g, 1e-3) / zp))
    return np.array(rows, dtype=float), np.array(false_v)


def rms(a):
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a**2))) if len(a) else float("nan")


def table(rows: np.ndarray, key: str, bins, colour: bool, n_frames: int, false_v=None):
    """Rows of (label, n, completeness, centroid rms, pred, cog rms, rg rms, bg rms, pred rg, cog rg rms, false/frame)."""
    out = []
    for lo, hi in bins:
        col = 0 if key == "mag" else 1
        m = (rows[:, col] >= lo) & (rows[:, col] < hi)
        if not m.any():
            continue
        b = rows[m]
        f = b[b[:, 2] == 1]
        rec = {
            "bin": f"{lo:.1f}-{hi:.1f}" if key == "mag" else (f">{lo:.0f}" if np.isinf(hi) else f"{lo:.0f}-{hi:.0f}"),
            "n": int(m.sum()),
            "completeness": float(f.shape[0] / m.sum()),
            "snr_median": float(np.median(b[:, 1])),
            "centroid_rms": rms(np.hypot(f[:, 3], f[:, 4])),
            "centroid_pred": rms(f[:, 7]),
            "cog_centroid_rms": rms(np.hypot(f[:, 9], f[:, 10])),
        }
        if colour:
            rec.update(
                {
                    "rg_rms": rms(f[:, 5]),
                    "bg_rms": rms(f[:, 6]),
                    "rg_pred": rms(f[:, 8]),
                    "cog_rg_rms": rms(f[:, 11]),
                    "cog_bg_rms": rms(f[:, 12]),
                }
            )
        if false_v is not None:
            rec["false_per_frame"] = float(np.count_nonzero((false_v >= lo) & (false_v < hi)) / n_frames)
        out.append(rec)
    return out


def print_table(title: str, recs: list, colour: bool):
    print(f"\n{title}")
    head = f"{'bin':>9} {'n':>4} {'compl':>6} {'SNR':>7} {'cent':>6} {'pred':>6} {'CoG':>6}"
    if colour:
        head += f" {'rg':>6} {'bg':>6} {'pred':>6} {'CoGrg':>6}"
    if recs and "false_per_frame" in recs[0]:
        head += f" {'false/fr':>8}"
    print(head)
    for r in recs:
        line = (
            f"{r['bin']:>9} {r['n']:>4} {r['completeness']:6.3f} {r['snr_median']:7.1f} {r['centroid_rms']:6.3f} "
            f"{r['centroid_pred']:6.3f} {r['cog_centroid_rms']:6.3f}"
        )
        if colour:
            line += f" {r['rg_rms']:6.3f} {r['bg_rms']:6.3f} {r['rg_pred']:6.3f} {r['cog_rg_rms']:6.3f}"
        if "false_per_frame" in r:
            line += f" {r['false_per_frame']:8.3f}"
        print(line)


def run_speed(cam: CameraModel, n_frames: int, repeats: int):
    det = DetectorModel()
    stages, jac_ratio, cpu = {"detect_s": [], "fit_s": [], "vectors_s": [], "total_s": []}, [], []
    n_stars = []
    for k in tqdm(range(n_frames), desc="speed", unit="frame"):
        att = attitude_from_radec_roll(0.3 * k, 0.2, 0.0)
        stars = random_star_field(cam, att, 20, vmag_range=(2.0, 6.0), seed=500 + k, min_separation_px=30)
        frame = render_frame(stars, att, cam, det, seed=600 + k).frame
        for _ in range(repeats):
            c0 = time.process_time()
            s = extract_stars(frame, cam)
            cpu.append(time.process_time() - c0)
            for key in stages:
                stages[key].append(s.timings[key])
        n_stars.append(len(s))
        d = detect_stars(frame)
        t0 = time.perf_counter()
        fit_stars(frame, d, FitParams(analytic_jacobian=True))
        t1 = time.perf_counter()
        fit_stars(frame, d, FitParams(analytic_jacobian=False))
        t2 = time.perf_counter()
        jac_ratio.append((t2 - t1) / (t1 - t0))
    med = {k: float(np.median(v)) for k, v in stages.items()}
    med["cpu_total_s"] = float(np.median(cpu))
    return (
        med,
        {k: float(np.percentile(v, 90)) for k, v in stages.items()},
        float(np.median(jac_ratio)),
        float(np.mean(n_stars)),
    )


def plot(results: dict, out: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    for name, style in (("colour", "o-"), ("mono", "s--")):
        recs = results[name]["by_mag"]
        mid = [float(r["bin"].split("-")[0]) + 0.25 for r in recs]
        axes[0, 0].semilogy(mid, [r["centroid_rms"] for r in recs], style, label=f"{name} PSF fit")
        axes[0, 0].semilogy(mid, [r["cog_centroid_rms"] for r in recs], style, alpha=0.4, label=f"{name} CoG")
        axes[1, 0].plot(mid, [r["completeness"] for r in recs], style, label=f"{name} completeness")
        axes[1, 0].plot(
            mid, [r.get("false_per_frame", 0) for r in recs], style, alpha=0.5, label=f"{name} false / frame"
        )
    recs = results["colour"]["by_mag"]
    mid = [float(r["bin"].split("-")[0]) + 0.25 for r in recs]
    axes[0, 1].semilogy(mid, [r["rg_rms"] for r in recs], "o-", label="rg RMS")
    axes[0, 1].semilogy(mid, [r["bg_rms"] for r in recs], "^-", label="bg RMS")
    axes[0, 1].semilogy(mid, [r["rg_pred"] for r in recs], ":", label="rg predicted by fit")
    axes[0, 1].semilogy(mid, [r["cog_rg_rms"] for r in recs], "o-", alpha=0.4, label="rg, CoG + linear")
    axes[0, 0].axhline(SEED_CENTROID_PX, color="r", lw=0.8, label="seed 0.2 px")
    axes[0, 0].axhline(SEED_CENTROID_PX / 2, color="r", ls="--", lw=0.8, label="target 0.1 px")
    axes[0, 1].axhline(SEED_COLOUR_RMS, color="r", lw=0.8, label="seed 0.05")
    axes[0, 1].axhline(SEED_COLOUR_RMS / 2, color="r", ls="--", lw=0.8, label="target 0.025")
    axes[0, 0].set(xlabel="V magnitude", ylabel="centroid RMS error, px", title="centroid vs magnitude")
    axes[0, 1].set(xlabel="V magnitude", ylabel="colour-ratio RMS error", title="colour ratios vs magnitude (RGGB)")
    axes[1, 0].set(xlabel="V magnitude", ylabel="fraction / count", title="detection completeness, false detections")
    sp = results["speed"]["median_ms"]
    keys = ["detect_ms", "fit_ms", "vectors_ms", "total_ms", "cpu_total_ms"]
    axes[1, 1].bar(keys, [sp[k] for k in keys], color=["C0", "C1", "C2", "C3", "C4"])
    axes[1, 1].axhline(100, color="r", ls="--", lw=0.8, label="target 100 ms")
    axes[1, 1].set(ylabel="ms (median)", title="time per stage, 2592 x 1944, ~20 stars")
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    path = out / "extract_accuracy.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=12, help="rendered frames per sensor for accuracy")
    ap.add_argument("--speed-frames", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=3, help="timed extractions per speed frame")
    ap.add_argument("--out", default="out/bench")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cam = CameraModel.reference_design()
    results = {}
    mag_bins = list(zip(MAG_BINS[:-1], MAG_BINS[1:]))
    for name, det in (("colour", DetectorModel(pattern="RGGB")), ("mono", DetectorModel(pattern="MONO"))):
        rows, false_v = run_accuracy(det, cam, args.frames, name, seed0=0 if name == "colour" else 50)
        colour = name == "colour"
        by_mag = table(rows, "mag", mag_bins, colour, args.frames, false_v)
        by_snr = table(rows, "snr", SNR_BANDS, colour, args.frames)
        results[name] = {
            "by_mag": by_mag,
            "by_snr": by_snr,
            "n_true": int(len(rows)),
            "false_total": int(len(false_v)),
            "frames": args.frames,
        }
        print_table(
            f"[{name}] accuracy and detection vs V magnitude ({args.frames} frames, {len(rows)} true stars, "
            f"{len(false_v)} false detections)",
            by_mag,
            colour,
        )
        print_table(f"[{name}] accuracy vs SNR", by_snr, colour)
        hi = rows[(rows[:, 1] > 50) & (rows[:, 2] == 1)]
        summary = {"centroid_rms": rms(np.hypot(hi[:, 3], hi[:, 4])), "n": int(len(hi))}
        if colour:
            summary.update({"rg_rms": rms(hi[:, 5]), "bg_rms": rms(hi[:, 6])})
        hi100 = rows[(rows[:, 1] > 100) & (rows[:, 2] == 1)]
        if colour:
            summary.update({"rg_rms_snr100": rms(hi100[:, 5]), "bg_rms_snr100": rms(hi100[:, 6])})
        results[name]["snr_above_50"] = summary
        print(
            f"[{name}] SNR > 50: "
            + ", ".join(f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}" for k, v in summary.items())
        )
    med, p90, jac_ratio, n_det = run_speed(cam, args.speed_frames, args.repeats)
    results["speed"] = {
        "median_ms": {k.replace("_s", "_ms"): v * 1e3 for k, v in med.items()},
        "p90_ms": {k.replace("_s", "_ms"): v * 1e3 for k, v in p90.items()},
        "finite_difference_over_analytic_jacobian": jac_ratio,
        "mean_detections": n_det,
    }
    results["speed"]["load_average_1min"] = os.getloadavg()[0]
    print(
        f"\nspeed, 2592 x 1944 RGGB, {n_det:.1f} stars/frame, {args.speed_frames} frames x {args.repeats} "
        f"(1-min load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores): "
        + ", ".join(
            f"{k} median {v:.1f} ms"
            + (f" (p90 {results['speed']['p90_ms'][k]:.1f})" if k in results["speed"]["p90_ms"] else "")
            for k, v in results["speed"]["median_ms"].items()
        )
    )
    print(
        f"fit time, finite-difference / analytic Jacobian (baseline ratio): {jac_ratio:.2f}x "
        "(finite differences run the numpy batched loop, the analytic Jacobian the compiled one; "
        "bench/bench_extract_speed.py times the stages against a one-pass baseline)"
    )
    (out / "extract_results.json").write_text(json.dumps(results, indent=1))
    print(f"plot: {plot(results, out)}; numbers: {out / 'extract_results.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
