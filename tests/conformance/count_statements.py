"""Counts the ICD statements of docs/conformance.md: those checked by a test of the suite, and
those not checkable from the public pages. ``python tests/conformance/count_statements.py``."""

from __future__ import annotations

import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
_TEST = re.compile(r"`(test_conf_\w+)`")


def statements(path: Path) -> list[dict]:
    """The rows of the tables in ``path``: ``| id | page | statement | test(s) or 'not checkable:
    why' |``, id ``S<n>`` for a statement of the ICD pages, ``O<n>`` for one of our choices where
    the pages are silent; each row's ``kind`` (S or O), ``tests`` (names in backticks), ``why``."""
    rows = []
    for line in path.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 4 or not re.fullmatch(r"[SO]\d+", cells[0]):
            continue
        unchecked = cells[3].lower().startswith("not checkable")
        tests = [] if unchecked else _TEST.findall(cells[3])
        why = cells[3] if unchecked else ""
        if not tests and not unchecked:
            raise ValueError(f"{cells[0]}: neither a test nor 'not checkable': {cells[3]!r}")
        rows.append(
            {"id": cells[0], "kind": cells[0][0], "page": cells[1], "statement": cells[2], "tests": tests, "why": why}
        )
    return rows


def main() -> int:
    everything = statements(REPO / "docs" / "conformance.md")
    rows = [r for r in everything if r["kind"] == "S"]
    ours = [r for r in everything if r["kind"] == "O"]
    checked = [r for r in rows if r["tests"]]
    print(
        f"ICD statements: {len(rows)}; checked by the suite: {len(checked)}; not checkable: {len(rows) - len(checked)}"
    )
    print(f"our choices where the pages are silent: {len(ours)}; checked: {sum(1 for r in ours if r['tests'])}")
    for r in everything:
        if not r["tests"]:
            print(f"  {r['id']} ({r['page']}): {r['why']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
