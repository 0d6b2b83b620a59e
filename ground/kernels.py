"""The pipeline's compiled kernels, loaded once per process before the first in-process solve, as
the device loads them before it says ``listening`` (``firmware_model.pipeline.run.warm_up``; docs/pipeline.md,
the compiled kernels)."""

from __future__ import annotations

import contextlib
import sys
import threading
import time

from tqdm import tqdm

_kernels_lock = threading.Lock()
_kernels_loaded = False


def warm_up_kernels(progress: bool = False) -> float:
    """Load the pipeline's compiled kernels once per process (from numba's disk cache; the first
    run after install compiles them). Returns the seconds this call spent (0 once they are loaded:
    a solve reports them as its ``compile`` stage). When something compiles, one line says so on
    stderr, and with ``progress`` a bar counts the kernels compiled."""
    global _kernels_loaded
    with _kernels_lock:
        if _kernels_loaded:
            return 0.0
        from firmware_model.pipeline.run import warm_up

        t0 = time.perf_counter()
        with _compile_progress(progress):
            warm_up()
        _kernels_loaded = True
        return time.perf_counter() - t0


@contextlib.contextmanager
def _compile_progress(progress: bool):
    """Say when numba compiles (its ``numba:compile`` events): a loaded cache says nothing."""
    from numba.core import event

    bar: list = []

    class Listener(event.Listener):
        def on_start(self, ev) -> None:
            if not bar:
                tqdm.write(
                    "compiling the pipeline's kernels: the first run after install (about a minute on 2 "
                    "cores; kept in numba's cache for every later run)",
                    file=sys.stderr,
                )
                bar.append(tqdm(desc="kernels compiled", unit=" kernel", disable=not progress, file=sys.stderr))

        def on_end(self, ev) -> None:
            if bar:
                bar[0].update(1)

    with event.install_listener("numba:compile", Listener()):
        try:
            yield
        finally:
            if bar:
                bar[0].close()
