"""Whole-sky identification simulation (Enright & McVittie section 5.2 and Dong et al. section 3).

Enright & McVittie ("colour" run): boresights on Saff & Kuijlaars' generalized spiral (Enright & McVittie ref. 20),
``n_roll`` roll angles each, the real rectangular field of a ``CameraModel``. Every catalog star
that projects onto the array is observed with the error model of eqs 19-21: ``s~ = (s + n)/|s + n|``
with ``n`` isotropic Gaussian of ``sigma_pix / f`` per axis (so the perpendicular error is
Gaussian with that sigma per axis) and zero-mean Gaussian colour noise. Optional false stars
(uniform over the array, colours drawn from the catalog) and dropped stars. The noise-free colours
are the catalog's (closed loop) unless ``ErrorModel.colours`` takes them from another model with
per-frame channel gains and scintillation (open loop, ``ground.sim.true_colours``). The solver's
quaternion is scored by eqs 22-23: ``q_err = q_true (x) q_est^-1``, ``phi_err = 2 acos|q_err,s|``.

Dong et al. ("fourstar" run): boresights on a 5 deg RA x Dec grid (72 x 37 = 2664 observations),
catalog stars within 12.25 deg of the boresight, per-axis direction noise ``eps / (3 sqrt 2)`` so
that ``|theta' - theta| < eps`` holds at three sigma; each star of the 4-star procedure is
identified, unidentified or misidentified.

Runs are split in chunks of poses and evaluated in parallel: local processes
(``multiprocessing.Pool``, terminated at once on Ctrl-C) with a tqdm progress bar, or a Dask cluster
(``scheduler="tcp://host:8786"``) for sweeps too big for one machine. Every pose has its own
seeded random stream, so results do not depend on the chunking or the executor.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from dataclasses import dataclass
from functools import partial

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.ident.budget import Stop
from firmware_model.ident.consensus import Outcome
from firmware_model.ident.four_star import FourStarParams, match_four_star
from firmware_model.ident.solver import Mode, SolveParams
from firmware_model.ident.strategy import (
    IdentificationInput,
    IdentifyTimings,
    StrategyParams,
    check_hypothesis,
    identify,
)
from firmware_model.ident.verify import FieldOfView
from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat, vec_to_radec
from ground.atomic_write import save_figure
from ground.sim.true_colours import TrueColours, impair, true_colour_table

STATUS_CODE = {Outcome.NO_MATCH: 0, Outcome.LOW_CONFIDENCE: 1, Outcome.HIGH_CONFIDENCE: 2}

#: One row per simulated pose. ``n_true``: true stars among the detections (after drops);
#: ``cause``: index into ``CAUSES`` for a pose with no solution (0 otherwise).
POSE_DTYPE = np.dtype(
    [
        ("boresight", np.int32),
        ("roll", np.float64),
        ("n_visible", np.int16),
        ("n_det", np.int16),
        ("status", np.int8),
        ("n_matched", np.int16),
        ("n_correct", np.int16),
        ("n_wrong", np.int16),
        ("err_deg", np.float64),
        ("time_s", np.float64),
        ("n_true", np.int16),
        ("cause", np.int8),
    ]
)

#: Why a pose has no solution (the availability loss), decided in this order:
#: ``too_few_true_stars``: fewer true stars detected than the method needs (2 for colour, 3 for
#: geometric), or fewer than the poor-match fraction of the visible stars (a correct answer would
#: still be a problem orientation): no matcher can help;
#: ``verification_rejects_truth``: the true identification of the detected stars, handed to the
#: solver's verification (``check_hypothesis``), is refused (e.g. too many predicted stars
#: missed): the verification's fault, whatever the matcher did;
#: ``search_budget``: a search stopped on its counted budget (``ident.budget``: the same on every
#: machine) before it found the truth;
#: ``matcher_missed``: the truth would verify but the matcher did not find it.
CAUSES = ("", "too_few_true_stars", "verification_rejects_truth", "search_budget", "matcher_missed")


#: How local worker processes start (``multiprocessing``): spawned, never forked (see :func:`execute`).
WORKER_START = "spawn"


def spiral_boresights(n: int) -> np.ndarray:
    """``n`` near-uniform unit vectors on Saff & Kuijlaars' generalized spiral, shape (n, 3)."""
    if n < 2:
        raise ValueError(f"need at least 2 boresights, got {n}")
    k = np.arange(1, n + 1)
    h = -1.0 + 2.0 * (k - 1) / (n - 1)
    theta = np.arccos(h)
    phi = np.zeros(n)
    for i in range(1, n - 1):
        phi[i] = (phi[i - 1] + 3.6 / np.sqrt(n * (1.0 - h[i] ** 2))) % (2 * np.pi)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)


def grid_boresights(step_deg: float = 5.0) -> np.ndarray:
    """Dong et al.'s RA x Dec grid: RA 0..360 (exclusive) by ``step``, Dec -90..+90 inclusive."""
    ra = np.radians(np.arange(0.0, 360.0, step_deg))
    dec = np.radians(np.arange(-90.0, 90.0 + 1e-9, step_deg))
    rr, dd = np.meshgrid(ra, dec)
    cd = np.cos(dd.ravel())
    return np.stack([cd * np.cos(rr.ravel()), cd * np.sin(rr.ravel()), np.sin(dd.ravel())], axis=1)


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of scalar-first quaternions, ``p (x) q``."""
    pw, pv = p[0], p[1:]
    qw, qv = q[0], q[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def attitude_error(q_true: np.ndarray, q_est: np.ndarray) -> float:
    """Enright & McVittie eqs 22-23: rotation angle (rad) of ``q_err = q_true (x) q_est^-1``."""
    q_inv = np.array([q_est[0], -q_est[1], -q_est[2], -q_est[3]])
    qe = quat_multiply(np.asarray(q_true, float), q_inv)
    return float(2.0 * np.arccos(min(1.0, abs(qe[0]) / np.linalg.norm(qe))))


@dataclass(frozen=True)
class ErrorModel:
    """Observation model: centroid noise (px), colour-ratio noise, false stars per frame (Poisson
    mean), probability of dropping a true star, where the noise-free colours come from."""

    sigma_pix: float = 0.2
    sigma_colour: float = 0.05
    false_stars: float = 0.0
    p_drop: float = 0.0
    colours: TrueColours = TrueColours()


@dataclass
class Scene:
    """Simulated detections, brightest first: sensor unit vectors, colours, truth catalog index (-1 false)."""

    vectors: np.ndarray
    rg: np.ndarray
    bg: np.ndarray
    truth: np.ndarray
    n_visible: int


def observe(
    catalog: OnboardCatalog,
    a: np.ndarray,
    camera: CameraModel,
    model: ErrorModel,
    rng: np.random.Generator,
    colour: bool = True,
    table: tuple[np.ndarray, np.ndarray] | None = None,
) -> Scene:
    """Detections of the catalog stars on the array for attitude ``a`` (eqs 19-21).

    ``table``: the noise-free (rg, bg) of every catalog star (default: ``true_colour_table`` of
    ``model.colours.source``; pass it to skip recomputing it per frame). Gains and scintillation
    draw from a stream spawned off ``rng``, so they leave every other draw of the frame unchanged.
    """
    true_rg, true_bg = table if table is not None else true_colour_table(catalog, model.colours.source)
    boresight = a[2]
    near = catalog.stars_within(boresight, _field_radius(camera))
    s = catalog.vec[near] @ a.T
    x, y = camera.vector_to_pixel(s)
    on = camera.in_frame(x, y)
    idx, s = near[on], s[on]
    n_visible = len(idx)
    if model.p_drop > 0 and len(idx):
        keep = rng.random(len(idx)) >= model.p_drop
        idx, s = idx[keep], s[keep]
    sigma = model.sigma_pix / camera.f
    noisy = s + rng.normal(scale=sigma, size=s.shape)
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    mag = catalog.mag[idx].astype(float)
    rg, bg = true_rg[idx], true_bg[idx]
    truth = idx.astype(np.int64)
    n_false = rng.poisson(model.false_stars) if model.false_stars > 0 else 0
    if n_false:
        fx = rng.uniform(-0.5, camera.width - 0.5, n_false)
        fy = rng.uniform(-0.5, camera.height - 0.5, n_false)
        pick = rng.integers(0, catalog.n_stars, n_false)
        noisy = np.vstack([noisy, camera.pixel_to_vector(fx, fy)])
        mag = np.concatenate([mag, rng.uniform(mag.min() - 1 if len(mag) else 0, catalog.mag.max(), n_false)])
        rg = np.concatenate([rg, true_rg[pick]])
        bg = np.concatenate([bg, true_bg[pick]])
        truth = np.concatenate([truth, np.full(n_false, -1)])
    order = np.argsort(mag, kind="stable")
    noisy, rg, bg, truth = noisy[order], rg[order], bg[order], truth[order]
    if colour:
        if model.colours.impaired:
            rg, bg = impair(rg, bg, model.colours, rng.spawn(1)[0])
        rg = rg + rng.normal(scale=model.sigma_colour, size=len(rg))
        bg = bg + rng.normal(scale=model.sigma_colour, size=len(bg))
    else:
        rg = np.full(len(rg), np.nan)
        bg = np.full(len(bg), np.nan)
    return Scene(noisy, rg, bg, truth, n_visible)


def _field_radius(camera: CameraModel) -> float:
    return FieldOfView.from_camera(camera, 0.0).radius


# ------------------------------------------------------------------ Enright & McVittie whole-sky run
@dataclass(frozen=True)
class ColourSimConfig:
    """A whole-sky colour run: ``n_boresights`` spiral directions x ``n_roll`` rolls.
    ``colour`` False: a mono frame, solved in the device's order (``strategy.identify``): geometric
    (4-star, triangle) matching and, when that finds nothing and ``geometric_fallback`` is set, the
    consensus matcher on geometry alone (``PipelineParams.geometric_fallback``).
    ``solver_sigma_colour``: the colour-ratio sigma the solver is told (None: ``model.sigma_colour``;
    an open-loop run may tell it the colour model's error too). ``colour_fallback``: a colour frame
    solved in the device's ``auto`` mode, geometry tried too when colour is not high-confidence
    (``StrategyParams.colour_fallback``); False: colour matching alone."""

    n_boresights: int = 10000
    n_roll: int = 10
    seed: int = 0
    model: ErrorModel = ErrorModel()
    solve: SolveParams | None = None  # None: derived from the camera and model
    colour: bool = True
    geometric_fallback: bool = True
    solver_sigma_colour: float | None = None
    colour_fallback: bool = False


def _solve_params(camera: CameraModel, cfg: ColourSimConfig) -> SolveParams:
    if cfg.solve is not None:
        return cfg.solve
    sigma_colour = cfg.model.sigma_colour if cfg.solver_sigma_colour is None else cfg.solver_sigma_colour
    return SolveParams(
        sigma_vec=cfg.model.sigma_pix / camera.f,
        sigma_rg=max(sigma_colour, 1e-3),
        sigma_bg=max(sigma_colour, 1e-3),
        fov=FieldOfView.from_camera(camera, 0.0),
        mode=(Mode.AUTO if cfg.colour_fallback else Mode.COLOUR) if cfg.colour else Mode.GEOMETRIC,
    )


def _strategy(params: SolveParams, cfg: ColourSimConfig) -> StrategyParams:
    """The device's order of methods (``strategy.identify``) on simulated star vectors: every
    detection at once (no brightest-first ladder), no photometric gate (no fluxes), the mono and
    colour fallbacks as configured."""
    return StrategyParams(
        solve=params,
        photometric_gate=None,
        geometric_cap=None,
        geometric_fallback=cfg.geometric_fallback,
        colour_fallback=cfg.colour_fallback,
    )


def pose_scene(
    catalog: OnboardCatalog,
    camera: CameraModel,
    cfg: ColourSimConfig,
    pid: int,
    boresights: np.ndarray,
    table: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, float, Scene]:
    """Attitude matrix, roll (rad) and scene of pose ``pid`` (``boresight * n_roll + roll``) of a
    run with spiral ``boresights``; the same for every caller (the pose's own seeded stream)."""
    b_idx, r_idx = divmod(int(pid), cfg.n_roll)
    rng = np.random.default_rng([cfg.seed, int(pid)])
    roll = 2 * np.pi * (r_idx + rng.random()) / cfg.n_roll
    ra, dec = vec_to_radec(boresights[b_idx])
    a = attitude_from_radec_roll(float(ra), float(dec), roll)
    return a, roll, observe(catalog, a, camera, cfg.model, rng, colour=cfg.colour, table=table)


def run_poses(catalog: OnboardCatalog, camera: CameraModel, cfg: ColourSimConfig, pose_ids: np.ndarray) -> np.ndarray:
    """Evaluate poses ``pose_ids`` (``boresight * n_roll + roll``) of a run; returns POSE_DTYPE rows."""
    boresights = spiral_boresights(cfg.n_boresights)
    params = _solve_params(camera, cfg)
    strategy = _strategy(params, cfg)
    table = true_colour_table(catalog, cfg.model.colours.source)
    out = np.zeros(len(pose_ids), POSE_DTYPE)
    for row, pid in enumerate(np.asarray(pose_ids, np.int64)):
        b_idx = int(pid) // cfg.n_roll
        a, roll, scene = pose_scene(catalog, camera, cfg, int(pid), boresights, table)
        t = time.perf_counter()
        ledger = IdentifyTimings()
        found = identify(IdentificationInput(scene.vectors, scene.rg, scene.bg), catalog, strategy, ledger)
        res = found.solution
        dt = time.perf_counter() - t
        rec = out[row]
        rec["boresight"], rec["roll"], rec["n_visible"], rec["n_det"] = b_idx, roll, scene.n_visible, len(scene.truth)
        rec["status"], rec["time_s"] = STATUS_CODE[res.status], dt
        rec["n_true"] = int(np.sum(scene.truth >= 0))
        rec["err_deg"] = np.nan
        if res.q_icrs_to_sensor is None:
            rec["cause"] = no_solution_cause(scene, ledger.stopped, catalog, params, cfg.colour)
        if res.q_icrs_to_sensor is not None:
            truth = scene.truth[found.rows[res.matched_det]]
            rec["n_matched"] = len(truth)
            rec["n_correct"] = int(np.sum(truth == res.matched_cat))
            rec["n_wrong"] = len(truth) - rec["n_correct"]
            rec["err_deg"] = np.degrees(attitude_error(matrix_to_quat(a), res.q_icrs_to_sensor))
    return out


def no_solution_cause(
    scene: Scene, stopped: Stop, catalog: OnboardCatalog, params: SolveParams, colour: bool, poor_fraction: float = 0.4
) -> int:
    """Index into ``CAUSES`` of an unsolved pose (see ``CAUSES`` for the order of the tests);
    ``stopped`` what stopped its searches early (``IdentifyTimings.stopped``)."""
    true_det = np.nonzero(scene.truth >= 0)[0]
    need = 2 if colour else 3
    if len(true_det) < need or len(true_det) < poor_fraction * scene.n_visible:
        return CAUSES.index("too_few_true_stars")
    match, _ = check_hypothesis(scene.vectors, scene.rg, scene.bg, true_det, scene.truth[true_det], catalog, params)
    if match is None:
        return CAUSES.index("verification_rejects_truth")
    if stopped is not Stop.NONE:
        return CAUSES.index("search_budget")
    return CAUSES.index("matcher_missed")


# ------------------------------------------------------------------ Dong et al. 4-star run
FOURSTAR_DTYPE = np.dtype(
    [
        ("boresight", np.int32),
        ("n_visible", np.int16),
        ("identified", np.int16),
        ("unidentified", np.int16),
        ("misidentified", np.int16),
        ("groups", np.int16),
        ("time_s", np.float64),
    ]
)


@dataclass(frozen=True)
class FourStarSimConfig:
    """Dong et al. test: 5 deg grid, 12.25 deg radius FOV, tolerance ``epsilon_deg``."""

    step_deg: float = 5.0
    radius_deg: float = 12.25
    epsilon_deg: float = 0.01
    noise_fraction: float = 1.0 / (3.0 * np.sqrt(2.0))  # per-axis sigma = fraction * epsilon
    seed: int = 0
    max_groups: int = 24
    check_consistency: bool = True  # False: the paper's procedure unchanged (no consistency, no resolution)


def run_fourstar(catalog: OnboardCatalog, cfg: FourStarSimConfig, pose_ids: np.ndarray) -> np.ndarray:
    """Evaluate boresights ``pose_ids`` of the Dong et al. grid; returns FOURSTAR_DTYPE rows."""
    boresights = grid_boresights(cfg.step_deg)
    eps = np.radians(cfg.epsilon_deg)
    params = FourStarParams(
        epsilon=eps,
        max_groups=cfg.max_groups,
        check_consistency=cfg.check_consistency,
        resolve_ambiguous=cfg.check_consistency,
    )
    out = np.zeros(len(pose_ids), FOURSTAR_DTYPE)
    for row, pid in enumerate(np.asarray(pose_ids, np.int64)):
        rng = np.random.default_rng([cfg.seed, int(pid)])
        bs = boresights[pid]
        ra, dec = vec_to_radec(bs)
        a = attitude_from_radec_roll(float(ra), float(dec), 0.0)
        idx = catalog.stars_within(bs, np.radians(cfg.radius_deg))
        s = catalog.vec[idx] @ a.T
        s = s + rng.normal(scale=cfg.noise_fraction * eps, size=s.shape)
        s /= np.linalg.norm(s, axis=1, keepdims=True)
        t = time.perf_counter()
        res = match_four_star(s, catalog, eps, params)
        dt = time.perf_counter() - t
        wrong = int(np.sum(idx[res.det] != res.cat))
        out[row] = (pid, len(idx), len(res.det) - wrong, len(idx) - len(res.det), wrong, res.groups, dt)
    return out


# ------------------------------------------------------------------ execution
def _chunks(n: int, size: int):
    return [np.arange(i, min(i + size, n)) for i in range(0, n, size)]


_WORKER: dict = {}


def _init_worker(payload):
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it ends the pool at once
    _WORKER["payload"] = payload


def _run_chunk(kind: str, ids: np.ndarray, payload=None):
    catalog, camera, cfg = payload if payload is not None else _WORKER["payload"]
    if kind == "colour":
        return run_poses(catalog, camera, cfg, ids)
    return run_fourstar(catalog, cfg, ids)


def execute(
    kind: str,
    catalog: OnboardCatalog,
    camera: CameraModel | None,
    cfg,
    n_poses: int,
    workers: int | None = None,
    chunk: int = 500,
    scheduler: str | None = None,
    progress: bool = True,
) -> tuple[np.ndarray, float]:
    """Run all ``n_poses`` of a ``kind`` ("colour" or "fourstar") simulation; returns rows and wall seconds.

    ``workers``: local processes (default: all cores; 1 runs in this process). ``scheduler``: a
    Dask scheduler address, used instead of local processes.
    """
    from tqdm import tqdm

    chunks = _chunks(n_poses, chunk)
    payload = (catalog, camera, cfg)
    t0 = time.perf_counter()
    parts = []
    bar = tqdm(total=n_poses, unit="pose", disable=not progress, desc=f"sim {kind}")
    if scheduler:
        from ground.optional import dask_distributed

        dd = dask_distributed()
        Client, dask_completed = dd.Client, dd.as_completed

        with Client(scheduler) as client:
            remote = client.scatter(payload, broadcast=True)
            futures = [client.submit(_run_chunk, kind, ids, remote, pure=False) for ids in chunks]
            for fut in dask_completed(futures):
                part = fut.result()
                parts.append(part)
                bar.update(len(part))
    elif (workers or os.cpu_count() or 1) <= 1:
        for ids in chunks:
            part = _run_chunk(kind, ids, payload)
            parts.append(part)
            bar.update(len(part))
    else:
        # leaving the with block terminates the workers: after the last chunk, or at once on Ctrl-C;
        # spawned, never forked: a fork of a process with other threads (a device's, a client's)
        # can copy a lock another thread holds, and the worker then waits on it for ever
        context = multiprocessing.get_context(WORKER_START)
        with context.Pool(workers or os.cpu_count(), _init_worker, (payload,)) as pool:
            for part in pool.imap_unordered(partial(_run_chunk, kind), chunks):
                parts.append(part)
                bar.update(len(part))
    bar.close()
    rows: np.ndarray = np.concatenate(parts) if parts else np.zeros(0)
    key = "boresight" if kind == "fourstar" else None
    if key:
        rows = rows[np.argsort(rows[key], kind="stable")]
    else:
        rows = rows[np.lexsort((rows["roll"], rows["boresight"]))]
    return rows, time.perf_counter() - t0


# ------------------------------------------------------------------ summaries and plots
def colour_summary(rows: np.ndarray, poor_fraction: float = 0.4, high_error_deg: float = 1.0) -> dict:
    """Enright & McVittie table 3 breakdown and headline figures of a colour run.

    Problem orientations (exclusive, in this order): no solution; incorrectly matched stars
    (any wrong star, broken down as "wrong of visible"); poor match (fewer than ``poor_fraction``
    of the visible stars matched); high error (> ``high_error_deg`` without a wrong star).
    """
    n = len(rows)
    solved = rows["status"] > 0
    wrong = solved & (rows["n_wrong"] > 0)
    poor = solved & ~wrong & (rows["n_matched"] < poor_fraction * rows["n_visible"])
    high_err = solved & ~wrong & ~poor & (rows["err_deg"] > high_error_deg)
    none = ~solved
    breakdown: dict[str, int] = {}
    for r in rows[wrong]:
        key = f"{int(r['n_wrong'])} of {int(r['n_visible'])}"
        breakdown[key] = breakdown.get(key, 0) + 1
    err = np.where(solved, rows["err_deg"], np.inf)
    high = rows["status"] == 2
    t = rows["time_s"]
    return {
        "poses": n,
        "problem_orientations": int(none.sum() + wrong.sum() + poor.sum() + high_err.sum()),
        "problem_fraction": float((none.sum() + wrong.sum() + poor.sum() + high_err.sum()) / max(n, 1)),
        "no_solution": int(none.sum()),
        "poor_match": int(poor.sum()),
        "incorrect": int(wrong.sum()),
        "high_error_only": int(high_err.sum()),
        "incorrect_breakdown": dict(sorted(breakdown.items(), key=lambda kv: (-kv[1], kv[0]))),
        "high_confidence": int(high.sum()),
        "high_confidence_wrong": int((high & ((rows["n_wrong"] > 0) | (rows["err_deg"] > high_error_deg))).sum()),
        "low_confidence": int((rows["status"] == 1).sum()),
        "low_confidence_wrong": int(((rows["status"] == 1) & (rows["n_wrong"] > 0)).sum()),
        "fraction_within_0.01deg": float(np.mean(err <= 0.01)),
        "fraction_within_1deg": float(np.mean(err <= 1.0)),
        "fewer_than_2_visible": int((rows["n_visible"] < 2).sum()),
        "no_solution_by_cause": {name: int((none & (rows["cause"] == k)).sum()) for k, name in enumerate(CAUSES) if k},
        "solve_ms_p50": float(np.percentile(t, 50) * 1e3) if n else float("nan"),
        "solve_ms_p99": float(np.percentile(t, 99) * 1e3) if n else float("nan"),
        "solve_ms_max": float(t.max() * 1e3) if n else float("nan"),
    }


def fourstar_summary(rows: np.ndarray) -> dict:
    """Dong et al. section 3 counts: stars identified / unidentified / misidentified, FOV success."""
    ok2 = rows["identified"] + rows["misidentified"] >= 2
    return {
        "observations": len(rows),
        "fovs_fewer_than_4_stars": int((rows["n_visible"] < 4).sum()),
        "mean_stars_per_fov": float(rows["n_visible"].mean()) if len(rows) else float("nan"),
        "identified": int(rows["identified"].sum()),
        "unidentified": int(rows["unidentified"].sum()),
        "misidentified": int(rows["misidentified"].sum()),
        "fovs_with_2plus_identified": int((ok2 & (rows["misidentified"] == 0)).sum()),
        "fraction_fovs_2plus_identified": float(np.mean(ok2 & (rows["misidentified"] == 0))) if len(rows) else 0.0,
        "fovs_with_misidentification": int((rows["misidentified"] > 0).sum()),
        "time_ms_p50": float(np.percentile(rows["time_s"], 50) * 1e3) if len(rows) else float("nan"),
        "time_ms_max": float(rows["time_s"].max() * 1e3) if len(rows) else float("nan"),
    }


def plot_error_cdf(rows: np.ndarray, path) -> None:
    """Enright & McVittie fig. 9: cumulative distribution of the attitude error (unsolved poses count as failures)."""
    from ground.optional import pyplot

    plt = pyplot()

    err = np.sort(np.where(rows["status"] > 0, rows["err_deg"], np.inf))
    frac = np.arange(1, len(err) + 1) / max(len(err), 1)
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    finite = np.isfinite(err)
    ax.semilogx(np.maximum(err[finite], 1e-5), frac[finite], lw=1.5)
    for x in (0.01, 1.0):
        ax.axvline(x, color="0.6", ls=":", lw=1)
        ax.text(x, 0.02, f" {np.mean(err <= x) * 100:.2f}% <= {x:g} deg", rotation=90, va="bottom", fontsize=8)
    ax.set_xlabel("attitude error phi_err (deg), eqs 22-23")
    ax.set_ylabel("cumulative fraction of poses")
    ax.set_title(f"Error CDF, {len(rows)} poses (cf. Enright & McVittie fig. 9)")
    ax.set_ylim(0, 1.01)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


#: Worst-result classes per boresight for the map, best to worst.
MAP_CLASSES = ("good", "low confidence (correct)", "poor match", "no solution", "incorrect")


def worst_per_boresight(rows: np.ndarray, n_boresights: int, poor_fraction: float = 0.4) -> np.ndarray:
    """Index into MAP_CLASSES of the worst pose of each boresight."""
    cls = np.zeros(len(rows), np.int8)
    solved = rows["status"] > 0
    cls[solved & (rows["status"] == 1)] = 1
    cls[solved & (rows["n_matched"] < poor_fraction * rows["n_visible"])] = 2
    cls[~solved] = 3
    cls[solved & (rows["n_wrong"] > 0)] = 4
    worst = np.zeros(n_boresights, np.int8)
    np.maximum.at(worst, rows["boresight"], cls)
    return worst


def plot_mollweide(rows: np.ndarray, boresights: np.ndarray, path) -> None:
    """Enright & McVittie fig. 10: worst result per boresight on a Mollweide map (RA increasing left)."""
    from ground.optional import pyplot

    plt = pyplot()

    worst = worst_per_boresight(rows, len(boresights))
    ra, dec = vec_to_radec(boresights)
    lon = -(np.mod(ra + np.pi, 2 * np.pi) - np.pi)  # sky view: RA increases to the left
    fig = plt.figure(figsize=(9, 5))
    ax = fig.add_subplot(111, projection="mollweide")
    colours = ("#b9d9b0", "#4a90d9", "#f0a030", "#808080", "#d62728")
    for k, name in enumerate(MAP_CLASSES):
        m = worst == k
        if m.any():
            ax.scatter(
                lon[m], dec[m], s=2 if k == 0 else 7, c=colours[k], label=f"{name} ({int(m.sum())})", linewidths=0
            )
    ticks = np.radians(np.arange(-150, 151, 30))
    ax.set_xticks(ticks)
    ax.set_xticklabels([f"{int(round(np.degrees(-t) % 360 / 15))}h" for t in ticks])
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.05), ncol=3, fontsize=8, markerscale=2)
    ax.set_title("Worst result per boresight (cf. Enright & McVittie fig. 10)", pad=18)
    save_figure(fig, path, dpi=120, bbox_inches="tight")
    plt.close(fig)
