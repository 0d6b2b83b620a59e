"""Outputs of ``st16-ground export`` put in place whole or not at all, even when the process is
killed (``kill -9``) at any moment.

The output is written into a sibling of the target named ``.NAME.st16-export-PID-XXXX.new``
(a directory or a file), flushed to disk, and renamed onto the target: ``os.rename`` of a
complete directory or file. A target that exists (only with ``--force``) is first renamed aside
to ``.NAME.st16-export-PID-XXXX.old``, the new one renamed in, and the old one removed: the
target is replaced whole, never merged into. A killed run leaves at most those siblings, and
between the two renames no target (never a partial one); the next run removes the siblings of
any process that is no longer running before it starts.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import shutil
from collections.abc import Iterator
from pathlib import Path

from ground.arg_types import InputError

MARK = ".st16-export-"  #: in every sibling's name, between the target's name and the writer's pid
_SIBLING = re.compile(r"\.st16-export-(\d+)-[0-9a-f]+\.(new|old)$")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def siblings(target: Path) -> list[Path]:
    """The staging siblings of ``target`` (this process's, other writers', killed runs')."""
    prefix = f".{target.name}{MARK}"
    try:
        names = os.listdir(target.parent)
    except FileNotFoundError:
        return []
    return [target.parent / n for n in names if n.startswith(prefix) and _SIBLING.search(n)]


def remove_stale(target: Path) -> list[Path]:
    """Remove the staging siblings of ``target`` left by processes no longer running; returns them."""
    stale = []
    for path in siblings(target):
        match = _SIBLING.search(path.name)
        if match and not _running(int(match.group(1))):
            _remove(path)
            stale.append(path)
    return stale


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(root: Path) -> None:
    """Every file and directory under ``root`` (and ``root``) on disk."""
    if root.is_file():
        _fsync(root)
        return
    for folder, _dirs, files in os.walk(root):
        for name in files:
            _fsync(Path(folder) / name)
        _fsync(Path(folder))


def _sibling(target: Path, kind: str) -> Path:
    return target.parent / f".{target.name}{MARK}{os.getpid()}-{secrets.token_hex(4)}.{kind}"


def _put_in_place(new: Path, target: Path, force: bool) -> None:
    """Rename the complete ``new`` onto ``target``; an existing target (``force``) is renamed
    aside first and removed once the new one is in place."""
    try:
        os.rename(new, target)  # target absent, an empty directory, or (a file onto) a file
        return
    except OSError as exc:
        if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR, errno.EISDIR):
            raise
        if not force:
            raise InputError(f"{target} exists and is not empty: add --force to replace it") from None
    old = _sibling(target, "old")
    os.rename(target, old)
    os.rename(new, target)
    _fsync(target.parent)
    _remove(old)


@contextlib.contextmanager
def staged(target: str | Path, force: bool, directory: bool) -> Iterator[Path]:
    """A path beside ``target`` for the block to fill (an empty directory if ``directory``,
    else a file path not yet created); once the block ends without an error it is flushed and
    renamed onto ``target`` (see the module docstring), else removed. Stale siblings of killed
    runs are removed first."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    remove_stale(target)
    new = _sibling(target, "new")
    if directory:
        new.mkdir()
    try:
        yield new
        if not directory:
            new.chmod(0o666 & ~_umask())
        _fsync_tree(new)
        _put_in_place(new, target, force)
        _fsync(target.parent)
    except BaseException:
        if new.exists() or new.is_symlink():
            _remove(new)
        raise
