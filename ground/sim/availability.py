"""A rendered whole-sky availability run: seeded random attitudes over the real sky, each frame
rendered with ``sensor_sim.render_frame`` and a list of effects, solved with ``run_pipeline``, and
scored.

* Attitudes: frame ``k`` of seed ``s`` draws its boresight uniformly on the sphere and its roll
  uniformly from ``default_rng([s, k])``; ``default_rng([s, k, 1])`` gives first its noise seed
  (the same with or without effects), then the effects' draws; so a frame is the same whatever the
  worker count or the order frames run in.
* Rendering: the real sky to V 6.5 (``sky_model.sky_stars``) cut to the field, the reference-design
  camera and a ``DetectorModel`` (RGGB, the run's exposure), as ``bench/bench_openloop.py``.
  Each effect is an object with ``render_inputs(attitude, camera, detector, rng) ->
  RenderInputs`` (``ground.sim.detector_effects``); effects apply in order, each to the detector
  the one before returned; their false objects are joined, their extra e- summed, their truth kept
  under ``truth["effects"]``, their metadata merged into the Frame's, the last timestamp wins. With
  a start time, frame ``k`` is at ``start + k x spacing`` (POSIX UTC s) and an effect with an
  ``at_time(t)`` method is moved there first.
* Solving: ``run_pipeline(frame, camera, catalog)`` with the default catalog (V <= 5) and
  ``PipelineParams()``, the frame carrying no camera, as the open-loop bench.
* Scoring (``ground.sim.truth.score``, as ``replay`` scores): ``correct`` when the attitude is within :data:`CORRECT_DEG` of the truth and no matched
  star carries a wrong id (truth stars within :data:`MATCH_RADIUS_PX` of the detection, none with
  its id); ``wrong`` for any other attitude; ``no_solution`` without one. Availability is the
  fraction of frames with a high-confidence (status OK) attitude.
"""

from __future__ import annotations

import dataclasses
import sys
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from ground.sim.truth import CORRECT_DEG, MATCH_RADIUS_PX, Truth
from ground.sim.truth import score as truth_score


@dataclass(frozen=True)
class AvailabilityConfig:
    """``n_attitudes`` frames of ``seed``, ``exposure_s`` (s) each, ``pattern`` the CFA; frame
    times from ``start_posix`` (POSIX UTC s, or None: no time) every ``spacing_s`` (s)."""

    n_attitudes: int
    seed: int = 0
    exposure_s: float = 0.1
    pattern: str = "RGGB"
    start_posix: float | None = None
    spacing_s: float = 60.0

    def __post_init__(self):
        if self.n_attitudes < 1:
            raise ValueError(f"need at least 1 attitude, got {self.n_attitudes}")
        if not self.exposure_s > 0:
            raise ValueError(f"an exposure must be positive, got {self.exposure_s}")


_CTX: tuple | None = None


def reference_scene():
    """(the default catalog, the reference-design camera, the real sky to V 6.5, the catalog's ids)
    of this process, built once: what the rendered availability run and the open-loop bench
    (``bench/bench_openloop.py``) render and solve with."""
    global _CTX
    if _CTX is None:
        from firmware_model.camera import CameraModel
        from ground.catalog.build import build_catalog
        from ground.catalog.design import CatalogDesign
        from ground.sim.sky_model import sky_stars

        cat = build_catalog(CatalogDesign())
        _CTX = (cat, CameraModel.reference_design(), sky_stars(), np.asarray(cat.star_id, dtype=np.int64))
    return _CTX


def frame_attitude(seed: int, k: int) -> np.ndarray:
    """Attitude matrix A of frame ``k``: boresight uniform on the sphere, roll uniform."""
    from firmware_model.reference_frames import attitude_from_radec_roll

    rng = np.random.default_rng([seed, k])
    return attitude_from_radec_roll(rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi))


def render_with_effects(stars, attitude, camera, detector, effects, rng: np.random.Generator, seed: int):
    """``render_frame`` with the joined inputs of ``effects`` (module docstring); returns the
    RenderResult with the effects' metadata in its Frame and their truth in ``truth["effects"]``."""
    from ground.sim.sensor_sim import render_frame

    det, objs, extra, truths, meta, stamp = detector, [], None, [], {}, None
    for effect in effects:
        inp = effect.render_inputs(attitude, camera, det, rng)
        det = inp.detector
        objs.extend(inp.false_objects)
        if inp.extra_e is not None:
            extra = inp.extra_e if extra is None else extra + inp.extra_e
        truths.append({"effect": type(effect).__name__, **inp.truth})
        meta.update(inp.metadata)
        stamp = inp.timestamp or stamp
    r = render_frame(stars, attitude, camera, det, seed=seed, false_objects=objs, timestamp=stamp, extra_e=extra)
    r.frame = dataclasses.replace(r.frame, metadata={**r.frame.metadata, **meta}, camera=None)
    r.truth["effects"] = truths
    return r


def score(record: dict, attitude: np.ndarray, truth_stars: list[dict]) -> dict:
    """Outcome (``correct``, ``wrong``, ``no_solution``), attitude error (deg) and wrong ids:
    ``truth.score`` against the rendered attitude and stars (its ``no_match`` named ``no_solution``)."""
    from firmware_model.reference_frames import matrix_to_quat

    truth = Truth(
        matrix_to_quat(attitude),
        np.array([s["id"] for s in truth_stars], dtype=np.int64),
        np.array([s["x"] for s in truth_stars], dtype=float),
        np.array([s["y"] for s in truth_stars], dtype=float),
    )
    scored = truth_score(record, truth)
    if scored["outcome"] == "no_match":
        return {"outcome": "no_solution", "attitude_error_deg": None, "wrong_ids": 0}
    return scored


def near_tracks(x: np.ndarray, y: np.ndarray, tracks: list[dict], radius_px: float = 3.0) -> np.ndarray:
    """Whether each point (px) lies within ``radius_px`` of a track's segment (truth rows)."""
    near = np.zeros(len(x), bool)
    for t in tracks:
        dx, dy = t["x2"] - t["x"], t["y2"] - t["y"]
        u = np.clip(((x - t["x"]) * dx + (y - t["y"]) * dy) / max(dx * dx + dy * dy, 1e-12), 0.0, 1.0)
        near |= np.hypot(x - t["x"] - u * dx, y - t["y"] - u * dy) <= radius_px
    return near


def run_frame(cfg: AvailabilityConfig, effects: tuple, k: int) -> dict:
    """Render, solve and score frame ``k``: one row (JSON-ready)."""
    from firmware_model.pipeline.run import run_pipeline
    from ground.link.solve_report import record_from_output
    from ground.sim.openloop import stars_in_cone
    from ground.sim.sensor_sim import DetectorModel

    cat, camera, sky, cat_ids = reference_scene()
    a = frame_attitude(cfg.seed, k)
    if cfg.start_posix is not None:
        t = cfg.start_posix + k * cfg.spacing_s
        effects = tuple(e.at_time(t) if hasattr(e, "at_time") else e for e in effects)
    rng = np.random.default_rng([cfg.seed, k, 1])
    noise_seed = int(rng.integers(2**31))  # first: a frame's noise is the same with or without effects
    det = DetectorModel(pattern=cfg.pattern, exposure_s=cfg.exposure_s)
    stars = stars_in_cone(sky, a, camera.fov_half_angle_diagonal + np.radians(1.0))
    r = render_with_effects(stars, a, camera, det, effects, rng, noise_seed)
    out = run_pipeline(r.frame, camera, cat)
    rec = record_from_output(out)
    tracks = [t for e in r.truth["effects"] for t in e.get("cosmic", {}).get("tracks", [])]
    dx = np.asarray(out.stars.x if out.stars is not None else [], dtype=float)
    dy = np.asarray(out.stars.y if out.stars is not None else [], dtype=float)
    tx, ty = np.array([s["x"] for s in r.truth["stars"]]), np.array([s["y"] for s in r.truth["stars"]])
    on_stars = [bool(len(tx)) and float(np.min(np.hypot(tx - x, ty - y))) <= MATCH_RADIUS_PX for x, y in zip(dx, dy)]
    return {
        "k": k,
        "status": rec["status"],
        "reason": out.reason or "",
        "n_detected": rec["n_detected"],
        "n_matched": rec["n_matched"],
        "n_catalog_in_view": int(np.isin([s["id"] for s in r.truth["stars"]], cat_ids).sum()),
        "n_hits": len(tracks),
        "n_detections": len(dx),
        "n_detections_on_tracks": int(near_tracks(dx, dy, tracks).sum()),
        "n_detections_on_stars": int(sum(on_stars)),
        "effects": [_without_tracks(e) for e in r.truth["effects"]],
        "timestamp": r.frame.timestamp,
        **score(rec, a, r.truth["stars"]),
    }


def _without_tracks(effect_truth: dict) -> dict:
    """An effect's truth with its cosmic tracks counted instead of listed (rows stay small)."""
    if "cosmic" not in effect_truth:
        return effect_truth
    cosmic = {k: v for k, v in effect_truth["cosmic"].items() if k != "tracks"}
    return {**effect_truth, "cosmic": cosmic}


def _chunk(args) -> list[dict]:
    cfg, effects, ks = args
    return [run_frame(cfg, effects, k) for k in ks]


def run_availability(
    cfg: AvailabilityConfig, effects=(), workers: int = 1, progress: bool = False, chunk: int = 4
) -> list[dict]:
    """Rows of frames ``0 .. n_attitudes - 1`` in order; ``workers`` processes (the rows do not
    depend on it); a tqdm bar on stderr when ``progress``."""
    from tqdm import tqdm

    from firmware_model.camera import CameraModel
    from ground.arg_types import InputError
    from ground.sim.detector_effects import MAX_HITS_PER_FRAME, MissionEffects, check_hits
    from ground.sim.sensor_sim import DetectorModel

    effects = tuple(effects)
    det = DetectorModel(pattern=cfg.pattern, exposure_s=cfg.exposure_s)
    for effect in effects:  # before any work: a flux over a long exposure could ask for millions of hits
        if isinstance(effect, MissionEffects):
            try:
                check_hits(effect, det, CameraModel.reference_design(), MAX_HITS_PER_FRAME)
            except ValueError as exc:
                raise InputError(f"sim availability: {exc}") from None
    ks = list(range(cfg.n_attitudes))
    parts = [ks[i : i + chunk] for i in range(0, len(ks), chunk)]
    rows: list[dict] = []
    with tqdm(total=len(ks), unit="frame", desc="sim availability", disable=not progress, file=sys.stderr) as bar:
        if workers <= 1:
            for part in parts:
                rows.extend(_chunk((cfg, effects, part)))
                bar.update(len(part))
        else:
            import multiprocessing

            from ground.sim.whole_sky import WORKER_START  # spawned, never forked (a fork beside threads can deadlock)

            with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(WORKER_START)) as pool:
                for got in pool.map(_chunk, [(cfg, effects, p) for p in parts]):
                    rows.extend(got)
                    bar.update(len(got))
    return rows


def summarise(rows: list[dict]) -> dict:
    """Counts and fractions of a run: availability (high-confidence attitudes / frames), correct,
    high-confidence wrong, low-confidence (and wrong), no solution, statuses, hits per frame,
    frames inside the SAA."""
    n = len(rows)
    hc = [r for r in rows if r["status"] == "OK"]
    lc = [r for r in rows if r["status"] == "LOW_CONFIDENCE"]
    return {
        "frames": n,
        "availability": len(hc) / n if n else 0.0,
        "high_confidence": len(hc),
        "correct": sum(r["outcome"] == "correct" for r in rows),
        "high_confidence_correct": sum(r["outcome"] == "correct" for r in hc),
        "high_confidence_wrong": sum(r["outcome"] == "wrong" for r in hc),
        "low_confidence": len(lc),
        "low_confidence_wrong": sum(r["outcome"] == "wrong" for r in lc),
        "no_solution": sum(r["outcome"] == "no_solution" for r in rows),
        "status_counts": dict(sorted(Counter(r["status"] for r in rows).items())),
        "mean_hits_per_frame": float(np.mean([r["n_hits"] for r in rows])) if n else 0.0,
        "frames_in_saa": sum(any(e.get("cosmic", {}).get("in_saa", False) for e in r["effects"]) for r in rows),
    }


def summary_table(summary: dict) -> str:
    """The summary as text lines (key: value) for a reader."""
    s = summary
    lines = [
        f"frames: {s['frames']}",
        f"availability (high-confidence attitude): {s['high_confidence']} ({s['availability'] * 100:.1f} %)",
        f"correct (within {CORRECT_DEG:g} deg, no wrong id): {s['correct']}",
        f"high-confidence wrong: {s['high_confidence_wrong']}",
        f"low-confidence: {s['low_confidence']} (wrong {s['low_confidence_wrong']})",
        f"no solution: {s['no_solution']}",
        f"statuses: {', '.join(f'{k} {v}' for k, v in s['status_counts'].items())}",
        f"radiation hits per frame (mean drawn): {s['mean_hits_per_frame']:.2f}",
        f"frames in the South Atlantic Anomaly: {s['frames_in_saa']}",
    ]
    return "\n".join(lines)
