"""The start-up of the device's index-building process (``sensor_input.PipelineSolver``): a module
of few imports, as the spawned process imports it (and the device's main module, ``cli``, whose
own imports are deferred to the device's build) before any task, beside the device's first GOs."""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import threading

#: How much lower than the device's the process' scheduling priority is (``nice`` steps): on a busy
#: machine its work waits for the device's, on an idle core it runs at full speed.
NICENESS = 10


def ready() -> bool:
    """The process' first task: import what an index build runs (``scale_free``), so that a
    catalog COMMIT's build starts at once."""
    import firmware_model.pipeline.scale_free  # noqa: F401

    return True


def init() -> None:
    """The process gives way to the device (:data:`NICENESS`: its imports at the device's start and
    its builds never take a core from the device's GOs and link), and ends with the device, however
    the device ends (a device killed outright would otherwise leave it waiting for work for ever):
    a thread waits for the parent's end and exits."""
    os.nice(NICENESS)
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        multiprocessing.connection.wait([parent.sentinel])
        os._exit(0)

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()
