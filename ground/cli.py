"""``st16-ground``: the ground tool's command line.

Each feature module contributes its subcommands through ``register(subparsers)``; a handler
receives the parsed ``args`` and returns a process exit code. Global options (link URL,
addresses, JSON output, exchange log) are parsed here once for every subcommand.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: Modules that add subcommands, in help order. Each defines ``register(subparsers)``.
COMMAND_MODULES = (
    "ground.cli_link",
    "ground.cli_catalog",
    "ground.cli_frame",
    "ground.cli_sim",
    "ground.cli_solve",
    "ground.cli_camera",
)


def _int_auto(text: str) -> int:
    return int(text, 0)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="st16-ground", description=__doc__.splitlines()[0])
    parser.add_argument("--port", help="pyserial URL of the device: pty path, /dev/tty*, socket://host:port, loop://")
    parser.add_argument("--baud", type=int, default=115200, help="baud rate for real serial ports")
    parser.add_argument("--device-address", type=_int_auto, default=0x0E, help="NSP address of the tracker")
    parser.add_argument("--host-address", type=_int_auto, default=0x11, help="our NSP address")
    parser.add_argument("--timeout", type=float, default=1.0, help="reply timeout in seconds")
    parser.add_argument("--json", action="store_true", help="machine-readable output")
    parser.add_argument("--log", help="append every exchange to this JSONL file")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue  # feature not installed in this build
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
