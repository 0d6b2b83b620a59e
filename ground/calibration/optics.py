"""Camera calibration from real sky frames: identify stars with the device pipeline, then fit
the camera model to them (``firmware_model.pipeline.camera_fit``).

A nominal focal length (lens label, pixel pitch) is often off by about a percent, which at the
edge of a 10-degree field is several pixels: too much for a tight lost-in-space match. So:

1. extract stars once per frame;
2. identify each frame with the pipeline's uncalibrated-optics search (scale-free patterns,
   focal length within ``focal_search`` of the initial camera, ``pipeline.OpticsSearch``); the
   initial camera of the joint fit takes the median of the per-frame fitted focal lengths;
3. fit the chosen camera parameters and per-frame attitudes to the identified stars;
4. identify again with the fitted camera (no search) and refit (``rounds`` times), so stars that
   the first camera missed join the fit.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from tqdm import tqdm

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.ident.consensus import Outcome
from firmware_model.pipeline.camera_fit import CalibrationResult, StarObservations, calibrate
from firmware_model.pipeline.extract import StarList, extract_stars
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.run import identify_stars
from firmware_model.pipeline.solve_types import OpticsSearch, PipelineOutput, PipelineParams


@dataclass
class FrameCalibration:
    result: CalibrationResult
    focal_scale: float  #: median per-frame focal length found by the search / the initial one
    solved: list[bool]  #: per frame: high-confidence solve with the final camera
    outputs: list[PipelineOutput]


def _identify_all(stars: list[StarList], camera: CameraModel, catalog: OnboardCatalog, params: PipelineParams):
    return [
        identify_stars(replace(s, vectors=camera.pixel_to_vector(s.x, s.y)), camera, catalog, params) for s in stars
    ]


def _high(out: PipelineOutput) -> bool:
    return out.solution is not None and out.solution.status is Outcome.HIGH_CONFIDENCE


def _observations(stars: list[StarList], outs: list[PipelineOutput], catalog: OnboardCatalog):
    obs = []
    for s, out in zip(stars, outs):
        sol = out.solution
        if _high(out) and sol is not None and len(sol.matched_det) >= 3:
            rows = out.used[sol.matched_det]
            obs.append(StarObservations(s.x[rows], s.y[rows], catalog.vec[sol.matched_cat]))
    return obs


def calibrate_from_frames(
    frames: list[Frame],
    catalog: OnboardCatalog,
    initial: CameraModel,
    params: PipelineParams = PipelineParams(),
    fit=("f", "k1"),
    focal_search: float = 0.05,
    rounds: int = 2,
    progress: bool = True,
) -> FrameCalibration:
    """Calibrate ``initial`` on ``frames`` of the real sky (module docstring)."""
    if rounds < 1:
        raise ValueError(f"rounds must be at least 1 (each round fits the camera), got {rounds}")
    stars = [extract_stars(f, None, params.extract) for f in frames]
    search = replace(params, optics=replace(params.optics or OpticsSearch(), focal_range=focal_search))
    outs = [
        identify_stars(replace(s, vectors=initial.pixel_to_vector(s.x, s.y)), initial, catalog, search)
        for s in tqdm(stars, desc="identify", disable=not progress)
    ]
    focals = [o.optics.camera.f for o in outs if _high(o) and o.optics is not None]
    if not any(_high(o) for o in outs):
        raise ValueError(
            f"no frame could be identified with focal lengths within {focal_search:.0%} of the initial camera"
        )
    camera = replace(initial, f=float(np.median(focals))) if focals else initial
    scale = camera.f / initial.f
    fixed = replace(params, optics=None)
    result: CalibrationResult | None = None
    for _ in range(rounds):
        obs = _observations(stars, outs, catalog)
        result = calibrate(obs, camera, fit=fit)
        camera = result.camera
        outs = _identify_all(stars, camera, catalog, fixed)
    assert result is not None  # rounds >= 1
    return FrameCalibration(result, float(scale), [_high(o) for o in outs], outs)
