"""Runs inside the benchmark-only venv (.venv-peers): cedar-solve's ``solve_from_image`` with its
recommended use (a horizontal field-of-view estimate, default settings otherwise), warm (one
untimed solve first), timed per file from open to solution.

Usage: python cedar_runner.py JOBS.json OUT.json, JOBS a list of [path, fov_deg]; prints nothing."""

import json
import sys
import time

import tetra3
from PIL import Image


def open_image(path):
    """The image as cedar-solve takes it (it refuses an alpha channel: dropped, as a user would)."""
    img = Image.open(path)
    return img.convert("RGB") if img.mode in ("RGBA", "LA", "P") else img


def main() -> None:
    jobs, out = json.load(open(sys.argv[1])), sys.argv[2]
    t3 = tetra3.Tetra3()
    t3.solve_from_image(open_image(jobs[0][0]), fov_estimate=jobs[0][1])  # warm-up, untimed
    rows = {}
    for path, fov in jobs:
        t0 = time.perf_counter()
        sol = t3.solve_from_image(open_image(path), fov_estimate=fov)
        rows[path] = {
            "ra": sol.get("RA"),
            "dec": sol.get("Dec"),
            "fov": sol.get("FOV"),
            "rmse": sol.get("RMSE"),
            "wall_s": time.perf_counter() - t0,
        }
    with open(out, "w") as fh:
        json.dump(rows, fh)


if __name__ == "__main__":
    main()
