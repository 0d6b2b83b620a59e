"""Our file solve through ``ground.api.solve_image`` as a worker of ``bench_peers.py`` (project
venv): the sky search with a field-of-view hint or blind, the whole-sky database and the field
catalogs as a user's first call gets them::

    .venv/bin/python bench/ours_sky_worker.py

JSON lines (``jsonl_worker``). Requests: ``setup()`` (untimed: the database loaded) and
``file(path, centre, fov)``: ``solve_image(path, fov_deg=fov)`` (``fov`` None: blind). Reply as
``ours_worker``'s ``file``: status, method, matched stars, RA/Dec of the pixel ``centre``, and the
split from the record's timings (extraction = detection + fit; identification = the rest of the
call).
"""

from __future__ import annotations

import numpy as np
from jsonl_worker import Clock, serve

from firmware_model.reference_frames import quat_to_matrix, vec_to_radec
from ground.api import solve_image


def setup() -> dict:
    return {"version": "ours (solve_image)"}


def file(path, centre, fov=None) -> dict:
    with Clock() as c:
        s = solve_image(path, fov_deg=fov)
    rep = c.times()
    rec = s.record
    t = rec.get("timings_s") or {}
    extract = t.get("detect", 0.0) + t.get("fit", 0.0)
    rep.update(
        status=rec["status"],
        method=rec.get("method"),
        matches=int(rec.get("n_matched") or 0),
        extract_s=extract,
        ident_s=c.wall - extract,
        checks=(rec.get("sky") or {}).get("checks"),
        ra=None,
        dec=None,
    )
    if s.q_icrs_to_sensor is not None:
        v = quat_to_matrix(s.q_icrs_to_sensor).T @ s.camera.pixel_to_vector(*centre)[0]
        ra, dec = np.degrees(vec_to_radec(v))
        rep.update(ra=float(ra), dec=float(dec))
    return rep


if __name__ == "__main__":
    serve({"setup": setup, "file": file})
