"""``st16-ground catalog ...``: build, analyze, plot colours, upload and inspect on-board catalogs."""

from __future__ import annotations

import json
import sys
from dataclasses import fields
from pathlib import Path
from typing import NoReturn

from ground import atomic_write, json_text
from ground.arg_types import SENSOR_PX, InputError, output_file, progress_on, ranged
from ground.catalog.design import CatalogDesign, DesignError
from protocol.commands import Slot

#: CLI flag -> CatalogDesign field
_DESIGN_FLAGS = {
    "theta_fov": "theta_fov_deg",
    "width": "sensor_width_px",
    "height": "sensor_height_px",
    "m_thresh": "m_thresh",
    "m_verify": "m_verify",
    "min_pattern_stars": "min_pattern_stars",
    "sigma_pix": "sigma_pix",
    "sigma_rg": "sigma_rg",
    "sigma_bg": "sigma_bg",
    "p_correct": "p_correct",
    "phi_min": "phi_min_deg",
    "phi_max": "phi_max_deg",
    "n_h": "n_h",
    "epoch": "epoch",
    "source": "source",
    "source_path": "source_path",
    "qe": "qe_path",
    "pickles": "pickles_dir",
    "resolve": "resolve_deg",
    "mk_types": "mk_types_path",
}


_QE_HELP = (
    "detector colour response: a shipped model (mt9p031_like [default, no IR-cut], mt9p031_like_ircut, "
    "em2013 [fitted to Enright & McVittie table 4]) or a CSV wavelength_nm,R,G,B on one step (docs/catalog.md)"
)


def _design_args(p) -> None:
    g = p.add_argument_group("design (flags override --design FILE.toml)")
    g.add_argument("--design", help="TOML design file (keys as in CatalogDesign, top level or [design])")
    g.add_argument("--source", choices=("hipparcos", "bsc5"), help="source star catalog")
    g.add_argument("--source-path", help="catalog file (default: bundled hip2.dat / ../shared BSC5)")
    g.add_argument("--theta-fov", type=float, help="half-angle FOV along the minor axis, deg")
    g.add_argument(
        "--fov-deg",
        type=float,
        help="horizontal field of view across --width, deg: sets theta-fov, "
        "phi-max (the diagonal), m-thresh (~15 stars in view) and m-verify unless given",
    )
    g.add_argument("--width", type=SENSOR_PX, help="sensor width, px")
    g.add_argument("--height", type=SENSOR_PX, help="sensor height, px")
    g.add_argument("--m-thresh", type=float, help="limiting V magnitude of the pattern stars (the pairs)")
    g.add_argument(
        "--m-verify",
        type=float,
        help="limiting V magnitude of verification-only stars (no pairs; matched once an answer is decided); "
        "--fov-deg sets it for ~45 stars in view",
    )
    g.add_argument(
        "--min-pattern-stars",
        type=int,
        help="promote the brightest verification-only stars to pattern stars where fewer than this many lie "
        "within theta-fov of a star (sparse sky); --fov-deg sets 8",
    )
    g.add_argument("--sigma-pix", type=float, help="centroid noise, px")
    g.add_argument("--sigma-rg", type=float, help="colour-ratio noise, rg")
    g.add_argument("--sigma-bg", type=float, help="colour-ratio noise, bg")
    g.add_argument("--p-correct", type=float, help="probability that a true pair passes the match test")
    g.add_argument("--phi-min", type=float, help="deg (default theta_FOV/500)")
    g.add_argument("--phi-max", type=float, help="deg (default 2 theta_FOV)")
    g.add_argument("--n-h", type=int, help="hash index size")
    g.add_argument("--epoch", type=float, help="Julian year of the positions")
    g.add_argument("--qe", help=_QE_HELP)
    g.add_argument("--pickles", help="directory of Pickles .sed spectra")
    g.add_argument("--mk-types", help="BSC5 catalog.dat lending MK types to Hipparcos stars (positional cross-match)")
    g.add_argument("--resolve", type=float, help="double-star merge angle, deg (default phi_min)")
    g.add_argument("--drop-variable", action="store_true", default=None, help="drop variable stars")
    defaults = {f.name: f.default for f in fields(CatalogDesign)}
    for action in g._group_actions:  # the flags default to None ("not given"): show the design's default
        field_name = _DESIGN_FLAGS.get(action.dest)
        default = defaults.get(field_name) if field_name else None
        if default is not None and "default" not in action.help:
            action.help += f" (default: {default}, or the --design file's)"


def design_from_args(args) -> CatalogDesign:
    """The ``CatalogDesign`` of a TOML file (if any) updated with the flags given on the command line."""
    base = CatalogDesign.from_toml(args.design).to_dict() if args.design else {}
    if getattr(args, "fov_deg", None) is not None:
        if not (args.width and args.height):
            raise DesignError("--fov-deg needs --width and --height")
        base.update(CatalogDesign.for_field(args.width, args.height, args.fov_deg).to_dict())
    for flag, name in _DESIGN_FLAGS.items():
        value = getattr(args, flag, None)
        if value is not None:
            base[name] = value
    if args.drop_variable:
        base["drop_variable"] = True
    return CatalogDesign.from_dict(base, origin=args.design or "command line")


def _fail(message: str) -> NoReturn:
    """Bad input: one line, exit 2 (``ground.cli.main``; under ``--json`` its error document too)."""
    raise InputError(message)


def _print(out: dict, as_json: bool) -> None:
    if as_json:
        print(json_text.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k:>22}: {v}")


def _design_errors() -> tuple[type[Exception], ...]:
    """What a bad design, source catalog or colour data raises (imported with the catalog code)."""
    from ground.catalog.colour import ColourDataError
    from ground.catalog.sources import CatalogFormatError

    return DesignError, CatalogFormatError, ColourDataError


def _build(args) -> int:
    from firmware_model.catalog.image_io import catalog_to_image
    from ground.catalog.build import build_catalog, summary
    from protocol.catalog_image import crc32

    try:
        design = design_from_args(args)
        cat = build_catalog(design)
    except _design_errors() as exc:
        return _fail(str(exc))
    image = catalog_to_image(cat)
    try:
        atomic_write.write_bytes(args.output, image)
    except OSError as exc:
        return _fail(f"{args.output}: {exc.strerror}")
    out = {**summary(cat), "image": args.output, "image_bytes": len(image), "image_crc32": f"0x{crc32(image):08X}"}
    _print(out, args.json)
    return 0


def _analyze(args) -> int:
    from ground.catalog.analyze import TABLE_HEADER, analyze, plot_views, table_row
    from ground.catalog.build import build_catalog

    errors: tuple[type[Exception], ...] = (*_design_errors(), ValueError)
    try:
        design = design_from_args(args)
        cat = build_catalog(design)
        res, views, vc, vm = analyze(cat, design, n_views=args.views, progress=progress_on(args), return_views=True)
    except errors as exc:
        return _fail(str(exc))
    if args.json_out:
        atomic_write.write_text(args.json_out, res.to_json() + "\n")
    if args.plot:
        plot_views(
            args.plot,
            views,
            vc,
            vm,
            title=f"{res.source} V<={design.m_thresh} thetaFOV={design.theta_fov_deg} deg: bad views",
        )
    if args.json:
        print(res.to_json())
    else:
        print(TABLE_HEADER)
        print(table_row(res))
        print(
            f"{res.n_stars} stars, Delta* = {res.delta_star:.3f}, sigma_phi = {res.sigma_phi_rad:.3e} rad, {res.n_views} views"
        )
    return 0


def _colours(args) -> int:
    from ground.catalog.colour import ColourDataError, ColourModel, load_qe
    from ground.catalog.colour_plot import plot_colour_ratios

    try:
        qe = load_qe(args.qe)
        model = ColourModel(qe=qe, pickles_dir=Path(args.pickles)) if args.pickles else ColourModel(qe=qe)
        ratios = plot_colour_ratios(model, args.plot)
    except ColourDataError as exc:
        return _fail(str(exc))
    out = {"plot": args.plot, "qe": qe.name, "templates": len(ratios)}
    for lk in (model.bv_lookup, model.vi_lookup):
        out[f"{lk.index}_lookup_range"] = (round(lk.lo, 3), round(lk.hi, 3))
        out[f"{lk.index}_lookup_rms_ln"] = (round(lk.rms_ln[0], 4), round(lk.rms_ln[1], 4))
    _print(out, args.json)
    return 0


def _upload(args) -> int:
    from ground.cli.link import open_client, report_error
    from ground.link.client import LinkError
    from protocol.catalog_image import CatalogImageError, parse_image

    try:
        data = Path(args.file).read_bytes()
    except OSError as exc:
        return _fail(f"{args.file}: {exc.strerror}")
    try:
        parse_image(data)  # refuse locally what the device would refuse
    except CatalogImageError as exc:
        return _fail(f"{args.file}: {exc}")
    with open_client(args) as client:
        try:
            report = client.upload(Slot.CATALOG, data, progress=progress_on(args))
            info = client.slot_info(Slot.CATALOG)
        except LinkError as exc:
            return report_error(exc, args.json)
    if not info.active or info.crc32 != report.crc32 or info.length != len(data):
        return _fail(
            f"device holds length {info.length} CRC-32 0x{info.crc32:08X}, sent {len(data)} 0x{report.crc32:08X}"
        )
    out = {
        "slot": Slot.CATALOG,
        "bytes": len(data),
        "crc32": f"0x{report.crc32:08X}",
        "resumed_from": report.resumed_from,
        "sent": report.sent,
        "seconds": round(report.seconds, 3),
        "verified": True,
    }
    _print(out, args.json)
    return 0


def _info(args) -> int:
    from ground.cli.link import open_client, report_error
    from ground.link.client import LinkError

    with open_client(args) as client:
        try:
            info = client.slot_info(Slot.CATALOG)
        except LinkError as exc:
            return report_error(exc, args.json)
    out = {"active": info.active, "bytes": info.length, "crc32": f"0x{info.crc32:08X}"}
    if info.info:
        try:
            out.update(json.loads(info.info.decode("utf-8")))
        except (UnicodeDecodeError, ValueError):
            out["info_hex"] = info.info.hex()
    _print(out, args.json)
    return 0


def _correction_beta(path: str):
    """The eq. 24 coefficients of ``colour fit -o FILE`` or of its ``.params.json``."""
    from ground.calibration.corrections import ColourCorrection

    try:
        text = Path(path).read_text()
        data = json.loads(text)
        if isinstance(data, dict) and "colour_correction" in data:
            data = {"kind": "colour_correction", **data["colour_correction"]}
        return ColourCorrection.from_json(json.dumps(data)).beta
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"--correction {path}: {exc}") from None


def _learn_colours(args) -> int:
    from ground.analysis.results_log import ResultsLog
    from ground.calibration.learned_colours import learn_image, observations_from_records, plot_learned
    from protocol.catalog_image import CatalogImageError

    if args.upload and not args.port:
        return _fail("learn-colours: --upload needs --port URL")
    results = Path(args.results)
    if results.is_dir():
        results = results / "results.jsonl"
    if not results.is_file():
        return _fail(f"learn-colours: {args.results}: no results log (a results.jsonl or a replay --out directory)")
    try:
        image = Path(args.catalog).read_bytes()
        beta = _correction_beta(args.correction) if args.correction else None
    except OSError as exc:
        return _fail(f"learn-colours: {args.catalog}: {exc.strerror}")
    except ValueError as exc:
        return _fail(f"learn-colours: {exc}")
    log = ResultsLog(results.parent)  # (the directory exists: nothing is created)
    log.jsonl_path = results
    obs = observations_from_records(log.records(), beta=beta)
    try:
        learned, new_image = learn_image(image, obs, prior_rel=args.prior_rel, clip=args.clip, min_obs=args.min_obs)
    except CatalogImageError as exc:
        return _fail(f"learn-colours: {args.catalog}: {exc}")
    report = {**learned.summary(), "stars": [s.to_dict() for s in learned.stars]}
    if args.report:
        atomic_write.write_text(args.report, json_text.dumps(report, indent=2) + "\n")
    if new_image is not None:
        atomic_write.write_bytes(args.output, new_image)
        if args.plot:
            plot_learned(learned, args.plot, f"Learned colours: {results}")
    if args.json:  # one document: what was written, and the patch when --upload sends one
        report["written"] = {
            "image": str(args.output) if new_image is not None else None,
            "report": str(args.report) if args.report else None,
            "plot": str(args.plot) if args.plot and new_image is not None else None,
        }
        if not (args.upload and new_image is not None):
            print(json_text.dumps(report))
    else:
        _print(learned.summary(), False)
        top = sorted(learned.updated, key=lambda s: -max(abs(v) for v in s.shift_sigma))[: args.show]
        if top:
            print(
                f"{'star':>8} {'used':>5} {'rej':>4}  {'rg cat -> learned (sigma)':>30}  {'bg cat -> learned (sigma)':>30}"
            )
        for s in top:
            cells = [
                f"{s.catalog[k]:.3f} -> {s.learned[k]:.3f} ({s.sigma[k]:.3f}) {s.shift_sigma[k]:+6.1f}s" for k in (0, 1)
            ]
            print(f"{s.star_id:>8} {s.n_used:>5} {s.n_rejected:>4}  {cells[0]:>30}  {cells[1]:>30}")
        if new_image is not None:
            print(f"wrote {args.output} ({len(new_image)} bytes, {len(learned.updated)} stars' colours learned)")
    if new_image is None:
        print(f"st16-ground catalog: learn-colours: {learned.reason}; no image written", file=sys.stderr)
        return 1
    return _upload_patch(args, image, new_image, report) if args.upload else 0


def _upload_patch(args, old: bytes, new: bytes, report: dict) -> int:
    """Send only the bytes ``new`` changes to the device's catalog (slot 3 patches slot 0 at COMMIT),
    after checking that the device holds ``old``; verify the result. Under ``--json`` prints
    ``report`` with the patch sent (``"patch"``): the command's one document."""
    from ground.cli.link import open_client, report_error
    from ground.link.client import LinkError
    from protocol.catalog_image import crc32
    from protocol.catalog_patch import diff_ranges, make_patch

    patch = make_patch(old, new)
    with open_client(args) as client:
        try:
            held = client.slot_info(Slot.CATALOG)
            if not held.active or held.crc32 != crc32(old):
                return _fail(
                    f"learn-colours: the device holds catalog CRC-32 0x{held.crc32:08X}, not {args.catalog} "
                    f"(0x{crc32(old):08X}) the colours were learned for: nothing sent"
                )
            sent = client.upload(Slot.CATALOG_PATCH, patch, progress=progress_on(args))
            info = client.slot_info(Slot.CATALOG)
        except LinkError as exc:
            return report_error(exc, args.json)
    if not info.active or info.crc32 != crc32(new) or info.length != len(new):
        return _fail(
            f"learn-colours: device catalog CRC-32 0x{info.crc32:08X} after the patch, want 0x{crc32(new):08X}"
        )
    ranges = len(diff_ranges(old, new))
    if args.json:
        patched = {"bytes": len(patch), "ranges": ranges, "image_bytes": len(new), "seconds": sent.seconds}
        print(json_text.dumps({**report, "patch": {**patched, "crc32": f"0x{info.crc32:08X}", "verified": True}}))
    else:
        print(
            f"patched the device's catalog: {len(patch)} bytes sent in {ranges} ranges "
            f"(the image is {len(new)}), {sent.seconds:.2f} s; CRC-32 0x{info.crc32:08X} verified"
        )
    return 0


def register(sub) -> None:
    cat = sub.add_parser("catalog", help="build, analyze, upload and inspect on-board star catalogs")
    csub = cat.add_subparsers(dest="catalog_command", metavar="ACTION")
    csub.required = True

    p = csub.add_parser("build", help="build a catalog image from a design")
    _design_args(p)
    p.add_argument("-o", "--output", type=output_file, default="catalog.st16cat", help="image file to write")
    p.set_defaults(func=_build)

    p = csub.add_parser("analyze", help="Enright & McVittie table 1: ambiguity and availability of a design")
    _design_args(p)
    p.add_argument("--views", type=int, default=100_000, help="boresights on the generalized spiral")
    p.add_argument("--json-out", type=output_file, help="write the result as JSON")
    p.add_argument("--plot", type=output_file, help="write a Mollweide PNG of bad/unresolvable views")
    p.set_defaults(func=_analyze)

    p = csub.add_parser("colours", help="plot colour ratios against spectral type (Enright & McVittie fig. 7)")
    p.add_argument("--qe", help=_QE_HELP)
    p.add_argument("--pickles", help="directory of Pickles .sed spectra")
    p.add_argument(
        "-o", "--output", "--plot", dest="plot", type=output_file, default="colour_ratios.png", help="PNG to write"
    )
    p.set_defaults(func=_colours)

    p = csub.add_parser("upload", help="upload an image to the device (resumable), verify CRC-32, commit")
    p.add_argument("file", help="catalog image (catalog build -o)")
    p.set_defaults(func=_upload)

    p = csub.add_parser(
        "learn-colours",
        help="learn each star's colour ratios from the matched stars of a run (docs/learned_colours.md)",
    )
    p.add_argument("results", help="results.jsonl of a solve or replay run, or the replay --out directory")
    p.add_argument("--catalog", required=True, help="catalog image the run used")
    p.add_argument("--correction", help="the eq. 24 correction the run used (colour fit -o FILE or its .params.json)")
    p.add_argument("-o", "--output", type=output_file, default="learned.st16cat", help="catalog image to write")
    p.add_argument("--report", type=output_file, help="write the per-star report as JSON")
    p.add_argument("--plot", type=output_file, help="write a PNG of catalog against learned rg and bg")
    p.add_argument(
        "--prior-rel",
        type=ranged(float, 1e-4, 10.0, "--prior-rel"),
        default=0.05,
        help="prior sigma of a catalog ratio, relative to it",
    )
    p.add_argument(
        "--clip",
        type=ranged(float, 1.0, 100.0, "--clip"),
        default=3.0,
        help="outlier threshold, normalised 2-D distance from the star's estimate",
    )
    p.add_argument(
        "--min-obs",
        type=ranged(int, 1, 10**6, "--min-obs"),
        default=3,
        help="fewest kept observations that update a star",
    )
    p.add_argument(
        "--show", type=ranged(int, 0, 10**6, "--show"), default=10, help="stars printed, largest shift first"
    )
    p.add_argument(
        "--upload",
        action="store_true",
        help="then patch the device's catalog (--port): only the changed bytes, applied at once and verified",
    )
    p.set_defaults(func=_learn_colours)

    p = csub.add_parser("info", help="what catalog the device holds")
    p.set_defaults(func=_info)
