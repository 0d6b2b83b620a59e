"""Real frames from cameras we did not model, solved with nothing but datasheet or field-of-view
optics and default settings, against cedar-solve in the same run.

Frames: the 8 ESA tetra3 frames (../shared/data/frames/tetra3-mono: 16-bit mono TIFF; optics
from the datasheet, 35 mm lens and 6.9 um binned pixels, no distortion) and the 7 colour-real
frames (demosaiced PNG/JPEG; a pinhole camera from the horizontal field of view in
reference_pointing.json). Ours: ``run_pipeline`` with ``PipelineParams()`` and a catalog from
``CatalogDesign.for_field`` (what ``catalog build --fov-deg`` writes). cedar-solve 0.5.1:
``solve_from_image(image, fov_estimate=F)`` with its bundled database, warm. Both timed per file
from reading the image to the solution, single-threaded, interleaved over ``--rounds`` rounds
(median per file). Pointing: the solved direction of the image-centre pixel against the
reference (astrometry.net for colour-real; for tetra3 fixtures/tetra3_cedar_reference.json, a
cedar-solve run written by ``--write-tetra3-reference``: agreement, not truth), in pixels; and ours
against this run's cedar-solve answer on the same file (``ours-cedar px``).

Identification time: ``id ms`` is the pipeline's own stage timings (``identify`` +
``attitude``, wall) of the timed run, the optics search included when the datasheet camera was
not good enough; ``cal id ms`` / ``cpu`` is the identification alone (``identify_stars`` without
the optics search) of the same extracted stars with the camera the answer was found with (the
calibrated camera a device runs with after its first solve), wall and CPU time of the thread
(``time.thread_time``), median over the rounds; ``in view`` is matched / catalog stars predicted
on the array within 2 px of a detection. The summary gives the median and p99 over the frames.

    python3 -m venv .venv-peers && .venv-peers/bin/pip install --no-deps cedar-solve "numpy<2" scipy pillow
    .venv/bin/python bench/bench_realframes.py [--rounds 3]
    .venv/bin/python bench/bench_realframes.py --write-tetra3-reference
    .venv/bin/python bench/bench_realframes.py --perturbed 25

``--perturbed N`` (ours only): every frame our clean run solves with high confidence
within 1 px, its extracted stars perturbed N times per kind (3 false stars at random places
with fluxes drawn from the frame's, 20 % of the detections dropped, 1 px centroid noise with
its variance added to the reported covariance, all three), identified with the calibrated camera
(no optics search) against the clean answer: returned, correct (within 0.1 deg), high
confidence, high confidence wrong (beyond 0.1 deg), high confidence off by more than 3 sigma on
an axis (``HC >3sig``, the attitude covariance about the sensor axes: about 0.8 % of Gaussian
errors) and in total angle (``>3sig tot``: more than 3 sqrt(trace P)), roll error p99, identification ms (wall, CPU).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "frames"
PEER_PYTHON = ROOT / ".venv-peers" / "bin" / "python"
REFERENCE = ROOT / "fixtures" / "tetra3_cedar_reference.json"
TETRA3_FOV = float(np.degrees(2 * np.arctan(1024 * 6.9e-3 / 2 / 35.0)))  # datasheet: 11.53 deg


def frames() -> list[dict]:
    """Jobs: path, horizontal FOV (deg), reference centre (RA, Dec deg) and plate scale (arcsec/px)."""
    jobs = []
    t3 = DATA / "tetra3-mono"
    if t3.is_dir():
        ref = json.loads(REFERENCE.read_text())["frames"]
        scale = 3600 * np.degrees(6.9e-3 / 35.0)
        for p in sorted(t3.glob("*.tiff")):
            ra, dec = ref[p.name][:2]
            jobs.append(
                {
                    "path": p,
                    "set": "tetra3",
                    "fov": TETRA3_FOV,
                    "ref": (ra, dec),
                    "scale": scale,
                    "datasheet": (35.0, 6.9),
                }
            )
    cr = DATA / "colour-real"
    if cr.is_dir():
        ref = json.loads((cr / "reference_pointing.json").read_text())
        for name, r in ref.items():
            jobs.append(
                {
                    "path": cr / name,
                    "set": "colour",
                    "fov": r["fov_deg"][0],
                    "ref": (r["centre_ra_deg"], r["centre_dec_deg"]),
                    "scale": r["plate_scale_arcsec_per_px"],
                    "size": r["size_px"],
                }
            )
    return jobs


def separation_px(ra, dec, job) -> float:
    from firmware_model.reference_frames import radec_to_vec

    a = radec_to_vec(np.radians(ra), np.radians(dec))
    b = radec_to_vec(np.radians(job["ref"][0]), np.radians(job["ref"][1]))
    return float(np.degrees(np.arccos(np.clip(a @ b, -1, 1))) * 3600 / job["scale"])


def ours(job, catalogs) -> dict:
    from firmware_model.camera import CameraModel
    from firmware_model.pipeline.frame_readers import read_frame
    from firmware_model.pipeline.run import run_pipeline
    from firmware_model.reference_frames import quat_to_matrix, vec_to_radec
    from ground.link.solve_report import record_from_output

    t0 = time.perf_counter()
    frame = read_frame(job["path"])
    if "datasheet" in job:
        camera = CameraModel.from_focal(frame.width, frame.height, *job["datasheet"])
    else:
        camera = CameraModel.from_horizontal_fov(frame.width, frame.height, job["fov"])
    catalog = catalogs[(frame.width, frame.height, job["fov"])]
    out = run_pipeline(frame, camera, catalog)
    wall = time.perf_counter() - t0
    rec = record_from_output(out)
    cal = calibrated_identification(out, catalog)
    row = {
        "status": rec["status"],
        "method": rec["method"],
        "matched": rec["n_matched"],
        "reason": rec["reason"],
        "wall_s": wall,
        "sep_px": None,
        "focal_px": rec["optics"]["focal_px"],
        "searched": rec["optics"]["searched"],
        "id_s": out.timings.identify + out.timings.attitude,
        **cal,
        "out": out,
        "catalog": catalog,
    }
    if rec["q_icrs_to_sensor"] is not None:
        w, h = job.get("size", (frame.width, frame.height))  # centre of the original image (before any crop)
        v = quat_to_matrix(rec["q_icrs_to_sensor"]).T @ out.camera.pixel_to_vector((w - 1) / 2, (h - 1) / 2)[0]
        ra, dec = np.degrees(vec_to_radec(v))
        row["sep_px"] = separation_px(ra, dec, job)
        row["ra"], row["dec"] = float(ra), float(dec)
    return row


def calibrated_identification(out, catalog) -> dict:
    """Identification alone (no optics search) of ``out``'s stars with the camera its answer was
    found with (the fitted optics when there are): wall and thread CPU seconds, status, and
    matched / in view (catalog stars predicted on the array within 2 px of a detection)."""
    from dataclasses import replace

    from firmware_model.pipeline.run import identify_stars
    from firmware_model.pipeline.solve_types import PipelineParams

    if out.stars is None or out.camera is None or out.solution is None or out.solution.q_icrs_to_sensor is None:
        return {"cal_s": None, "cal_cpu_s": None, "cal_status": None, "in_view": None, "cal_matched": None}
    camera = out.optics.camera if out.optics is not None else out.camera
    stars = replace(out.stars, vectors=camera.pixel_to_vector(out.stars.x, out.stars.y))
    params = PipelineParams(optics=None)
    c0, t0 = time.thread_time(), time.perf_counter()
    again = identify_stars(stars, camera, catalog, params)
    wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
    in_view = matched = None
    if again.solution is not None and again.solution.q_icrs_to_sensor is not None:
        from firmware_model.reference_frames import quat_to_matrix

        a = quat_to_matrix(again.solution.q_icrs_to_sensor)
        near = catalog.stars_within(a[2], camera.fov_half_angle_diagonal * 1.05)
        px, py = camera.vector_to_pixel(catalog.vec[near] @ a.T)
        on = np.isfinite(px) & camera.in_frame(px, py)
        d = np.hypot(stars.x[:, None] - px[on][None, :], stars.y[:, None] - py[on][None, :])
        in_view = int(np.count_nonzero(np.nanmin(d, axis=0) < 2.0)) if d.size else 0
        matched = len(again.solution.matched_det)
    return {
        "cal_s": wall,
        "cal_cpu_s": cpu,
        "cal_status": again.status.name,
        "in_view": in_view,
        "cal_matched": matched,
    }


def perturb(stars, camera, kind: str, rng):
    """``stars`` with one perturbation (``--perturbed``): "false", "drop", "noise" or "all"."""
    from dataclasses import fields, replace

    n = len(stars)
    arrays = {f.name: getattr(stars, f.name) for f in fields(stars)}
    arrays = {k: v for k, v in arrays.items() if isinstance(v, np.ndarray) and v.shape[:1] == (n,)}
    keep = np.ones(n, bool)
    if kind in ("drop", "all"):
        keep[rng.choice(n, int(round(0.2 * n)), replace=False)] = False
    new = {k: v[keep].copy() for k, v in arrays.items()}
    if kind in ("noise", "all"):
        new["x"] = new["x"] + rng.normal(0.0, 1.0, len(new["x"]))
        new["y"] = new["y"] + rng.normal(0.0, 1.0, len(new["y"]))
        new["cov_xy"] = new["cov_xy"] + np.eye(2)[None]
    if kind in ("false", "all"):
        m = len(new["x"])
        src = rng.integers(0, m, 3)  # fluxes and the other fields of random real detections
        extra = {k: v[src].copy() for k, v in new.items()}
        extra["x"] = rng.uniform(0, camera.width - 1, 3)
        extra["y"] = rng.uniform(0, camera.height - 1, 3)
        new = {k: np.concatenate([new[k], extra[k]]) for k in new}
        order = np.argsort(-new["flux"], kind="stable")
        new = {k: v[order] for k, v in new.items()}
    new["vectors"] = camera.pixel_to_vector(new["x"], new["y"])
    return replace(stars, **new)


def perturbed_run(jobs, catalogs, reps: int, seed: int = 12) -> int:
    """The ``--perturbed`` table (module docstring)."""
    from dataclasses import replace

    from firmware_model.pipeline.run import identify_stars
    from firmware_model.pipeline.solve_types import PipelineParams
    from firmware_model.reference_frames import quat_to_matrix

    rng = np.random.default_rng(seed)
    params = PipelineParams(optics=None)
    base = []
    for j in jobs:
        row = ours(j, catalogs)
        out, catalog = row["out"], row["catalog"]
        if out.status.name != "OK" or row["sep_px"] is None or row["sep_px"] > 1.0:
            continue
        cam = out.optics.camera if out.optics is not None else out.camera
        assert out.stars is not None and cam is not None
        stars = replace(out.stars, vectors=cam.pixel_to_vector(out.stars.x, out.stars.y))
        ref = identify_stars(stars, cam, catalog, params)  # the reference: clean stars, the same camera
        if ref.status.name == "OK" and ref.solution is not None:
            base.append((j["set"], cam, catalog, stars, quat_to_matrix(ref.solution.q_icrs_to_sensor)))
    print(f"\nperturbed inputs: {reps} per frame and kind on {len(base)} frames (calibrated camera, no optics search)")
    print(
        f"{'set':<8}{'kind':<8}{'inputs':>7}{'returned':>9}{'correct':>8}{'HC':>5}{'HC wrong':>9}{'HC >3sig':>9}{'>3sig tot':>10}"
        f"{'roll p99 deg':>13}{'id ms p50':>10}{'p99':>7}{'cpu p50':>8}{'p99':>7}"
    )
    for name, kind in [(n, k) for n in sorted({b[0] for b in base}) for k in ("false", "drop", "noise", "all")]:
        n = ret = good = hc = hc_wrong = hc_out = hc_total = 0
        walls, cpus, rolls = [], [], []
        for _set, cam, catalog, stars, a_ref in (b for b in base if b[0] == name):
            for _ in range(reps):
                st = perturb(replace(stars), cam, kind, rng)
                c0, t0 = time.thread_time(), time.perf_counter()
                got = identify_stars(st, cam, catalog, params)
                walls.append(time.perf_counter() - t0)
                cpus.append(time.thread_time() - c0)
                n += 1
                sol = got.solution
                if sol is None or sol.q_icrs_to_sensor is None:
                    continue
                ret += 1
                d = quat_to_matrix(sol.q_icrs_to_sensor) @ a_ref.T
                e = 0.5 * np.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]])
                err = float(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
                ok = err <= 0.1
                good += ok
                rolls.append(abs(float(np.degrees(e[2]))))
                if got.status.name == "OK":
                    hc += 1
                    hc_wrong += not ok
                    sig = np.sqrt(np.clip(np.diag(sol.covariance), 0, None))
                    hc_out += bool(np.any(np.abs(e) > 3 * sig))
                    hc_total += bool(np.linalg.norm(e) > 3 * np.sqrt(np.trace(sol.covariance)))
        print(
            f"{name:<8}{kind:<8}{n:>7}{ret:>9}{good:>8}{hc:>5}{hc_wrong:>9}{hc_out:>9}{hc_total:>10}"
            f"{(np.percentile(rolls, 99) if rolls else float('nan')):>13.4f}"
            f"{1e3 * np.median(walls):>10.1f}{1e3 * np.percentile(walls, 99):>7.1f}"
            f"{1e3 * np.median(cpus):>8.1f}{1e3 * np.percentile(cpus, 99):>7.1f}"
        )
    return 0


def cedar(jobs) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        spec, out = Path(tmp) / "jobs.json", Path(tmp) / "out.json"
        spec.write_text(json.dumps([[str(j["path"]), j["fov"]] for j in jobs]))
        subprocess.run(
            [str(PEER_PYTHON), str(ROOT / "bench" / "cedar_runner.py"), str(spec), str(out)],
            check=True,
            stderr=subprocess.DEVNULL,
        )
        return json.loads(out.read_text())


def write_tetra3_reference() -> int:
    """The tetra3 frames' reference pointing: cedar-solve's recommended use (``cedar_runner.py``:
    a field-of-view estimate, default settings), with its RMSE per frame."""
    jobs = [j for j in frames() if j["set"] == "tetra3"]
    if not jobs or not PEER_PYTHON.exists():
        print(f"need the tetra3 frames under {DATA} and cedar-solve in {PEER_PYTHON.parent.parent}", file=sys.stderr)
        return 1
    res = cedar(jobs)
    rows = {
        j["path"].name: [
            round(res[str(j["path"])]["ra"], 5),
            round(res[str(j["path"])]["dec"], 5),
            round(res[str(j["path"])]["rmse"], 2),
            round(res[str(j["path"])]["fov"], 4),
        ]
        for j in jobs
    }
    REFERENCE.write_text(
        json.dumps(
            {
                "what": "boresight (image-centre) RA/Dec in degrees of the 8 tetra3 test frames as solved by cedar-solve "
                f"0.5.1 (solve_from_image(image, fov_estimate={TETRA3_FOV:.2f}), bundled database, default settings), an "
                "independent reference for our solutions (agreement, not truth)",
                "how": "bench/bench_realframes.py --write-tetra3-reference (runs cedar-solve in the benchmark venv .venv-peers)",
                "frames": rows,
                "columns": ["ra_deg", "dec_deg", "cedar_rmse_arcsec", "cedar_fov_deg"],
            },
            indent=2,
        )
        .replace(",\n      ", ", ")
        .replace("[\n      ", "[")
        .replace("\n    ]", "]")
        + "\n"
    )  # one line per frame
    for name, r in rows.items():
        print(f"{name}: RA {r[0]:.5f} Dec {r[1]:.5f} RMSE {r[2]:.2f} arcsec FOV {r[3]:.4f} deg")
    print(f"written {REFERENCE}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument(
        "--write-tetra3-reference",
        action="store_true",
        help=f"solve the tetra3 frames once with cedar-solve and write {REFERENCE.relative_to(ROOT)}",
    )
    ap.add_argument("--set", choices=("all", "tetra3", "colour"), default="all", help="--perturbed: which frames")
    ap.add_argument("--perturbed", type=int, default=0, metavar="N", help="perturbed-input table, N per frame and kind")
    args = ap.parse_args()
    if args.write_tetra3_reference:
        return write_tetra3_reference()
    from firmware_model.pipeline.frame_readers import read_frame
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    jobs = frames()
    if not jobs:
        print(f"no frames under {DATA}; nothing to do")
        return 0
    catalogs = {}
    for j in jobs:
        fr = read_frame(j["path"])
        key = (fr.width, fr.height, j["fov"])
        if key not in catalogs:
            catalogs[key] = build_catalog(
                CatalogDesign.for_field(fr.width, fr.height, j["fov"], epoch=2019.6 if j["set"] == "tetra3" else 2025.0)
            )
    if args.perturbed:
        return perturbed_run([j for j in jobs if args.set in ("all", j["set"])], catalogs, args.perturbed)
    have_cedar = PEER_PYTHON.exists()
    if not have_cedar:
        print(f"(cedar-solve not installed in {PEER_PYTHON.parent.parent}; see the module docstring)")
    for j in jobs:  # warm-up, untimed
        ours(j, catalogs)
    runs_ours, runs_cedar = {str(j["path"]): [] for j in jobs}, {str(j["path"]): [] for j in jobs}
    for _ in range(args.rounds):
        for j in jobs:
            runs_ours[str(j["path"])].append(ours(j, catalogs))
        if have_cedar:
            for k, v in cedar(jobs).items():
                runs_cedar[k].append(v)
    print(
        f"\n{'frame':<34}{'ours':<15}{'method':<10}{'stars':>6}{'sep px':>8}{'ms':>8}"
        f"{'cedar':>8}{'sep px':>8}{'ms':>8}{'ratio':>7}{'ours-cedar px':>14}"
        f"{'id ms':>7}{'cal id ms':>10}{'cpu':>6}{'in view':>9}"
    )
    summary = {}
    for j in jobs:
        key = str(j["path"])
        mine = runs_ours[key][-1]
        my_ms = 1e3 * float(np.median([r["wall_s"] for r in runs_ours[key]]))
        c = runs_cedar[key]
        c_ok = bool(c) and c[-1]["ra"] is not None
        c_ms = 1e3 * float(np.median([r["wall_s"] for r in c])) if c else float("nan")
        c_sep = separation_px(c[-1]["ra"], c[-1]["dec"], j) if c_ok else None
        # ours against today's cedar-solve on the same file (the tetra3 reference is an older cedar run)
        vs_cedar = (
            separation_px(mine["ra"], mine["dec"], {**j, "ref": (c[-1]["ra"], c[-1]["dec"])})
            if c_ok and mine["sep_px"] is not None
            else None
        )
        s = summary.setdefault(
            j["set"],
            {
                "n": 0,
                "ours": 0,
                "ours_1px": 0,
                "cedar": 0,
                "cedar_1px": 0,
                "both": 0,
                "agree_1px": 0,
                "ours_ms": [],
                "cedar_ms": [],
                "ratio": [],
                "id_ms": [],
                "cal_ms": [],
                "cal_cpu_ms": [],
                "all_in_view": 0,
            },
        )
        id_ms = 1e3 * float(np.median([r["id_s"] for r in runs_ours[key]]))
        cal = [r for r in runs_ours[key] if r["cal_s"] is not None]
        cal_ms = 1e3 * float(np.median([r["cal_s"] for r in cal])) if cal else float("nan")
        cal_cpu = 1e3 * float(np.median([r["cal_cpu_s"] for r in cal])) if cal else float("nan")
        s["id_ms"].append(id_ms)
        if cal:
            s["cal_ms"].append(cal_ms)
            s["cal_cpu_ms"].append(cal_cpu)
        view = "-" if mine["in_view"] is None else f"{mine['cal_matched']}/{mine['in_view']}"
        s["all_in_view"] += mine["in_view"] is not None and mine["cal_matched"] >= mine["in_view"]
        s["n"] += 1
        s["ours"] += mine["status"] == "OK"
        s["ours_1px"] += mine["status"] == "OK" and mine["sep_px"] is not None and mine["sep_px"] <= 1.0
        s["cedar"] += c_ok
        s["cedar_1px"] += c_ok and c_sep <= 1.0
        s["both"] += mine["status"] == "OK" and vs_cedar is not None
        s["agree_1px"] += mine["status"] == "OK" and vs_cedar is not None and vs_cedar <= 1.0
        s["ours_ms"].append(my_ms)
        if c:
            s["cedar_ms"].append(c_ms)
            s["ratio"].append(c_ms / my_ms)
        sep = "-" if mine["sep_px"] is None else f"{mine['sep_px']:.2f}"
        print(
            f"{j['path'].name[:33]:<34}{mine['status']:<15}{mine['method'] or '-':<10}{mine['matched']:>6}{sep:>8}"
            f"{my_ms:>8.0f}{('OK' if c_ok else ('fail' if c else '-')):>8}"
            f"{('-' if c_sep is None else f'{c_sep:.2f}'):>8}{c_ms:>8.0f}"
            f"{(f'{c_ms / my_ms:.2f}' if c else '-'):>7}{('-' if vs_cedar is None else f'{vs_cedar:.2f}'):>14}"
            f"{id_ms:>7.1f}{cal_ms:>10.1f}{cal_cpu:>6.1f}{view:>9}"
        )
        if mine["status"] != "OK":
            print(f"{'':<34}reason: {mine['reason']}")
    print()
    for name, s in summary.items():
        line = (
            f"{name}: ours {s['ours']}/{s['n']} high confidence ({s['ours_1px']} within 1 px of the reference), "
            f"median {np.median(s['ours_ms']):.0f} ms"
        )
        if s["cedar_ms"]:
            line += (
                f"; cedar-solve {s['cedar']}/{s['n']} ({s['cedar_1px']} within 1 px), median "
                f"{np.median(s['cedar_ms']):.0f} ms; time ratio cedar/ours median {np.median(s['ratio']):.2f}; "
                f"both high confidence on {s['both']}, ours within 1 px of cedar-solve's on {s['agree_1px']}"
            )
        print(line)
        if s["cal_ms"]:
            print(
                f"{name}: identification (pipeline stages, optics search included) median {np.median(s['id_ms']):.1f} ms, "
                f"p99 {np.percentile(s['id_ms'], 99):.1f} ms; with the calibrated camera median "
                f"{np.median(s['cal_ms']):.1f} ms wall / {np.median(s['cal_cpu_ms']):.1f} ms CPU, p99 "
                f"{np.percentile(s['cal_ms'], 99):.1f} ms wall / {np.percentile(s['cal_cpu_ms'], 99):.1f} ms CPU; "
                f"every star in view matched on {s['all_in_view']}/{len(s['cal_ms'])}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
