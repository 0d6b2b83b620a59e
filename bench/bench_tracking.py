"""Tracking mode on rendered, motion-smeared frames along constant-rate slews (docs/tracking.md).

Per rate (deg/s, about a fixed oblique axis with a roll component): ``--runs`` slews from random
attitudes, ``--frames`` frames each at ``--hz`` (100 ms exposure, smear rendered with
``ground.sim.smear.SmearPSF``, the real sky to V 6.5, the reference camera and the default
catalog V <= 5). Frame 0 is solved lost in space (``identify_stars``, timed: the baseline), the
rest tracked (``tracking.track``, timed alone; extraction is not timed in either). At frame
``--loss`` the fix is dropped (a forced loss) and lost in space runs on each following frame
until it is confident again; from frame ``--jump`` the true attitude carries a step of
``--jump-arcsec`` (a disturbance the constant-rate model does not know). A lost tracking step
falls back to lost in space on the same frame. Prints per rate: tracked share, track time p50 / p99 (and the
p50 ratio to the lost-in-space solve time of the same run), attitude error p50 / p99 (whole
rotation, and the boresight direction alone: the rest is roll), rate error
(norm of the error vector) with the filter's 1-sigma, and the
re-acquisition time after the forced loss (frames and wall ms of the lost-in-space solves), then
whether the step was caught and every lost step with its reason.
The rate error is taken over the ``--settle`` frames before the loss (the filter has run from
the first fix).

    .venv/bin/python bench/bench_tracking.py [--runs 3] [--frames 36] [--loss 20] [--jump 30] [--rate-noise 1e-7] [--seed 1]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from firmware_model.camera import CameraModel  # noqa: E402
from firmware_model.ident.attitude import quat_matrix  # noqa: E402
from firmware_model.ident.tracking import TrackParams, TrackState, track  # noqa: E402
from firmware_model.pipeline.extract import extract_stars  # noqa: E402
from firmware_model.pipeline.run import identify_stars
from firmware_model.pipeline.solve_types import PipelineParams  # noqa: E402
from firmware_model.reference_frames import attitude_from_radec_roll, rotation_angle  # noqa: E402
from ground.catalog.build import build_catalog  # noqa: E402
from ground.catalog.design import CatalogDesign  # noqa: E402
from ground.sim.exposure import ExposureRenderer  # noqa: E402
from ground.sim.sensor_sim import DetectorModel  # noqa: E402
from ground.sim.smear import SmearPSF  # noqa: E402
from protocol.result import Status  # noqa: E402

RATES_DEG_S = (0.0, 0.1, 0.5, 1.0)
AXIS = np.array([0.6, 0.64, 0.48])  #: slew axis (sensor frame, unit): mostly across the boresight


def run_slew(rate_deg, run, args, cam, det, cat, renderer, pparams, tparams):
    """One slew: records of timings, errors and the two losses (forced, attitude jump)."""
    rng = np.random.default_rng(args.seed * 1000 + run)
    a0 = attitude_from_radec_roll(rng.uniform(0, 2 * np.pi), np.arcsin(rng.uniform(-1, 1)), rng.uniform(0, 2 * np.pi))
    omega = np.radians(rate_deg) * AXIS
    jump = Rotation.from_rotvec([np.radians(args.jump_arcsec / 3600), 0.0, 0.0]).as_matrix()
    psf = SmearPSF(cam, det, omega, det.exposure_s) if rate_deg > 0 else None
    rec = {"track_s": [], "ok": 0, "tried": 0, "att_err": [], "bore_err": [], "rate_err": [], "rate_sigma": []}
    rec["lis_s"] = []
    rec.update(reacq_frames=None, reacq_s=0.0, reasons=[], jump_lost=False, jump_reacq=None)
    state, lost_at = None, None
    for k in range(args.frames):
        t = k / args.hz
        a_true = Rotation.from_rotvec(-omega * t).as_matrix() @ a0
        if k >= args.jump:
            a_true = jump @ a_true  # an attitude step the constant-rate model does not know
        frame = renderer.render(a_true, det, seed=args.seed * 100000 + run * 100 + k, psf=psf)
        stars = extract_stars(frame, cam, pparams.extract)
        if k == args.loss:
            state, lost_at = None, k  # forced loss
        if state is not None:
            t0 = time.perf_counter()
            res = track(np.column_stack([stars.x, stars.y]), state, t, cat, cam, tparams, exposure_s=det.exposure_s)
            rec["track_s"].append(time.perf_counter() - t0)
            rec["tried"] += 1
            state = res.state if res.ok else None
            if res.ok:
                rec["ok"] += 1
                a_est = quat_matrix(state.q)
                rec["att_err"].append(rotation_angle(a_est, a_true))
                rec["bore_err"].append(np.arccos(np.clip(a_est[2] @ a_true[2], -1.0, 1.0)))
                if args.loss - args.settle <= k < args.loss:
                    rec["rate_err"].append(np.linalg.norm(state.omega - omega))
                    rec["rate_sigma"].append(np.sqrt(np.trace(state.rate_covariance)))
                continue
            rec["reasons"].append((k, res.reason))
            rec["jump_lost"] |= k == args.jump
        # lost in space on this frame: the first fix, after the forced loss, after a lost track
        t0 = time.perf_counter()
        out = identify_stars(stars, cam, cat, pparams)
        wall = time.perf_counter() - t0
        rec["lis_s"].append(wall)
        if lost_at is not None and rec["reacq_frames"] is None:
            rec["reacq_s"] += wall
        if out.status is Status.OK:
            assert out.solution is not None
            state = TrackState.from_fix(out.solution.q_icrs_to_sensor, out.solution.covariance, t, tparams)
            if lost_at is not None and rec["reacq_frames"] is None:
                rec["reacq_frames"] = k - lost_at + 1
            if k >= args.jump and rec["jump_reacq"] is None:
                rec["jump_reacq"] = k - args.jump + 1
    return rec


def pct(x, q):
    return float(np.percentile(x, q)) if len(x) else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="slews per rate")
    ap.add_argument("--frames", type=int, default=36, help="frames per slew")
    ap.add_argument("--hz", type=float, default=5.0, help="frame rate")
    ap.add_argument("--loss", type=int, default=20, help="frame of the forced loss")
    ap.add_argument("--settle", type=int, default=10, help="rate error over this many frames before the loss")
    ap.add_argument("--jump", type=int, default=30, help="frame from which the attitude steps (a disturbance)")
    ap.add_argument("--jump-arcsec", type=float, default=60.0, help="the step, about sensor x")
    ap.add_argument("--rate-noise", type=float, default=TrackParams.rate_noise, help="TrackParams.rate_noise")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    cam = CameraModel.reference_design()
    det = DetectorModel()
    t0 = time.perf_counter()
    cat = build_catalog(CatalogDesign())
    renderer = ExposureRenderer(cam)
    print(f"catalog V <= 5: {cat.n_stars} stars ({time.perf_counter() - t0:.1f} s to build); sky to V 6.5")
    pparams, tparams = PipelineParams(optics=None), TrackParams(rate_noise=args.rate_noise)
    print(
        f"reference camera f = {cam.f:.0f} px, {det.pattern}, exposure {det.exposure_s * 1e3:.0f} ms, {args.hz:g} Hz,"
        f" {args.runs} slews x {args.frames} frames per rate, forced loss at frame {args.loss}; 'tracked' leaves out"
        " the step frame, 'ratio' = lost-in-space p50 / tracking p50, rate error over the"
        f" {args.settle} frames before the forced loss"
    )
    head = (
        f"{'deg/s':>6}{'smear px':>9}{'tracked':>10}{'trk p50 ms':>11}{'p99 ms':>8}{'LIS p50 ms':>11}{'ratio':>7}"
        f"{'att p50 as':>11}{'p99':>7}{'bore p50':>9}{'p99':>7}{'rate err deg/s p50':>19}{'max':>8}{'1-sig':>8}{'reacq fr':>9}{'ms':>7}"
    )
    print(head)
    for rate in RATES_DEG_S:
        recs = [run_slew(rate, r, args, cam, det, cat, renderer, pparams, tparams) for r in range(args.runs)]
        cat_all = {
            key: sum((r[key] for r in recs), []) for key in ("track_s", "att_err", "bore_err", "rate_err", "rate_sigma")
        }
        lis_s = sum((r["lis_s"] for r in recs), [])
        ok, tried = sum(r["ok"] for r in recs), sum(r["tried"] for r in recs) - sum(r["jump_lost"] for r in recs)
        trk = np.array(cat_all["track_s"]) * 1e3
        att = np.degrees(cat_all["att_err"]) * 3600
        bore = np.degrees(cat_all["bore_err"]) * 3600
        rate_err = np.degrees(cat_all["rate_err"])
        reacq = [r["reacq_frames"] for r in recs if r["reacq_frames"] is not None]
        smear_px = np.radians(rate) * det.exposure_s * cam.f
        print(
            f"{rate:>6.2f}{smear_px:>9.1f}{f'{ok}/{tried}':>10}{pct(trk, 50):>11.2f}{pct(trk, 99):>8.2f}"
            f"{np.median(lis_s) * 1e3:>11.1f}{np.median(lis_s) * 1e3 / pct(trk, 50):>7.0f}"
            f"{pct(att, 50):>11.1f}{pct(att, 99):>7.1f}{pct(bore, 50):>9.1f}{pct(bore, 99):>7.1f}{pct(rate_err, 50):>19.4f}{pct(rate_err, 100):>8.4f}"
            f"{np.degrees(np.median(cat_all['rate_sigma'])):>8.4f}"
            f"{(f'{np.mean(reacq):.1f}' if reacq else 'never'):>9}{np.mean([r['reacq_s'] for r in recs]) * 1e3:>7.0f}"
        )
        jumps = [r["jump_reacq"] for r in recs if r["jump_lost"] and r["jump_reacq"] is not None]
        print(
            f"        {args.jump_arcsec:g} arcsec attitude step at frame {args.jump}: tracking lost there in"
            f" {sum(r['jump_lost'] for r in recs)}/{len(recs)} slews, fixed again by lost in space on frame"
            f" {'+'.join(str(j - 1) for j in jumps) or '-'} after it"
        )
        for r in recs:
            for k, why in r["reasons"]:
                print(f"        frame {k}{' (the step)' if k == args.jump else ''}: lost: {why}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
