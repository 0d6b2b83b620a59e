"""The start-up of the device's index-building process (``sensor_input.PipelineSolver``): a module
of few imports, as the spawned process imports it (and the device's main module, ``cli``, whose
own imports are deferred to the device's build) before any task, beside the device's first GOs.

The process runs at the device's priority. It ran 10 ``nice`` steps lower, so that its start-up
imports gave way to the device's first GOs; on a busy machine that starved it, and the first GO
after a new catalog's COMMIT, which waits for the build, waited with it (docs/e2e.md)."""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import threading


def ready() -> bool:
    """The process' first task: import what an index build runs (``scale_free``), so that a
    catalog COMMIT's build starts at once."""
    import firmware_model.pipeline.scale_free  # noqa: F401

    return True


def init() -> None:
    """The process ends with the device, however the device ends (a device killed outright would
    otherwise leave it waiting for work for ever): a thread waits for the parent's end and exits."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        multiprocessing.connection.wait([parent.sentinel])
        os._exit(0)

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()
