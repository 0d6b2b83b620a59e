"""Tracking mode on the device's frames: a frame tracked from the last fix, else lost in space.

:class:`Tracker` keeps the :class:`~firmware_model.ident.tracking.TrackState` between frames
(docs/tracking.md). Per frame, at mid-exposure time ``t`` (s): with a state, the frame's stars
are extracted and tracked (``tracking.track``); a tracked answer has method TRACKING, the
filtered attitude and its covariance, and the rate (``PipelineOutput.omega``). Without a state
the frame is solved lost in space (``run_pipeline``); when the track is lost, lost in space runs
on the same extracted stars (``identify_stars``) and its reason starts ``tracking lost, lost in
space: <why>`` (the fallback first: the result's reason holds 96 bytes). Every high-confidence
lost-in-space answer starts a new track; any other answer ends it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from datetime import UTC, datetime

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.ident.consensus import Outcome
from firmware_model.ident.solver import Method, SolveResult
from firmware_model.ident.tracking import TrackParams, TrackResult, TrackState, track
from firmware_model.pipeline.exclusion import Recall, check_exclusion
from firmware_model.pipeline.extract import StarList
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.run import frame_stars, identify_stars, run_pipeline
from firmware_model.pipeline.solve_types import PipelineOutput, PipelineParams
from protocol.result import Status


def frame_time(frame: Frame, started: float) -> float:
    """Mid-exposure time of ``frame`` (POSIX s): its ``timestamp`` (UTC ISO-8601, the exposure
    start; no zone: UTC) when it has a readable one, else ``started`` (the GO time, when the
    capture starts), plus half the exposure."""
    start = started
    try:
        stamp = datetime.fromisoformat(frame.timestamp) if frame.timestamp else None
    except ValueError:
        stamp = None  # unreadable: the GO time
    if stamp is not None:
        start = (stamp if stamp.tzinfo else stamp.replace(tzinfo=UTC)).timestamp()
    return start + 0.5 * (frame.exposure_s or 0.0)


@dataclass
class Tracker:
    """The track between frames (``state`` None: none); ``params`` the tracking settings."""

    params: TrackParams = TrackParams()
    state: TrackState | None = None

    def solve(
        self,
        frame: Frame,
        t: float,
        camera: CameraModel,
        catalog: OnboardCatalog,
        params: PipelineParams,
        recall: Recall | None = None,
    ) -> PipelineOutput:
        """``frame`` taken at mid-exposure time ``t`` (s), tracked when a track exists, else lost
        in space, then checked for bright bodies (``recall``: the device's last attitude at ``t``);
        the track is then kept, restarted from a confident fix, or ended."""
        if self.state is None:
            out = run_pipeline(frame, camera, catalog, params, recall)
        else:
            out = check_exclusion(
                self._track(frame, t, camera, catalog, params, self.state), frame, params.exclusion, recall
            )
        sol = out.solution
        if sol is not None and sol.method is Method.TRACKING:
            return out  # self.state updated by _track
        self.state = None
        if out.status is Status.OK and sol is not None and sol.q_icrs_to_sensor is not None:
            self.state = TrackState.from_fix(sol.q_icrs_to_sensor, sol.covariance, t, self.params)
        return out

    def _track(
        self,
        frame: Frame,
        t: float,
        camera: CameraModel,
        catalog: OnboardCatalog,
        params: PipelineParams,
        state: TrackState,
    ) -> PipelineOutput:
        stars = frame_stars(frame, camera, params)
        if isinstance(stars, PipelineOutput):
            return stars  # a bad frame
        t0 = time.perf_counter()
        res = track(
            np.column_stack([stars.x, stars.y]),
            state,
            t,
            catalog,
            camera,
            self.params,
            sigma_px=params.fixed_sigma_px,
            exposure_s=frame.exposure_s or 0.0,
        )
        if not res.ok:
            out = identify_stars(stars, camera, catalog, params)
            out.reason = f"tracking lost, lost in space: {res.reason}" + (f"; {out.reason}" if out.reason else "")
            return out
        self.state = res.state
        out = _tracked_output(stars, res, catalog, camera, params)
        out.timings.identify = time.perf_counter() - t0
        out.timings.total = stars.timings.get("total_s", 0.0) + out.timings.identify
        return out


def _tracked_output(
    stars: StarList, res: TrackResult, catalog: OnboardCatalog, camera: CameraModel, params: PipelineParams
) -> PipelineOutput:
    """A tracking step as a pipeline answer: the filtered attitude, covariance and rate."""
    n = len(res.matched_det)
    sol = SolveResult(
        Outcome.HIGH_CONFIDENCE,
        q_icrs_to_sensor=res.state.q,
        covariance=res.state.attitude_covariance,
        matched_det=res.matched_det,
        matched_cat=res.matched_cat,
        matched_star_id=catalog.star_id[res.matched_cat],
        matched_rg=catalog.rg[res.matched_cat].astype(float),
        matched_bg=catalog.bg[res.matched_cat].astype(float),
        residuals=res.residuals,
        consensus_size=n,
        consensus_rms=float(np.sqrt(np.mean(res.residuals**2))),
        confidence=n / res.n_predicted,
        coverage=n / res.n_predicted,
        method=Method.TRACKING,
        n_used=len(stars),
    )
    out = PipelineOutput(
        Status.OK,
        stars=stars,
        used=np.arange(len(stars)),
        solution=sol,
        colour_beta=params.colour_beta,
        camera=camera,
        omega=res.state.omega,
        omega_covariance=res.state.rate_covariance,
    )
    out.timings.detect = stars.timings.get("detect_s", 0.0)
    out.timings.fit = stars.timings.get("fit_s", 0.0)
    out.timings.vectors = stars.timings.get("vectors_s", 0.0)
    return out
