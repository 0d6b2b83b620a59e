"""Are our high-confidence covariances honest? The normalised attitude error of every
high-confidence answer on bench_peers.py's perturbed centroid sets.

Our centroids of the 8 tetra3 frames (../shared/data/frames/tetra3-mono), solved once with the
datasheet optics; then ``--inputs`` perturbed lists per set (``bench_peers.perturb``, drawn as
``bench_peers.py`` draws them: at the same ``--seed`` and ``--inputs`` the same lists), each
solved in process with the optics fitted on the unperturbed list (``ours_worker.Ours``, the
added noise not announced) and scored against the unperturbed solution. For each high-confidence
answer, ``z = error / sigma`` on each sensor axis (x, y, roll about the boresight) from its
reported covariance. An exactly right Gaussian covariance gives ``std z = 1`` and 0.27 % of the
axes beyond 3 (0.81 % of the answers on some axis); printed: those counts against their
expectation, the per-axis std of z, a Kolmogorov-Smirnov p-value against N(0, 1) and the largest
|z|, overall and split by method and by whether the answer estimated the frame's noise.

    .venv/bin/python bench/bench_covariance.py [--inputs 200] [--seed 1] [--sets "1px noise" "all combined"]
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_peers import P_ANY, SETS, TARGET_OFFSETS, attitude_error, perturb  # noqa: E402
from bench_realframes import frames  # noqa: E402
from ours_worker import Ours  # noqa: E402


def solve_sets(args):
    """Records (set, method, adapted, high confidence, correct, z per axis) of every answer."""
    from PIL import Image

    from firmware_model.reference_frames import quat_to_matrix

    jobs = [j for j in frames() if j["set"] == "tetra3"]
    if not jobs:
        sys.exit("no tetra3 frames under ../shared/data/frames/tetra3-mono")
    ours = Ours()
    ours.setup(
        [{"path": str(j["path"]), "fov": j["fov"], "epoch": 2019.6, "datasheet": list(j["datasheet"])} for j in jobs]
    )
    bases, sizes = {}, {}
    for j in jobs:
        key = str(j["path"])
        ours.file(key, [0, 0])
        h, w = Image.open(j["path"]).size[::-1]
        sizes[key] = (h, w)
        bases[key] = ours.base_of(key, (TARGET_OFFSETS + [(w - 1) / 2, (h - 1) / 2]).tolist())
        b = bases[key]
        ours.centroids(key, list(range(len(b["x"]))), b["x"], b["y"], b["flux"], "estimate")
    draw = np.random.default_rng([args.seed, 2])  # bench_peers.perturbed_sets' draws
    records = []
    for set_name, (n_false, p_drop, noise) in SETS.items():
        inputs = [jobs[i % len(jobs)] for i in range(args.inputs)]
        lists = [perturb(bases[str(j["path"])], n_false, p_drop, noise, draw, sizes[str(j["path"])]) for j in inputs]
        if set_name not in args.sets:
            continue
        for j, (rows, x, y, flux) in zip(inputs, lists):
            key = str(j["path"])
            rep = ours.centroids(key, rows, x, y, flux, "fitted")
            if rep["q"] is None:
                records.append({"set": set_name, "returned": False})
                continue
            base = bases[key]
            err, _, rv = attitude_error(
                quat_to_matrix(rep["q"]), quat_to_matrix(base["q"]), np.asarray(base["target_vectors"])[0]
            )
            sigma = np.sqrt(np.clip(np.diag(np.asarray(rep["cov"])), 1e-30, None))
            records.append(
                {
                    "set": set_name,
                    "returned": True,
                    "high": rep["status"] == "OK",
                    "correct": err < 0.1,
                    "method": rep["method"],
                    "adapted": rep["noise_extra"] > 0,
                    "z": np.asarray(rv) / sigma,
                }
            )
    return records


def describe(label: str, recs: list) -> str:
    from scipy.stats import kstest

    z = np.array([r["z"] for r in recs]).reshape(-1, 3)
    n = len(z)
    beyond = int(np.count_nonzero(np.any(np.abs(z) > 3.0, axis=1)))
    std = " / ".join(f"{v:.2f}" for v in np.std(z, axis=0)) if n > 1 else "-"
    ks = " / ".join(f"{kstest(z[:, k], 'norm').pvalue:.2g}" for k in range(3)) if n > 7 else "-"
    top = f"{np.max(np.abs(z)):.2f}" if n else "-"
    return f"  {label:<34s} {n:>5d} {beyond:>6d} {n * P_ANY:>9.2f}   {std:<18s} {ks:<22s} {top:>6s}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", type=int, default=200, help="perturbed lists per set")
    ap.add_argument("--seed", type=int, default=1, help="bench_peers.py's seed")
    ap.add_argument("--sets", nargs="+", default=["1px noise", "all combined"], choices=list(SETS))
    args = ap.parse_args()
    records = solve_sets(args)
    print(f"{args.inputs} inputs per set, seed {args.seed}; HC = high confidence; z = error / reported sigma per axis")
    head = f"  {'answers':<34s} {'HC':>5s} {'>3 sig':>6s} {'expected':>9s}   {'std z x / y / roll':<18s} {'KS p x / y / roll':<22s} {'max|z|':>6s}"
    for set_name in args.sets:
        recs = [r for r in records if r["set"] == set_name]
        high = [r for r in recs if r["returned"] and r["high"]]
        returned = sum(r["returned"] for r in recs)
        correct = sum(r["returned"] and r["correct"] for r in recs)
        wrong = sum(not r["correct"] for r in high)
        print(
            f"\n{set_name}: returned {returned}, high confidence {len(high)}, correct (< 0.1 deg) {correct}, HC wrong {wrong}"
        )
        print(head)
        print(describe("all high-confidence", high))
        groups = defaultdict(list)
        for r in high:
            groups[(r["method"], r["adapted"])].append(r)
        for (method, adapted), rs in sorted(groups.items()):
            print(describe(f"{method}, {'noise estimated' if adapted else 'noise as announced'}", rs))
    print(f"\nexpected: {100 * P_ANY:.2f} % of the answers beyond 3 sigma on some axis for an exactly right covariance")


if __name__ == "__main__":
    main()
