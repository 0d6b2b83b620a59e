"""Two heads, one swept past the Sun: flight-side head selection (issue 45; ground/hil/two_heads.py).

    .venv/bin/python bench/bench_two_heads_sun.py [--out DIR]

Starts ``st16-device --heads --sky`` on the sweep's body schedule, runs the lockstep selection and
prints each row (each head's status, the head selected, its error) and the verdict; writes
``two_heads.png`` and ``two_heads.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("two_heads_out"))
    args = ap.parse_args()

    from ground.hil import two_heads

    ok = two_heads.run_scenario(args.out)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
