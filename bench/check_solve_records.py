"""Behaviour check for refactors of the in-process solve: the 15 real frames in
../shared/data/frames solved with ``ground.api.solve_image`` in the four modes (the field of view
as the hint, blind, the hint x0.75 and x1.25), and the tetra3 frames as the device's twin (the
datasheet camera and a ``CatalogDesign.for_field`` catalog object) before and after a
field-of-view search has used the same catalog object; every record written without its timings.

    .venv/bin/python bench/check_solve_records.py --write out/records-before.json
    .venv/bin/python bench/check_solve_records.py --compare out/records-before.json

``--compare`` prints each record that differs (frame, mode, the first differing fields) and exits
1 when any does. Timings, and the seconds the search report counts, are left out: they are the
only fields a refactor may move.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from jsonl_worker import SINGLE_THREAD  # noqa: E402  (standard library only)

for _name, _value in SINGLE_THREAD.items():
    os.environ.setdefault(_name, _value)

from bench_realframes import DATA, frames  # noqa: E402

MODES: dict[str, float | None] = {"fov": 1.0, "blind": None, "x0.75": 0.75, "x1.25": 1.25}
TIMING_KEYS = {"timings_s", "setup_s", "wall_s", "elapsed_s", "seconds"}


def untimed(value: Any) -> Any:
    """``value`` with every timing field removed, floats rounded to 9 significant digits."""
    if isinstance(value, dict):
        return {k: untimed(v) for k, v in value.items() if k not in TIMING_KEYS and not k.endswith("_ms")}
    if isinstance(value, (list, tuple)):
        return [untimed(v) for v in value]
    if isinstance(value, float):
        return float(f"{value:.9g}")
    return value


def records() -> dict[str, Any]:
    """Every frame in every mode, then the twin before and after a field-of-view search."""
    from ground.api import solve_image

    out: dict[str, Any] = {}
    jobs = frames()
    for job in jobs:
        for mode, factor in MODES.items():
            kw = {} if factor is None else {"fov_deg": factor * job["fov"]}
            s = solve_image(str(job["path"]), **kw)
            out[f"{job['path'].name}/{mode}"] = untimed(s.record)
            print(f"{job['path'].name:32s} {mode:6s} {s.status}", flush=True)
    tetra3 = [j for j in jobs if j["set"] == "tetra3"]
    if tetra3:
        from firmware_model.camera import CameraModel
        from firmware_model.pipeline.frame_readers import read_frame
        from ground.catalog.field_catalogs import catalog_for_field

        frame = read_frame(tetra3[0]["path"])
        camera = CameraModel.from_focal(frame.width, frame.height, *tetra3[0]["datasheet"])
        catalog = catalog_for_field(frame.width, frame.height, tetra3[0]["fov"])
        first, other = tetra3[0], tetra3[1]
        for label in ("twin-before", None, "twin-after"):
            if label is None:  # a field-of-view search on the same catalog object
                solve_image(str(other["path"]), catalog=catalog, fov_deg=other["fov"])
                continue
            s = solve_image(str(first["path"]), camera=camera, catalog=catalog)
            out[f"{first['path'].name}/{label}"] = untimed(s.record)
            print(f"{first['path'].name:32s} {label:12s} {s.status}", flush=True)
    return out


def diff(a: Any, b: Any, path: str = "") -> list[str]:
    """The paths where ``a`` and ``b`` differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        found = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                found.append(f"{path}/{k}: only in {'after' if k not in a else 'before'}")
            else:
                found += diff(a[k], b[k], f"{path}/{k}")
        return found
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in diff(x, y, f"{path}[{i}]")]
    return [] if a == b else [f"{path}: {a!r} -> {b!r}"[:200]]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    group = ap.add_mutually_exclusive_group(required=True)
    group.add_argument("--write", type=Path, help="write the records to this JSON file")
    group.add_argument("--compare", type=Path, help="compare the records with this JSON file")
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"check_solve_records: no frames under {DATA}", file=sys.stderr)
        return 2
    if args.compare is not None and not args.compare.is_file():
        print(f"check_solve_records: {args.compare}: no such file", file=sys.stderr)
        return 2
    now = records()
    if args.write is not None:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(json.dumps(now, indent=1, sort_keys=True))
        print(f"{len(now)} records written to {args.write}")
        return 0
    before = json.loads(args.compare.read_text())
    changed = {key: d for key in sorted(set(before) | set(now)) if (d := diff(before.get(key), now.get(key)))}
    for key, found in changed.items():
        print(f"DIFFERS {key}: {len(found)} field(s): " + "; ".join(found[:4]))
    print(f"{len(now)} records; {len(changed)} differ from {args.compare}")
    return 1 if changed else 0


if __name__ == "__main__":
    sys.exit(main())
