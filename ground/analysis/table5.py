"""Enright & McVittie table 5 on frames with truth: correct and incorrect matches for the basic
pipeline, with idealised colour, with idealised geometry (the paper's chromatic correction) and
with both (``st16-ground table5``)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.pipeline.extract import StarList, extract_stars
from firmware_model.pipeline.frame_readers import read_frame
from firmware_model.pipeline.run import identify_stars
from firmware_model.pipeline.solve_types import PipelineParams
from ground.arg_types import InputError
from ground.link.solve_report import record_from_output
from ground.sim.truth import MATCH_RADIUS_PX, Truth, score

TABLE5_MODES = ("basic", "ideal colour", "chromatic correction", "ideal colour + chromatic")


def _associate(stars: StarList, truth: Truth):
    """(detection row, truth row) pairs within MATCH_RADIUS_PX."""
    pairs = []
    for i in range(len(stars)):
        d = np.hypot(truth.x - stars.x[i], truth.y - stars.y[i])
        if len(d) and d.min() <= MATCH_RADIUS_PX:
            pairs.append((i, int(np.argmin(d))))
    return pairs


class NothingToScore(InputError):
    """``table5`` was given no frame it can score (none has a truth file): ``st16-ground`` says why in
    one line and exits 2, as for any input it cannot use."""


def _mean_colour_error(errors: list) -> np.ndarray | None:
    """Mean (rg, bg) error of one star over the frames where its colour was measured; None when it
    never was (a mono frame measures no colour: its rg, bg are NaN)."""
    e = np.array(errors, dtype=float)
    e = e[np.isfinite(e).all(axis=1)]
    return e.mean(axis=0) if len(e) else None


def table5(
    paths,
    camera: CameraModel,
    catalog: OnboardCatalog,
    params: PipelineParams = PipelineParams(),
    progress: bool = True,
) -> dict:
    """Enright & McVittie table 5 on frames with truth: correct/incorrect matches for the basic pipeline,
    with idealised colour (each star's mean colour error over the run removed), with
    idealised geometry (each star's mean centroid error removed: the paper's chromatic
    correction) and with both. Frames without a truth file are left out; none with one raises
    :class:`NothingToScore`."""
    ids = {int(s): k for k, s in enumerate(catalog.star_id)}
    paths = [Path(p) for p in paths]
    runs = []
    for path in tqdm(paths, desc="extract", unit="frame", disable=not progress):
        truth = Truth.for_frame(path)
        if truth is None:
            continue
        stars = extract_stars(read_frame(path), camera, params.extract)
        runs.append((stars, truth, _associate(stars, truth)))
    if not runs:
        where = f" in {paths[0].parent}" if len({p.parent for p in paths}) == 1 else ""
        missing = f"none of the {len(paths)} frames{where} has truth" if paths else "no frame to score"
        raise NothingToScore(
            f"table5: {missing}: table5 scores frames against truth files <stem>.truth.json beside them "
            "(frame render and the demo write them)"
        )
    colour_err: dict[int, list] = {}
    pos_err: dict[int, list] = {}
    for stars, truth, pairs in runs:
        for i, t in pairs:
            sid = int(truth.star_id[t])
            pos_err.setdefault(sid, []).append((stars.x[i] - truth.x[t], stars.y[i] - truth.y[t]))
            if sid in ids:
                c = ids[sid]
                colour_err.setdefault(sid, []).append((stars.rg[i] - catalog.rg[c], stars.bg[i] - catalog.bg[c]))
    mean_colour = {s: m for s, v in colour_err.items() if (m := _mean_colour_error(v)) is not None}
    mean_pos = {s: np.mean(np.array(v), axis=0) for s, v in pos_err.items()}
    table = {}
    for mode in TABLE5_MODES:
        counts = {"correct": 0, "incorrect": 0, "no_match": 0}
        for stars, truth, pairs in runs:
            s2 = replace(stars, x=stars.x.copy(), y=stars.y.copy(), rg=stars.rg.copy(), bg=stars.bg.copy())
            for i, t in pairs:
                sid = int(truth.star_id[t])
                if "colour" in mode and sid in mean_colour:
                    s2.rg[i] -= mean_colour[sid][0]
                    s2.bg[i] -= mean_colour[sid][1]
                if "chromatic" in mode:
                    s2.x[i] -= mean_pos[sid][0]
                    s2.y[i] -= mean_pos[sid][1]
            s2 = replace(s2, vectors=camera.pixel_to_vector(s2.x, s2.y))
            sc = score(record_from_output(identify_stars(s2, camera, catalog, params)), truth)
            key = {"correct": "correct", "wrong": "incorrect"}.get(sc["outcome"], "no_match")
            counts[key] += 1
        table[mode] = counts
    return {"frames": len(runs), "table": table}
