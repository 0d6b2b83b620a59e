"""``st16-ground colour fit RESULTS.jsonl``: the Enright & McVittie eq. 24 colour correction from the
matched stars of a run, written with the parameter file that ``params upload`` sends."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ground import json_text
from ground.arg_types import output_file
from ground.atomic_write import write_text
from ground.cli.offline_options import load_catalog


def _colour_fit(args) -> int:
    import numpy as np

    from ground.calibration.corrections import ColourCorrection

    cat = load_catalog(args.catalog)
    index = {int(s): k for k, s in enumerate(cat.star_id)}
    obs, ref = [], []
    for line in Path(args.results).read_text().splitlines():
        if not line.strip():
            continue
        rec = json.loads(line)
        for s in rec.get("stars", []):
            k = index.get(s.get("catalog_id"))
            if k is not None and s.get("rg") is not None and s.get("bg") is not None:
                obs.append((s["rg"], s["bg"]))
                ref.append((float(cat.rg[k]), float(cat.bg[k])))
    try:
        fit = ColourCorrection.fit(np.array(obs).reshape(-1, 2), np.array(ref).reshape(-1, 2))
    except ValueError as exc:
        print(f"st16-ground: {exc}", file=sys.stderr)
        return 1
    fit.save(args.output)
    write_text(
        Path(args.output).with_suffix(".params.json"),
        json_text.dumps({"colour_correction": {"beta": [float(b) for b in fit.beta]}}, indent=2),
    )
    print(
        fit.to_json()
        if args.json
        else f"eq. 24 fit on {fit.n_used} stars ({fit.n_rejected} rejected): colour RMS {fit.rms_before:.3f} -> "
        f"{fit.rms_after:.3f}; wrote {args.output} and {Path(args.output).with_suffix('.params.json')}"
    )
    return 0


def register(sub) -> None:
    colour = sub.add_parser("colour", help="field colour calibration (Enright & McVittie eq. 24)")
    csub = colour.add_subparsers(dest="colour_command", metavar="ACTION")
    csub.required = True
    p = csub.add_parser("fit", help="fit eq. 24 from the matched stars of a results log")
    p.add_argument("results", help="results.jsonl of a solve or replay run")
    p.add_argument("--catalog", required=True, help="catalog image the run used")
    p.add_argument(
        "-o",
        "--output",
        type=output_file,
        default="colour_correction.json",
        help="colour correction JSON to write (and its .params.json for params upload)",
    )
    p.set_defaults(func=_colour_fit)
