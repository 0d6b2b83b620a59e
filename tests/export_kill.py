"""``st16-ground export openc3`` killed (SIGKILL, as ``kill -9``) part-way, and what it leaves.

Two ways to cut it (both run the export of the checkout ``repo``, so an older checkout can be
measured the same way):

* :func:`kill_at_each_event`: one process imports everything once, then forks one export per
  file event ``k`` (each ``mkdir``, ``rename``, ``replace``, ``unlink``, ``rmdir``, ``chmod``, file
  write and file copy, counted from the start of the export) whose child kills itself just before
  its ``k``-th event; until an export runs to its end. Every moment between two events is
  covered once, deterministically.
* :func:`kill_at_random`: ``st16-ground export openc3`` as a process of its own, killed after a
  random delay drawn over the span in which a clean export touches the disk (measured first).

After each kill the output is classified (:func:`classify`): ``absent``, ``old`` (the tree that
was there before, unchanged), ``new`` (equal to a clean export, file for file) or ``partial``.
Then the next run (``--force`` when something is there) must succeed, leave ``new`` and no
staging sibling. ``python tests/export_kill.py [--kills N] [--repo DIR]`` prints the figures
(``bench/bench_export_kill.py`` runs it).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: Runs in a process of its own (cwd: the checkout): argv = out, force (0/1), old (a tree to put
#: at out on "reset", or ""), fast (0/1). Reads commands, one a line: "reset"; "kill K" (an export whose
#: child kills itself before its K-th file event); "run" (an export, --force when out exists).
#: Answers each with a line: the export's exit code (-9: killed).
HARNESS = r"""
import functools, os, pathlib, shutil, signal, sys
from ground.cli.main import main
from ground.export import model

model.build = functools.cache(model.build)  # the same description every time: built once
out, force, old = pathlib.Path(sys.argv[1]), sys.argv[2] == "1", sys.argv[3]
if sys.argv[4] == "1":  # openc3's parse of the written target only reads: its answer, once
    from ground.export import openc3

    _validate, _answer = openc3.validate, []

    def validate(root, target=openc3.TARGET):
        if not _answer:
            _answer.append(_validate(root, target))
        return _answer[0]

    openc3.validate = validate

def reset():
    for p in out.parent.iterdir():
        shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
    if old:
        shutil.copytree(old, out, symlinks=True)


def run(kill_at, force):
    pid = os.fork()
    if pid == 0:
        count = [0]

        def hook(fn):
            def wrapped(*a, **kw):
                count[0] += 1
                if count[0] == kill_at:
                    os.kill(os.getpid(), signal.SIGKILL)
                return fn(*a, **kw)
            return wrapped

        for name in ("mkdir", "rename", "replace", "unlink", "rmdir", "chmod"):
            setattr(os, name, hook(getattr(os, name)))
        pathlib.Path.write_text = hook(pathlib.Path.write_text)
        pathlib.Path.write_bytes = hook(pathlib.Path.write_bytes)
        shutil.copyfile = hook(shutil.copyfile)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1), os.dup2(devnull, 2)
        os._exit(main(["export", "openc3", str(out)] + (["--force"] if force else [])))
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


scratch = out.parent.parent / "warm"
assert main(["--json", "export", "openc3", str(scratch)]) == 0  # imports, caches: filled before any fork
sys.stdout.flush()
shutil.rmtree(scratch)
for line in sys.stdin:
    word, *rest = line.split()
    if word == "reset":
        reset()
        rc = 0
    elif word == "kill":
        rc = run(int(rest[0]), force)
    else:
        rc = run(0, force or out.exists())
    print(rc, flush=True)
"""


def tree(root: Path) -> dict[str, bytes | None]:
    """Relative path -> bytes (None for a directory, the link target for a symlink)."""
    if not root.exists() and not root.is_symlink():
        return {}
    if root.is_file() or root.is_symlink():
        return {".": root.read_bytes() if not root.is_symlink() else os.readlink(root).encode()}
    out: dict[str, bytes | None] = {}
    for path in sorted(root.rglob("*")):
        rel = str(path.relative_to(root))
        out[rel] = os.readlink(path).encode() if path.is_symlink() else None if path.is_dir() else path.read_bytes()
    return out


def classify(out: Path, new: dict, old: dict | None) -> str:
    if not out.exists() and not out.is_symlink():
        return "absent"
    found = tree(out)
    if found == new:
        return "new"
    if old is not None and found == old:
        return "old"
    return "partial"


def siblings(out: Path) -> list[str]:
    """Everything beside ``out`` that is not ``out`` itself or a fixture of the run."""
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith("." + out.name))


def _export(repo: Path, out: Path, force: bool) -> subprocess.CompletedProcess:
    args = [sys.executable, "-m", "ground.cli", "export", "openc3", str(out)] + (["--force"] if force else [])
    return subprocess.run(args, cwd=repo, capture_output=True, text=True)


def _next_run(repo: Path, out: Path, new: dict, force: bool) -> dict:
    """The run after a kill: it must succeed, leave a whole new target and no sibling."""
    run = _export(repo, out, force or out.exists())
    return {"next_rc": run.returncode, "next_state": classify(out, new, None), "next_siblings": siblings(out)}


def reference(repo: Path, work: Path) -> dict:
    """The tree a clean export writes."""
    ref = work / "reference" / "target"
    ref.parent.mkdir(parents=True)
    run = _export(repo, ref, False)
    assert run.returncode == 0, run.stderr
    return tree(ref)


def old_tree(work: Path, new_root: Path) -> Path:
    """A tree to export over with ``--force``: a whole earlier target, with a file of the user's
    and ``tlm.txt`` a directory (so a merge shows)."""
    old = work / "old"
    shutil.copytree(new_root, old)
    (old / "mine.txt").write_text("the user's")
    tlm = old / "targets" / "ST16" / "cmd_tlm" / "tlm.txt"
    tlm.unlink()
    tlm.mkdir()
    (tlm / "inside").write_text("x")
    return old


def kill_at_each_event(work: Path, force: bool, repo: Path = REPO, fast: bool = False) -> list[dict]:
    """One record per file event of an export (see the module docstring); ``fast``: openc3's
    parse of the written target (it only reads) runs once, its answer reused."""
    new = reference(repo, work)
    runs = work / "runs"
    runs.mkdir()
    out = runs / "target"
    old_root = old_tree(work, work / "reference" / "target") if force else None
    old = tree(old_root) if old_root else None
    args = [sys.executable, "-c", HARNESS, str(out), "1" if force else "0", str(old_root or ""), "1" if fast else "0"]
    proc = subprocess.Popen(args, cwd=repo, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdin is not None and proc.stdout is not None

    proc.stdout.readline()  # the warm-up export's line

    def ask(command: str) -> int:
        proc.stdin.write(command + "\n")
        proc.stdin.flush()
        return int(proc.stdout.readline())

    records = []
    try:
        for k in range(1, 1000):
            ask("reset")
            rec: dict = {"k": k, "rc": ask(f"kill {k}")}
            rec["killed"] = rec["rc"] == -signal.SIGKILL
            rec["state"] = classify(out, new, old)
            rec["siblings"] = siblings(out)
            if rec["killed"]:
                rec["next_rc"] = ask("run")
                rec["next_state"], rec["next_siblings"] = classify(out, new, None), siblings(out)
            records.append(rec)
            if not rec["killed"]:
                break
    finally:
        proc.stdin.close()
        proc.wait(60)
    return records


def _disk_span(repo: Path, out: Path) -> tuple[float, float]:
    """(first, last) second after the start at which a clean export was seen to touch the disk
    beside ``out`` (polled every millisecond), and its end."""
    args = [sys.executable, "-m", "ground.cli", "export", "openc3", str(out)]
    start = time.monotonic()
    proc = subprocess.Popen(args, cwd=repo, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    first = None
    while proc.poll() is None:
        if first is None and any(p.name.startswith("." + out.name) or p == out for p in out.parent.iterdir()):
            first = time.monotonic() - start
        time.sleep(0.001)
    end = time.monotonic() - start
    assert proc.returncode == 0
    return (first if first is not None else 0.0), end


def kill_at_random(work: Path, kills: int, seed: int, force: bool = False, repo: Path = REPO) -> list[dict]:
    """``kills`` exports as processes of their own, each killed at a random delay over the span
    in which a clean export touches the disk (with 20 % of it either side)."""
    new = reference(repo, work)
    old_root = old_tree(work, work / "reference" / "target") if force else None
    old = tree(old_root) if old_root else None
    runs = work / "runs"
    runs.mkdir()
    out = runs / "target"
    first, end = _disk_span(repo, out)
    margin = 0.2 * (end - first)
    rng = random.Random(seed)
    records = []
    for _ in range(kills):
        shutil.rmtree(runs)
        runs.mkdir()
        if old_root:
            shutil.copytree(old_root, out)
        delay = rng.uniform(max(0.0, first - margin), end + margin)
        args = [sys.executable, "-m", "ground.cli", "export", "openc3", str(out)] + (["--force"] if force else [])
        proc = subprocess.Popen(args, cwd=repo, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        rc = proc.wait()
        rec = {"delay_s": round(delay, 3), "killed": rc == -signal.SIGKILL, "rc": rc}
        rec["state"] = classify(out, new, old)
        rec["siblings"] = siblings(out)
        rec.update(_next_run(repo, out, new, force))
        records.append(rec)
    return records


def _summary(label: str, records: list[dict]) -> str:
    killed = [r for r in records if r["killed"]]
    states = {s: sum(r["state"] == s for r in killed) for s in ("absent", "old", "new", "partial")}
    left = sum(bool(r["siblings"]) for r in killed)
    bad_next = sum(
        bool(r.get("next_rc", 0) or r.get("next_state", "new") != "new" or r.get("next_siblings")) for r in killed
    )
    return (
        f"{label}: {len(killed)} of {len(records)} runs killed (the others had finished): "
        + ", ".join(f"{n} {s}" for s, n in states.items())
        + f"; {left} left a staging sibling; next run failed or left something in {bad_next}"
    )


def main() -> None:
    import tempfile

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kills", type=int, default=20, help="random kills per case")
    parser.add_argument("--seed", type=int, default=31)
    parser.add_argument("--repo", type=Path, default=REPO, help="checkout whose export is run")
    args = parser.parse_args()
    print(f"export openc3 of {args.repo}")
    for force in (False, True):
        case = "--force over a tree (tlm.txt a directory, a user file)" if force else "into a new directory"
        with tempfile.TemporaryDirectory() as tmp:
            recs = kill_at_each_event(Path(tmp), force, args.repo)
        print(_summary(f"kill at each of {len(recs) - 1} file events, {case}", recs))
        with tempfile.TemporaryDirectory() as tmp:
            recs = kill_at_random(Path(tmp), args.kills, args.seed, force, args.repo)
        print(_summary(f"kill at {args.kills} random moments, {case}", recs))
        for r in recs:
            if r["state"] == "partial" or r["next_rc"]:
                print("   ", json.dumps(r))


if __name__ == "__main__":
    main()
