"""``st16-ground export openc3`` killed with SIGKILL part-way: what it leaves (issue 31).

Prints, for an export into a new directory and for ``--force`` over an existing tree (holding a
file of the user's and ``tlm.txt`` as a directory): the outcome of a kill just before each file
event in turn, and of ``--kills`` kills at random moments over the span in which a clean export
touches the disk. Outcomes: ``absent``, ``old`` (the tree as it was), ``new`` (equal to a clean
export, file for file) or ``partial``; then whether the next run succeeded and left nothing
beside the target. ``--repo DIR`` measures another checkout (e.g. a ``git worktree`` of an older
commit) with the same harness (``tests/export_kill.py``)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import export_kill  # noqa: E402

if __name__ == "__main__":
    export_kill.main()
