"""Argument types for the command lines that refuse out-of-range values before any work starts
(argparse turns the refusal into one usage line and exit code 2)."""

from __future__ import annotations

import argparse
from pathlib import Path

#: Longest echo of a refused value (a 5000-digit count was echoed in a 5087-character line).
ECHO_CHARS = 40


def ranged(kind, lo=None, hi=None, what: str = "value"):
    """An argparse type: ``kind(text)`` (ints also as 0x.. / 0o.. / 0b..) within [lo, hi]."""

    def parse(text: str):
        shown = text if len(text) <= ECHO_CHARS else f"{text[: ECHO_CHARS - 3]}... ({len(text)} characters)"
        try:
            value = int(text, 0) if kind is int else kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{what} must be {'an integer' if kind is int else 'a number'}, got {shown!r}"
            ) from None
        if value != value or (lo is not None and value < lo) or (hi is not None and value > hi):  # NaN too
            bounds = (
                f"from {lo} to {hi}"
                if lo is not None and hi is not None
                else (f"at least {lo}" if lo is not None else f"at most {hi}")
            )
            raise argparse.ArgumentTypeError(f"{what} must be {bounds}, got {shown}")
        return value

    parse.__name__ = what  # argparse names the type in its messages
    return parse


def output_file(text: str) -> str:
    """An argparse type: a file path whose directory exists (checked before any work is done)."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a directory, not a file")
    if path.parent.exists() and not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"{path.parent} is a file, not a directory (for {text})")
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"directory {path.parent} does not exist (for {text})")
    return text


U8 = ranged(int, 0, 0xFF, "a byte")
U16 = ranged(int, 0, 0xFFFF, "a 16-bit value")
U32 = ranged(int, 0, 0xFFFFFFFF, "a 32-bit address")
#: Sensor sizes (px): a full-frame camera is ~10 000 px across; larger would only exhaust memory.
SENSOR_PX = ranged(int, 2, 16384, "a sensor size in px")
SECONDS = ranged(float, 1e-6, 86400.0, "a time in seconds")
SEED = ranged(int, 0, 2**63 - 1, "a seed")
RA_DEG = ranged(float, 0.0, 360.0, "RA in degrees")
DEC_DEG = ranged(float, -90.0, 90.0, "Dec in degrees")
ANGLE_DEG = ranged(float, -360.0, 360.0, "an angle in degrees")
#: Radiation on a simulated detector (``sim availability``): a particle flux (cm^-2 s^-1; 1e6 hits
#: a full reference-design frame ~24 000 times in 100 ms, far beyond any orbit's), a mean number
#: of hits per frame, a total ionising dose (krad(Si); 10 Mrad is beyond any CMOS sensor's life).
FLUX_PER_CM2_S = ranged(float, 0.0, 1e6, "a particle flux per cm^2 per s")
HITS_PER_FRAME = ranged(float, 0.0, 1e5, "a number of hits per frame")
DOSE_KRAD = ranged(float, 0.0, 1e4, "a dose in krad")


def progress_on(args) -> bool:
    """Whether a command shows progress bars: not with ``--no-progress`` or ``--json``, and only
    when stderr is a terminal (bars in a log file or a pipe are noise)."""
    import sys

    return not (getattr(args, "no_progress", False) or getattr(args, "json", False)) and sys.stderr.isatty()


class InputError(Exception):
    """A bad value or input file found after parsing (a missing companion option, an unreadable
    catalog or camera file): ``st16-ground`` prints the message on one line and exits 2."""
