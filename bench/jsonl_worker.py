"""The JSON-lines protocol of the peer benchmark's workers (``bench_peers.py``): one request per
line on stdin (``{"op": NAME, ...}``), one reply per line on stdout, in order. Standard library
only: the peers' workers import it from the benchmark-only venv, ours from the project's.

A handler returns a dict; :class:`Clock` times the part of it that counts (wall, the calling
thread's CPU and the whole process's CPU, seconds), so argument conversion stays outside. Library
output printed to stdout goes to stderr, so it never corrupts the protocol. An exception becomes
``{"error": "..."}`` and the worker goes on."""

from __future__ import annotations

import json
import sys
import time
import traceback
from collections.abc import Callable

#: Environment of every worker: one thread for BLAS, OpenMP, numba and rayon (tetra3rs).
SINGLE_THREAD = {
    name: "1"
    for name in (
        "OMP_NUM_THREADS",
        "OPENBLAS_NUM_THREADS",
        "MKL_NUM_THREADS",
        "NUMBA_NUM_THREADS",
        "NUMEXPR_NUM_THREADS",
        "VECLIB_MAXIMUM_THREADS",
        "RAYON_NUM_THREADS",
    )
}


class Clock:
    """``with Clock() as c: ...`` then ``c.times()``: wall_s, cpu_s (this thread), proc_cpu_s."""

    def __enter__(self) -> Clock:
        self.w0, self.c0, self.p0 = time.perf_counter(), time.thread_time(), time.process_time()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall = time.perf_counter() - self.w0
        self.cpu = time.thread_time() - self.c0
        self.proc = time.process_time() - self.p0

    def times(self) -> dict[str, float]:
        return {"wall_s": self.wall, "cpu_s": self.cpu, "proc_cpu_s": self.proc}


def serve(handlers: dict[str, Callable[..., dict]]) -> None:
    """Answer requests until stdin closes."""
    out = sys.stdout
    sys.stdout = sys.stderr
    for line in sys.stdin:
        if not line.strip():
            continue
        req = json.loads(line)
        op = req.pop("op")
        try:
            rep = handlers[op](**req)
        except Exception as exc:  # the bench prints it; the worker stays up
            traceback.print_exc()
            rep = {"error": f"{type(exc).__name__}: {exc}"}
        out.write(json.dumps(rep) + "\n")
        out.flush()
