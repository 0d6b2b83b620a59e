"""Wire and file formats shared by device and ground. Pure code, no I/O."""

from importlib.metadata import PackageNotFoundError, version

try:
    #: The project's one version number (pyproject.toml): both CLIs' ``--version`` and the PING banner.
    __version__ = version("colour-st16")
except PackageNotFoundError:  # run from a source tree that was never installed
    __version__ = "0+unknown"
