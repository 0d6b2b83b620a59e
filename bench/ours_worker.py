"""Our pipeline as a long-lived worker of ``bench_peers.py`` (project venv)::

    .venv/bin/python bench/ours_worker.py

JSON lines (``jsonl_worker``). Requests:

* ``setup(jobs)``: jobs ``{path, fov, epoch, datasheet: [focal_mm, pixel_um] | null}``; builds one
  catalog per array size and field (``CatalogDesign.for_field``, what ``catalog build --fov-deg``
  writes). Untimed.
* ``file(path, centre)``: file to attitude: ``read_frame``, the datasheet camera (or a pinhole from
  the FOV estimate) and ``run_pipeline`` with ``PipelineParams()``. Reply: status, method, matched
  stars, RA/Dec of the pixel ``centre``, the split from the pipeline's own timings (extraction =
  reading + ``extract_stars``; identification = the rest: identification, attitude, optics search).
  The frame's stars, camera and solution are kept as its base.
* ``base(path, targets)``: the kept base: our centroids (x, y, flux, brightest first), the
  quaternion and covariance, and the sensor vectors of ``targets`` pixels under its camera.
* ``centroids(key, rows, x, y, flux, camera)``: the pipeline's identification stage
  (``identify_stars``: strategy, optics search and fit) on a given centroid list: row ``i`` takes
  every field but the position and brightness from base row ``rows[i]`` (a false star a donor
  row's: fit covariance, flags, colour), unit vectors from the camera: ``"estimate"`` the
  datasheet / FOV camera, ``"fitted"`` the camera of the last ``estimate`` answer for ``key``.
  Reply: status, method, quaternion, covariance, matched stars, the extra noise the answer
  estimated (rad per axis, 0 when the announced noise stood).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jsonl_worker import Clock, serve

from firmware_model.camera import CameraModel
from firmware_model.pipeline.frame_readers import read_frame
from firmware_model.pipeline.run import identify_stars, run_pipeline
from firmware_model.pipeline.solve_types import PipelineOutput, PipelineParams
from firmware_model.reference_frames import quat_to_matrix, vec_to_radec
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign


class Ours:
    def __init__(self) -> None:
        self.jobs: dict[str, dict] = {}
        self.catalogs: dict[tuple, object] = {}
        self.base: dict[str, PipelineOutput] = {}
        self.fitted: dict[str, CameraModel] = {}

    def setup(self, jobs) -> dict:
        for job in jobs:
            frame = read_frame(job["path"])
            key = (frame.width, frame.height, job["fov"])
            if key not in self.catalogs:
                self.catalogs[key] = build_catalog(
                    CatalogDesign.for_field(frame.width, frame.height, job["fov"], epoch=job["epoch"])
                )
            self.jobs[job["path"]] = {**job, "key": key}
        return {"version": "ours"}

    def _camera(self, job, width, height) -> CameraModel:
        if job.get("datasheet"):
            return CameraModel.from_focal(width, height, *job["datasheet"])
        return CameraModel.from_horizontal_fov(width, height, job["fov"])

    def file(self, path, centre) -> dict:
        job = self.jobs[path]
        with Clock() as c:
            with Clock() as cr:
                frame = read_frame(path)
            out = run_pipeline(frame, self._camera(job, frame.width, frame.height), self.catalogs[job["key"]])
        rep = c.times()
        self.base[path] = out
        extract = cr.wall + (out.stars.timings.get("total_s", 0.0) if out.stars is not None else 0.0)
        sol = out.solution
        rep.update(
            status=out.status.name,
            method=None if sol is None or sol.method is None else sol.method.name.lower(),
            matches=0 if sol is None else len(sol.matched_det),
            extract_s=extract,
            ident_s=c.wall - extract,
            ra=None,
            dec=None,
            fov=None,
        )
        if sol is not None and sol.q_icrs_to_sensor is not None and out.camera is not None:
            v = quat_to_matrix(sol.q_icrs_to_sensor).T @ out.camera.pixel_to_vector(*centre)[0]
            ra, dec = np.degrees(vec_to_radec(v))
            rep.update(ra=float(ra), dec=float(dec))
        return rep

    def base_of(self, path, targets) -> dict:
        out = self.base[path]
        assert out.stars is not None and out.camera is not None and out.solution is not None
        t = np.asarray(targets, float).reshape(-1, 2)
        return {
            "x": out.stars.x.tolist(),
            "y": out.stars.y.tolist(),
            "flux": out.stars.flux.tolist(),
            "status": out.status.name,
            "q": np.asarray(out.solution.q_icrs_to_sensor).tolist(),
            "cov": np.asarray(out.solution.covariance).tolist(),
            "target_vectors": out.camera.pixel_to_vector(t[:, 0], t[:, 1]).tolist(),
        }

    def centroids(self, key, rows, x, y, flux, camera) -> dict:
        base = self.base[key]
        job = self.jobs[key]
        stars = base.stars
        assert stars is not None
        if camera == "fitted":
            cam = self.fitted.get(key, base.camera)
        else:
            cam = self._camera(job, job["key"][0], job["key"][1])
        rows = np.asarray(rows, np.int64)
        n = len(stars)
        picked = {}
        for f in dataclasses.fields(stars):
            v = getattr(stars, f.name)
            if isinstance(v, np.ndarray) and v.ndim >= 1 and len(v) == n:
                picked[f.name] = v[rows]
        x, y = np.asarray(x, float), np.asarray(y, float)
        picked.update(x=x, y=y, flux=np.asarray(flux, float), vectors=cam.pixel_to_vector(x, y), timings={})
        given = dataclasses.replace(stars, **picked)
        with Clock() as c:
            out = identify_stars(given, cam, self.catalogs[job["key"]], PipelineParams())
        rep = c.times()
        sol = out.solution
        found = sol is not None and sol.q_icrs_to_sensor is not None
        if found and camera == "estimate" and out.camera is not None:
            self.fitted[key] = out.camera
        rep.update(
            status=out.status.name,
            method=None if sol is None or sol.method is None else sol.method.name.lower(),
            q=np.asarray(sol.q_icrs_to_sensor).tolist() if found else None,
            cov=np.asarray(sol.covariance).tolist() if found and sol.covariance is not None else None,
            matches=0 if sol is None else len(sol.matched_det),
            noise_extra=float(sol.noise_extra) if found else None,
        )
        return rep


def main() -> None:
    ours = Ours()
    serve({"setup": ours.setup, "file": ours.file, "base": ours.base_of, "centroids": ours.centroids})


if __name__ == "__main__":
    main()
