"""Two heads, one swept past the Sun: flight-side head selection (issue 45; ground/hil/two_heads.py).

    .venv/bin/python bench/bench_two_heads_sun.py [--out DIR]

Starts ``st16-device --heads --sky`` on the sweep's body schedule, runs the lockstep selection and
prints each row (each head's status, the head selected, its error) and the verdict; writes
``two_heads.png`` and ``two_heads.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("two_heads_out"))
    args = ap.parse_args()

    from firmware_model.catalog.image_io import catalog_to_image
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.hil import two_heads
    from ground.sim.device_process import start_device, stop_device

    image = catalog_to_image(build_catalog(CatalogDesign()))
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        heads, schedule, rows = two_heads.write_inputs(work)
        proc, pty = start_device(work / "state", "--heads", str(heads), "--sky", str(schedule))
        try:
            out = two_heads.run(pty, rows, image)
        finally:
            stop_device(proc)
    for r in out:
        err = "-" if r["error_arcsec"] is None else f"{r['error_arcsec']:.1f}"
        print(
            f"row {r['row']:>2}  0x0E {r['status']['0x0E']:<14} 0x0F {r['status']['0x0F']:<14} selected {r['selected']}  error {err} arcsec"
        )
    ok, text = two_heads.verdict(out)
    print(text)
    (args.out / "two_heads.json").write_text(json.dumps(out, indent=1))
    two_heads.plot(out, args.out / "two_heads.png")
    print(f"wrote {args.out / 'two_heads.png'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
