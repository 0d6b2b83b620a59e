"""Runs inside the benchmark-only venv (.venv-peers): cedar-solve's solve_from_image on image
files, timed per file. Usage: python tetra3_cedar_runner.py OUT.json FILE... (prints nothing)."""

import json
import sys
import time

import tetra3
from PIL import Image


def main() -> None:
    out, files = sys.argv[1], sys.argv[2:]
    t3 = tetra3.Tetra3()
    rows = {}
    for path in files:
        t0 = time.perf_counter()
        img = Image.open(path)
        sol = t3.solve_from_image(img, distortion=[-0.2, 0.1])
        wall = time.perf_counter() - t0
        rows[path] = {"ra": sol.get("RA"), "dec": sol.get("Dec"), "rmse": sol.get("RMSE"), "wall_s": wall,
                      "t_solve_ms": sol.get("T_solve"), "t_extract_ms": sol.get("T_extract")}
    with open(out, "w") as fh:
        json.dump(rows, fh)


if __name__ == "__main__":
    main()
