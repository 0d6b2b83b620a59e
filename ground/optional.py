"""The heavy optional parts, imported only where used, with a one-line answer when missing:
``[plots]`` (matplotlib) and ``[dask]`` (dask.distributed for ``sim --scheduler``)."""

from __future__ import annotations

from types import ModuleType


class MissingExtra(ImportError):
    """An optional part is not installed; the message names the extra that provides it."""


def pyplot() -> ModuleType:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (the ``[plots]`` extra)."""
    try:
        import matplotlib
    except ImportError:
        raise MissingExtra("plots need matplotlib: pip install 'colour-st16[plots]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def dask_distributed() -> ModuleType:
    """``dask.distributed`` (the ``[dask]`` extra)."""
    try:
        import dask.distributed
    except ImportError:
        raise MissingExtra("--scheduler needs dask: pip install 'colour-st16[dask]'") from None
    return dask.distributed
