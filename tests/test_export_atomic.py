"""``st16-ground export`` puts its output in place whole or not at all (ground/export/staging.py):
killed (SIGKILL) at any file event or at random moments it leaves no target or a whole one,
``--force`` replaces a target whole (never merges into it), and the next run removes what a
killed run left beside the target. ``tests/export_kill.py`` is the harness (and, with
``bench/bench_export_kill.py``, the bench of the figures)."""

import signal
import subprocess
import sys

import export_kill
from conftest import required

from ground.cli.main import main
from ground.export import staging


def _dead_pid() -> int:
    """The pid of a process that has ended."""
    return int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True).stdout)


def test_a_kill_at_any_file_event_leaves_no_target_or_a_whole_one(tmp_path):
    """--force over a tree holding a file of the user's and tlm.txt as a directory, killed just
    before each file event in turn: the old tree as it was, no target (between the two renames)
    or the new one, never a mix; the next run succeeds and leaves nothing beside the target."""
    required("openc3")
    records = export_kill.kill_at_each_event(tmp_path, force=True, fast=True)
    killed = [r for r in records if r["killed"]]
    assert records[-1]["rc"] == 0 and records[-1]["state"] == "new" and records[-1]["siblings"] == []
    assert len(killed) >= 10
    assert {r["state"] for r in killed} == {"old", "absent", "new"}, records  # every phase was cut
    for r in killed:
        assert r["state"] in ("old", "absent", "new"), r
        assert (r["next_rc"], r["next_state"], r["next_siblings"]) == (0, "new", []), r
    assert any(r["siblings"] for r in killed)  # the kills did leave staging siblings, and they went


def test_kill_9_at_random_moments_leaves_no_target_or_a_whole_one(tmp_path):
    required("openc3")
    records = export_kill.kill_at_random(tmp_path, kills=5, seed=31)
    # a run in which no kill landed (every export finished first) proves nothing: it fails
    assert any(r["killed"] for r in records), f"no kill landed: {records}"
    for r in records:
        assert r["rc"] in (0, -signal.SIGKILL), r
        assert r["state"] in ("absent", "new"), r
        assert (r["next_rc"], r["next_state"], r["next_siblings"]) == (0, "new", []), r


def test_force_replaces_the_whole_target_and_never_merges(tmp_path, capsys):
    required("openc3")
    fresh = tmp_path / "fresh"
    assert main(["export", "openc3", str(fresh)]) == 0
    old = export_kill.old_tree(tmp_path, fresh)  # tlm.txt a directory, a file of the user's
    target = tmp_path / "target"
    old.rename(target)
    assert main(["export", "openc3", str(target)]) == 2  # refused without --force, untouched
    assert (target / "mine.txt").exists()
    capsys.readouterr()
    assert main(["export", "openc3", str(target), "--force"]) == 0
    assert export_kill.tree(target) == export_kill.tree(fresh)  # tlm.txt a file again, mine.txt gone
    assert export_kill.siblings(target) == []
    # a file where the directory goes is replaced too, with --force
    (tmp_path / "file").write_text("x")
    assert main(["export", "openc3", str(tmp_path / "file")]) == 2
    assert main(["export", "openc3", str(tmp_path / "file"), "--force"]) == 0
    assert export_kill.tree(tmp_path / "file") == export_kill.tree(fresh)


def test_siblings_of_dead_runs_are_removed_and_a_running_ones_kept(tmp_path):
    required("yamcs.pymdb")
    out = tmp_path / "st16.xml"
    dead, alive = _dead_pid(), subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        stale_dir = tmp_path / f".st16.xml{staging.MARK}{dead}-0a1b.new"
        stale_dir.mkdir()
        (stale_dir / "half").write_text("x")
        stale_file = tmp_path / f".st16.xml{staging.MARK}{dead}-2c3d.old"
        stale_file.write_text("x")
        running = tmp_path / f".st16.xml{staging.MARK}{alive.pid}-4e5f.new"
        running.write_text("another export still writing")
        other = tmp_path / ".st16.xml.mine"  # not a staging name: never touched
        other.write_text("mine")
        assert main(["export", "xtce", str(out)]) == 0
    finally:
        alive.kill()
        alive.wait()
    assert not stale_dir.exists() and not stale_file.exists()
    assert running.exists() and other.read_text() == "mine"
    assert out.read_text().startswith("<?xml")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, running.name, other.name])
