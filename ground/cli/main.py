"""``st16-ground``: the ground tool's command line.

Each feature module contributes its subcommands through ``register(subparsers)``; a handler
receives the parsed ``args`` and returns a process exit code. Global options (link URL,
addresses, JSON output, exchange log, log level) are parsed here once for every subcommand.
Expected failures that a handler does not report itself end here as one line on stderr with the
exit code of their class (:data:`EXIT_CODES`); ``--debug`` shows the traceback instead.

A command's output goes to stdout; its warnings and notes go through :mod:`logging` (a logger per
module) to one stderr handler that ``main`` installs for the run, from ``--log-level`` up (default
warning: the lines a user always saw, as they read before), one line each, as ``st16-device``
writes its own.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import sys
from collections.abc import Iterator

from ground.arg_types import U8, InputError, output_file, ranged

#: Modules that add subcommands, in help order. Each defines ``register(subparsers)``.
COMMAND_MODULES = (
    "ground.cli.link",
    "ground.cli.catalog",
    "ground.cli.frame",
    "ground.cli.sim",
    "ground.cli.solve",
    "ground.cli.database",
    "ground.cli.replay",
    "ground.cli.colour",
    "ground.cli.params",
    "ground.cli.demo",
    "ground.cli.camera",
    "ground.cli.hil",
    "ground.cli.export",
)


#: Exit codes by class of outcome (also in ``st16-ground --help``).
EXIT_CODES = {
    0: "success (a solve: a high-confidence attitude)",
    1: "the command failed or its answer is not a confident solve (the reason is printed)",
    2: "usage or input: bad arguments, a missing or unreadable file",
    3: "solve: no attitude",
    4: "link: the port cannot be opened, or the device does not answer",
    5: "refused: the device answered with a NACK",
    130: "interrupted (Ctrl-C)",
}


class Parser(argparse.ArgumentParser):
    """argparse with a usage error on one line (``PROG: error: MESSAGE (PROG --help: usage)``),
    exit 2, as every other refusal of ``st16-ground``; subcommands' parsers are of this class too."""

    def error(self, message: str):
        line = f"{self.prog}: error: {message} ({self.prog} --help: usage)"
        print(line, file=sys.stderr)
        raise UsageError(line)


class UsageError(SystemExit):
    """A command line argparse refused (exit 2); ``line`` is what was printed."""

    def __init__(self, line: str):
        super().__init__(2)
        self.line = line


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions as written; an option's help ends with its default unless the default is
    None, False or suppressed, or the help already says what it is."""

    def _get_help_string(self, action):
        text = action.help or ""
        if (
            any(action.default is v for v in (None, False, argparse.SUPPRESS))
            or "default" in text
            or not (action.option_strings or action.nargs in (argparse.OPTIONAL, argparse.ZERO_OR_MORE))
        ):
            return text
        return text + " (default: %(default)s)"


def _global_options(parser: argparse.ArgumentParser, defaults: bool = True) -> None:
    """The options every subcommand shares; on subcommands (``defaults=False``) they are accepted
    after the subcommand's name too, and only override what was given before it when present."""

    def add(name: str, help_text: str, default, shown=None, **kw) -> None:
        if default is not None and default is not False:
            help_text += f" (default: {shown or default})"
        parser.add_argument(name, help=help_text, default=default if defaults else argparse.SUPPRESS, **kw)

    add("--debug", "show the traceback of a failure", False, action="store_true")
    add("--port", "pyserial URL of the device: pty path, /dev/tty*, socket://host:port, loop://", None)
    add("--baud", "baud rate for real serial ports", 115200, type=ranged(int, 50, 16_000_000, "a baud rate"))
    add("--device-address", "NSP address of the tracker", 0x0E, "0x0E", type=U8)
    add("--host-address", "our NSP address", 0x11, "0x11", type=U8)
    add("--timeout", "reply timeout in seconds", 1.0, type=ranged(float, 0.001, 3600.0, "a reply timeout in s"))
    add("--json", "machine-readable output", False, action="store_true")
    add(
        "--no-progress",
        "no progress bars (also off with --json or when stderr is not a terminal)",
        False,
        action="store_true",
    )
    add("--log", "append every exchange to this JSONL file", None, type=output_file)
    add(
        "--log-level",
        "messages on stderr from this level up (skipped plots, ignored files, a device that stops answering: warning)",
        "warning",
        choices=LOG_LEVELS,
    )


#: ``--log-level`` choices, as ``st16-device`` spells them.
LOG_LEVELS = ("debug", "info", "warning", "error")
#: The loggers the stderr handler serves: this project's (a third-party logger keeps its own
#: handling, e.g. astropy's, as it had before).
OWN_LOGGERS = ("ground", "firmware_model", "protocol")


class _StderrHandler(logging.StreamHandler):
    """One line per record on stderr; above a progress bar (``tqdm.write``) when tqdm is in use,
    so a message never breaks a bar."""

    def emit(self, record: logging.LogRecord) -> None:
        tqdm = sys.modules.get("tqdm")
        if tqdm is None:
            super().emit(record)
            return
        try:
            tqdm.tqdm.write(self.format(record), file=self.stream)
            self.flush()
        except Exception:  # noqa: BLE001 - logging's own convention: report, never raise
            self.handleError(record)


@contextlib.contextmanager
def stderr_logging(level: str) -> Iterator[None]:
    """For the length of a command: a stderr handler (``%(message)s``) on this project's loggers
    (:data:`OWN_LOGGERS`), which open down to ``level``; removed and restored afterwards (a test or
    a script may call :func:`main` many times in one process). Records still propagate to the
    root logger, so whatever listens there (pytest's ``caplog``) sees them too."""
    number = logging.getLevelName(level.upper())
    handler = _StderrHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(message)s"))
    own = [logging.getLogger(name) for name in OWN_LOGGERS]
    saved = [logger.level for logger in own]
    for logger in own:
        logger.addHandler(handler)
        logger.setLevel(number)
    try:
        yield
    finally:
        for logger, old in zip(own, saved):
            logger.removeHandler(handler)
            logger.setLevel(old)


def _leaf_parsers(parser: argparse.ArgumentParser):
    """Every parser below ``parser`` that runs a command (subcommands of subcommands included)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):  # aliases share a parser
                yield child
                yield from _leaf_parsers(child)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="st16-ground",
        description=__doc__.splitlines()[0],
        formatter_class=HelpFormatter,
        epilog="exit codes:\n" + "\n".join(f"  {code:>3}  {text}" for code, text in EXIT_CODES.items()),
    )
    from protocol import __version__  # package metadata only: start-up stays fast

    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    _global_options(parser)
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
    for child in _leaf_parsers(parser):
        child.formatter_class = HelpFormatter
        group = child.add_argument_group("global options (also accepted before the command)")
        _global_options(group, defaults=False)
    return parser


def check_port_url(url: str) -> None:
    """Refuse a ``--port`` URL pyserial cannot parse (an unknown ``scheme://``, a bad option)
    before anything is opened: :class:`InputError` (exit 2), not a traceback."""
    import serial

    try:
        serial.serial_for_url(url, do_not_open=True)
    except ValueError as exc:
        raise InputError(f"--port {url}: {exc}") from None


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except UsageError as exc:  # the line is on stderr; under --json stdout has its document too
        if "--json" in (sys.argv[1:] if argv is None else argv):
            from ground import json_text

            print(json_text.dumps({"error": "UsageError", "message": exc.line, "exit_code": 2}))
        raise
    from serial import SerialException  # after parsing: --help and usage errors stay fast

    from ground.link.client import LinkError
    from ground.link.commands import exit_code
    from ground.link.exchange_log import LogWriteError
    from ground.optional import MissingExtra

    try:
        with stderr_logging(args.log_level):
            if args.port:
                check_port_url(args.port)
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        if args.debug:
            raise
        return _failed(args, "interrupted", "Interrupted", 130)
    except (InputError, LogWriteError, MissingExtra) as exc:  # bad input, an unwritable --log, a part not installed
        if args.debug:
            raise
        return _failed(args, str(exc), type(exc).__name__, 2)
    except BrokenPipeError:  # the reader went away (| head): no traceback, no second error at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except (LinkError, SerialException, OSError) as exc:
        if args.debug:
            raise
        return _failed(args, str(exc), type(exc).__name__, exit_code(exc))


def _failed(args, message: str, kind: str, code: int) -> int:
    """A failure that ends the command: one line on stderr (``st16-ground: MESSAGE``) and its exit
    code; under ``--json`` stdout gets its one document too, ``{"error", "message", "exit_code"}``."""
    print(f"st16-ground: {message}", file=sys.stderr)
    if args.json:
        from ground import json_text

        print(json_text.dumps({"error": kind, "message": message, "exit_code": code}))
    return code
