"""``st16-ground sim ...``: whole-sky identification simulations (Enright & McVittie and Dong et al.).

``sim colour``: spiral boresights x rolls on the reference array, Enright & McVittie eqs 19-21 noise; prints
the table 3 breakdown next to the paper's figures and writes rows (.npy), summary (.json), the
error CDF (fig. 9) and the Mollweide map (fig. 10); ``--true-colours``, ``--gain-error`` and
``--scintillation`` observe colours the catalog did not predict (open loop). ``sim fourstar``: Dong et al.'s 5 deg grid at one or
more tolerances. Both run on local cores (``--workers``) or a Dask cluster (``--scheduler``).
``sim availability``: rendered frames at seeded random attitudes over the real sky with detector
effects over a mission (radiation hits, the South Atlantic Anomaly, dose, temperature), solved by the
pipeline; prints availability, correct, high-confidence wrong, low confidence and no solution.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ground import json_text
from ground.arg_types import (
    DOSE_KRAD,
    FLUX_PER_CM2_S,
    HITS_PER_FRAME,
    SEED,
    SENSOR_PX,
    InputError,
    progress_on,
    ranged,
)
from ground.atomic_write import atomic_path, write_text
from ground.optional import MissingExtra

log = logging.getLogger(__name__)

#: Open-loop colour impairments (``ground.sim.true_colours`` bounds), refused before any work.
GAIN_ERROR = ranged(float, 0.0, 0.5, "a gain error")
SCINTILLATION = ranged(float, 0.0, 1.0, "a scintillation sigma")
#: ``sim availability``: frames, exposure (ms) and the detector's duty cycle (fraction busy).
ATTITUDES = ranged(int, 1, 1_000_000, "a number of attitudes")
EXPOSURE_MS = ranged(float, 0.01, 60_000.0, "an exposure in ms")
DUTY = ranged(float, 0.0, 1.0, "a duty cycle")


#: ``--temperature-c`` (degC): ``detector_effects.TEMPERATURE_RANGE_C``, not imported here so that
#: ``--help`` stays fast (scipy, astropy); a test keeps the two equal.
TEMPERATURE_RANGE_C = (-40.0, 85.0)
TEMPERATURE_C = ranged(float, *TEMPERATURE_RANGE_C, "a detector temperature in degC")

#: Enright & McVittie section 5.2 (table 3, fig. 9) for 1e6 poses.
PAPER_COLOUR = {
    "poses": 1_000_000,
    "problem_orientations": 7078,
    "no_solution": 897,
    "poor_match": 1763,
    "incorrect": 4418,
    "fraction_within_0.01deg": 0.90,
    "fraction_within_1deg": 0.993,
}
#: Dong et al. section 3 (2664 observations).
PAPER_FOURSTAR = {
    "observations": 2664,
    "fovs_fewer_than_4_stars": 2,
    "mean_stars_per_fov": 17.5,
    "misidentified": 0,
    "fraction_fovs_2plus_identified": 2662 / 2664,
}


def _common(p) -> None:
    p.add_argument("--seed", type=SEED, default=0, help="random seed (each pose has its own stream)")
    p.add_argument("--workers", type=int, default=None, help="local processes (default: all cores)")
    p.add_argument("--chunk", type=int, default=500, help="poses per task")
    p.add_argument("--scheduler", help="Dask scheduler address (tcp://host:8786) instead of local processes")
    p.add_argument("-o", "--output", "--out", dest="out", type=Path, help="directory for rows, summary and plots")
    p.add_argument("--source", choices=("hipparcos", "bsc5"), default="hipparcos", help="source catalog")


def register(subparsers) -> None:
    sim = subparsers.add_parser("sim", help="whole-sky identification simulations")
    sub = sim.add_subparsers(dest="sim_command", metavar="KIND")
    sub.required = True
    c = sub.add_parser("colour", help="Enright & McVittie colour consensus matching over the whole sky")
    c.add_argument("--boresights", type=int, default=10000, help="spiral boresight directions")
    c.add_argument("--rolls", type=int, default=10, help="roll angles per boresight")
    c.add_argument("--m-thresh", type=float, default=5.0, help="limiting V magnitude")
    c.add_argument("--theta-fov", type=float, default=7.5, help="half FOV on the minor axis, deg")
    c.add_argument("--width", type=SENSOR_PX, default=2592, help="sensor width, px")
    c.add_argument("--height", type=SENSOR_PX, default=1944, help="sensor height, px")
    c.add_argument("--sigma-pix", type=float, default=0.2, help="centroid noise, px")
    c.add_argument("--sigma-colour", type=float, default=0.05, help="colour-ratio noise")
    c.add_argument("--false-stars", type=float, default=0.0, help="mean false detections per frame")
    c.add_argument("--drop", type=float, default=0.0, help="probability of missing a true star")
    c.add_argument(
        "--mono",
        action="store_true",
        help="mono frames, solved as the device does: geometric (4-star, triangle) matching, then consensus on geometry alone",
    )
    c.add_argument(
        "--true-colours",
        choices=("catalog", "blackbody"),
        default="catalog",
        help="where the observed colours come from: the catalog's own (closed loop) or a Planck "
        "spectrum at the Ballesteros T(B-V) through the catalog's QE",
    )
    c.add_argument(
        "--gain-error",
        type=GAIN_ERROR,
        default=0.0,
        help="per-frame channel gain error: g_r/g_g and g_b/g_g each 1 +- this (random sign), 0-0.5",
    )
    c.add_argument(
        "--scintillation",
        type=SCINTILLATION,
        default=0.0,
        help="per-star, per-channel log-normal signal sigma (fraction), 0-1",
    )
    _common(c)
    c.set_defaults(func=run_colour)
    f = sub.add_parser("fourstar", help="Dong et al. 4-star matching test on a 5 deg grid")
    f.add_argument("--step", type=float, default=5.0, help="grid step, deg")
    f.add_argument("--radius", type=float, default=12.25, help="FOV radius, deg")
    f.add_argument("--m-thresh", type=float, default=5.0, help="limiting V magnitude")
    f.add_argument("--epsilon", type=float, nargs="+", default=[0.005, 0.01], help="tolerance(s), deg")
    f.add_argument("--paper", action="store_true", help="the paper's procedure without the consistency check")
    _common(f)
    f.set_defaults(func=run_fourstar)
    a = sub.add_parser(
        "availability",
        help="rendered frames at random attitudes with detector effects over a mission, solved by the pipeline",
    )
    a.add_argument("--attitudes", type=ATTITUDES, default=100, help="frames (seeded random attitudes), 1-1e6")
    a.add_argument("--seed", type=SEED, default=0, help="random seed (each frame has its own stream)")
    a.add_argument("--exposure-ms", type=EXPOSURE_MS, default=100.0, help="exposure, ms (0.01-60000)")
    hits = a.add_mutually_exclusive_group()
    hits.add_argument(
        "--cosmic-rate",
        type=FLUX_PER_CM2_S,
        default=0.0,
        help="radiation flux, particles per cm^2 per s on the array (0-1e6; hits per frame are Poisson)",
    )
    hits.add_argument("--hits-per-frame", type=HITS_PER_FRAME, help="mean radiation hits per frame instead (0-1e5)")
    a.add_argument(
        "--saa",
        action="store_true",
        help="raise the flux inside a coarse South Atlantic Anomaly of the sub-satellite point (frames spread "
        "over one day of --orbit)",
    )
    a.add_argument(
        "--orbit",
        default="550",
        help="circular orbit for --saa: ALT_KM[,INC_DEG[,RAAN_DEG[,ARG_LAT_DEG[,EPOCH_UTC]]]] (default: 550 km, 97.6 deg)",
    )
    a.add_argument(
        "--dose-krad", type=DOSE_KRAD, default=0.0, help="total dose, krad(Si): hot pixels grow with it (0-1e4)"
    )
    temp = a.add_mutually_exclusive_group()
    temp.add_argument(
        "--temperature-c",
        type=TEMPERATURE_C,
        help=f"detector temperature, degC ({TEMPERATURE_RANGE_C[0]:g} to {TEMPERATURE_RANGE_C[1]:g}): dark current "
        "doubles every 6.5 degC from the detector model's value at 20 degC",
    )
    temp.add_argument(
        "--duty", type=DUTY, help="detector temperature from the housekeeping model at this duty cycle (0-1)"
    )
    a.add_argument("--workers", type=ranged(int, 1, 256, "a number of workers"), default=1, help="local processes")
    a.add_argument("-o", "--output", "--out", dest="out", type=Path, help="directory for rows and summary (JSON)")
    a.set_defaults(func=run_availability)


def _emit(args, payload: dict, text: str) -> None:
    if getattr(args, "json", False):
        print(json_text.dumps(payload, indent=2))
    else:
        print(text)


def run_colour(args) -> int:
    import numpy as np

    from firmware_model.camera import CameraModel
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign, DesignError
    from ground.sim import whole_sky as skysim
    from ground.sim.true_colours import TrueColours

    try:
        design = CatalogDesign(
            theta_fov_deg=args.theta_fov,
            sensor_width_px=args.width,
            sensor_height_px=args.height,
            m_thresh=args.m_thresh,
            sigma_pix=args.sigma_pix,
            sigma_rg=args.sigma_colour,
            sigma_bg=args.sigma_colour,
            source=args.source,
        )
        if args.boresights < 2 or args.rolls < 1:
            raise DesignError("need --boresights >= 2 and --rolls >= 1")
    except (DesignError, ValueError) as exc:
        raise InputError(str(exc)) from None
    catalog = build_catalog(design)
    camera = CameraModel.from_fov(args.width, args.height, args.theta_fov)
    cfg = skysim.ColourSimConfig(
        n_boresights=args.boresights,
        n_roll=args.rolls,
        seed=args.seed,
        colour=not args.mono,
        model=skysim.ErrorModel(
            args.sigma_pix,
            args.sigma_colour,
            args.false_stars,
            args.drop,
            TrueColours(args.true_colours, args.gain_error, args.scintillation),
        ),
    )
    n = args.boresights * args.rolls
    rows, wall = skysim.execute(
        "colour",
        catalog,
        camera,
        cfg,
        n,
        workers=args.workers,
        chunk=args.chunk,
        scheduler=args.scheduler,
        progress=progress_on(args),
    )
    summary = skysim.colour_summary(rows)
    summary.update(
        poses_per_second=n / wall,
        wall_seconds=wall,
        catalog_stars=catalog.n_stars,
        catalog_pairs=catalog.n_pairs,
        true_colours=args.true_colours,
        gain_error=args.gain_error,
        scintillation=args.scintillation,
        workers=args.workers,
        scheduler=args.scheduler,
    )
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        with atomic_path(args.out / "colour_rows.npy") as tmp, open(tmp, "wb") as f:
            np.save(f, rows)
        write_text(args.out / "colour_summary.json", json_text.dumps(summary, indent=2))
        try:
            skysim.plot_error_cdf(rows, args.out / "error_cdf.png")
            skysim.plot_mollweide(rows, skysim.spiral_boresights(args.boresights), args.out / "problem_map.png")
        except MissingExtra as exc:  # rows and summary are written; only the pictures are missing
            log.warning("st16-ground: plots skipped: %s", exc)
    lines = [
        f"{n} poses ({args.boresights} boresights x {args.rolls} rolls), {catalog.n_stars} stars, "
        f"{catalog.n_pairs} pairs; {wall:.1f} s, {n / wall:.0f} poses/s",
        f"true colours: {args.true_colours}, gain error {args.gain_error:g}, scintillation {args.scintillation:g}",
        f"{'':32s}{'this run':>14s}{'paper (1e6)':>16s}",
    ]
    for key in ("problem_orientations", "no_solution", "poor_match", "incorrect"):
        lines.append(f"{key:32s}{summary[key] / n * 100:13.3f}%{PAPER_COLOUR[key] / 1e4:15.3f}%")
    for key in ("fraction_within_0.01deg", "fraction_within_1deg"):
        lines.append(f"{key:32s}{summary[key] * 100:13.2f}%{PAPER_COLOUR[key] * 100:15.2f}%")
    lines.append(
        f"{'high confidence (wrong)':32s}{summary['high_confidence']:>8d} ({summary['high_confidence_wrong']})"
    )
    lines.append(f"{'low confidence (wrong)':32s}{summary['low_confidence']:>8d} ({summary['low_confidence_wrong']})")
    lines.append(f"incorrect breakdown (wrong of visible): {summary['incorrect_breakdown']}")
    lines.append("no solution by cause (availability loss):")
    for key, count in summary["no_solution_by_cause"].items():
        lines.append(f"  {key:30s}{count:8d}{count / n * 100:13.3f}%")
    lines.append(
        f"solve time ms p50/p99/max: {summary['solve_ms_p50']:.3f} / {summary['solve_ms_p99']:.3f} / "
        f"{summary['solve_ms_max']:.3f}"
    )
    _emit(args, summary, "\n".join(lines))
    return 0


def run_fourstar(args) -> int:
    import numpy as np

    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign, DesignError
    from ground.sim import whole_sky as skysim

    try:
        design = CatalogDesign(
            theta_fov_deg=args.radius,
            sensor_width_px=1024,
            sensor_height_px=1024,
            m_thresh=args.m_thresh,
            phi_min_deg=0.05,
            phi_max_deg=2 * args.radius,
            source=args.source,
        )
    except (DesignError, ValueError) as exc:
        raise InputError(str(exc)) from None
    catalog = build_catalog(design)
    n = len(skysim.grid_boresights(args.step))
    results, lines = (
        {},
        [f"{n} observations, {catalog.n_stars} stars, {catalog.n_pairs} pairs (paper: 2664, 1631, 65890)"],
    )
    for eps in args.epsilon:
        cfg = skysim.FourStarSimConfig(
            step_deg=args.step,
            radius_deg=args.radius,
            epsilon_deg=eps,
            seed=args.seed,
            check_consistency=not args.paper,
        )
        rows, wall = skysim.execute(
            "fourstar",
            catalog,
            None,
            cfg,
            n,
            workers=args.workers,
            chunk=args.chunk,
            scheduler=args.scheduler,
            progress=progress_on(args),
        )
        s = skysim.fourstar_summary(rows)
        s.update(epsilon_deg=eps, wall_seconds=wall, fovs_per_second=n / wall)
        results[str(eps)] = s
        if args.out:
            args.out.mkdir(parents=True, exist_ok=True)
            with atomic_path(args.out / f"fourstar_rows_eps{eps:g}.npy") as tmp, open(tmp, "wb") as f:
                np.save(f, rows)
        lines.append(
            f"eps {eps:g} deg: identified {s['identified']}, unidentified {s['unidentified']}, "
            f"misidentified {s['misidentified']} (paper 0); FOVs with >= 2 identified "
            f"{s['fovs_with_2plus_identified']}/{n} = {s['fraction_fovs_2plus_identified'] * 100:.2f}% "
            f"(paper 99.9%); FOVs < 4 stars {s['fovs_fewer_than_4_stars']} (paper 2); "
            f"mean stars {s['mean_stars_per_fov']:.1f} (paper 17.5); {n / wall:.0f} FOV/s"
        )
    if args.out:
        write_text(args.out / "fourstar_summary.json", json_text.dumps(results, indent=2))
    _emit(args, results, "\n".join(lines))
    return 0


def run_availability(args) -> int:
    from ground.sim import availability as av
    from ground.sim.detector_effects import CosmicRays, MissionEffects, SouthAtlanticAnomaly
    from ground.sim.orbit import CircularOrbit

    try:
        orbit = CircularOrbit.parse(args.orbit) if args.saa else None
    except ValueError as exc:
        raise InputError(f"--orbit: {exc}") from None
    flux, hits = args.cosmic_rate, args.hits_per_frame
    cosmic = None
    if flux > 0 or hits is not None or args.saa:
        cosmic = CosmicRays(flux_cm2_s=flux, hits_per_frame=hits, saa=SouthAtlanticAnomaly() if args.saa else None)
    effects = MissionEffects(
        cosmic=cosmic, dose_krad=args.dose_krad, temperature_c=args.temperature_c, duty=args.duty, orbit=orbit
    )
    cfg = av.AvailabilityConfig(
        n_attitudes=args.attitudes,
        seed=args.seed,
        exposure_s=args.exposure_ms / 1000.0,
        start_posix=orbit.epoch_posix if orbit else None,
        spacing_s=86400.0 / args.attitudes,
    )
    if args.out and args.out.exists() and not args.out.is_dir():
        raise InputError(f"-o {args.out}: a file, not a directory")
    rows = av.run_availability(cfg, [effects], workers=args.workers, progress=progress_on(args))
    summary = av.summarise(rows)
    summary["config"] = {
        "attitudes": args.attitudes,
        "seed": args.seed,
        "exposure_ms": args.exposure_ms,
        "cosmic_rate_per_cm2_s": flux,
        "hits_per_frame": hits,
        "saa": args.saa,
        "orbit": args.orbit if args.saa else None,
        "dose_krad": args.dose_krad,
        "temperature_c": effects.temperature(),
        "duty": args.duty,
    }
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        write_text(args.out / "availability_rows.json", json_text.dumps(rows, indent=1))
        write_text(args.out / "availability_summary.json", json_text.dumps(summary, indent=2))
    _emit(args, summary, av.summary_table(summary))
    return 0
