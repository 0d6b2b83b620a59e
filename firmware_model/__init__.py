"""The emulated star tracker: device shell and detection-to-attitude pipeline.

The pipeline's compiled kernels (numba, ``cache=True``) are compiled once per install and loaded
from disk afterwards. Where they are kept is settled here, at import, before any kernel is
defined: ``NUMBA_CACHE_DIR`` when the user set it; else beside the modules (numba's own
``__pycache__`` folders) when the package folder is writable; else the user's cache directory
(:func:`user_cache_dir`). A cache directory that cannot be written is said in one warning line
naming it, and the kernels are then compiled for the process alone (a temporary folder removed
at exit): slower to start, never broken.
"""

from __future__ import annotations

import atexit
import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def user_cache_dir() -> Path:
    """This project's folder in the user's cache directory (``~/.cache/colour-st16`` on Linux,
    the platform's equivalent elsewhere; ``XDG_CACHE_HOME`` honoured)."""
    from numba.misc.appdirs import AppDirs  # numba's copy of appdirs: no further dependency

    return Path(AppDirs("colour-st16", appauthor=False).user_cache_dir)


def _writable(path: Path) -> bool:
    """Whether files can be created in ``path`` (made if missing), tried as numba tries it."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
    except OSError:
        return False
    return True


def kernel_cache_dir(environ=os.environ, package: Path = _PACKAGE) -> tuple[Path | None, bool]:
    """(the folder the compiled kernels go to, whether it can be written): ``NUMBA_CACHE_DIR`` if
    set, None for numba's place beside the modules when ``package`` is writable, else
    ``user_cache_dir()/numba``."""
    chosen = environ.get("NUMBA_CACHE_DIR")
    pycache = package / "__pycache__"
    if chosen:
        path = Path(chosen)
    elif os.access(pycache if pycache.exists() else package, os.W_OK):
        return None, True
    else:
        path = user_cache_dir() / "numba"
    return path, _writable(path)


def _configure_kernel_cache() -> None:
    path, writable = kernel_cache_dir()
    if path is None:
        return
    if not writable:
        logging.getLogger(__name__).warning(
            "st16: compiled kernels cannot be cached in %s (not writable): they are compiled in every "
            "process (about a minute on 2 cores); set NUMBA_CACHE_DIR to a writable folder",
            path,
        )
        path = Path(tempfile.mkdtemp(prefix="st16-kernels-"))
        atexit.register(shutil.rmtree, path, True)
    os.environ["NUMBA_CACHE_DIR"] = str(path)  # child processes (spawned builds) see the same
    config = sys.modules.get("numba.core.config")
    if config is not None:  # numba was imported first: it read the environment already
        config.CACHE_DIR = str(path)  # type: ignore[attr-defined]


_configure_kernel_cache()
