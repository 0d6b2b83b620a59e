"""``st16-ground`` link subcommands (one per entry of ``ground.link.commands.COMMANDS``) and the
interactive console: open the client from the global options, run, print (``--json`` for one line).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ground import json_text
from ground.arg_types import InputError
from ground.link.commands import Run, add_commands, render, report_error


def mark_cut_reason(rec: dict) -> dict:
    """A device result's reason fills its 96-byte field (``protocol.result.EXT_REASON_BYTES``) when
    the text was longer: end it at its last whole word with " ..." and set ``reason_cut``, so a
    reader never takes "fitted to a search-chosen" for the whole reason (the offline record of the
    same frame has it all)."""
    from protocol.result import EXT_REASON_BYTES

    reason = rec.get("reason")
    if isinstance(reason, str) and len(reason.encode()) >= EXT_REASON_BYTES - 3:  # full, but for a cut character
        rec["reason"] = reason.rsplit(" ", 1)[0].rstrip(" ,;:(") + " ..."
        rec["reason_cut"] = True
    return rec


def solve_exit_code(rec: dict) -> int:
    """A solve's exit code (``ground.cli.main.EXIT_CODES``): 0 a high-confidence attitude, 1 an
    attitude that is not (use with care), 3 no attitude; for ``solve``, ``solve-file``, and
    ``result`` / ``go --wait`` / ``combination``, which report one."""
    if rec.get("q_icrs_to_sensor") is None:
        return 3
    return 0 if rec.get("status") == "OK" else 1


if TYPE_CHECKING:  # the client imports numpy and pyserial: only when a command runs
    from ground.link.client import Client


def client_kwargs(args) -> dict:
    """``Client`` keyword arguments from the global options of ``st16-ground``."""
    return {
        "device_address": args.device_address,
        "host_address": args.host_address,
        "timeout": args.timeout,
        "log": args.log,
        "baudrate": args.baud,
    }


def open_client(args) -> Client:
    from ground.link.client import Client

    if not args.port:
        raise InputError("--port URL is required for link commands")
    return Client(args.port, **client_kwargs(args))


def _handler(run: Run):
    def handle(args) -> int:
        from ground.link.client import LinkError

        with open_client(args) as client:
            try:
                out = run(client, args)
            except LinkError as exc:
                return report_error(exc, args.json)
        if "q_icrs_to_sensor" in out:  # a result: its reason as cut by the device, and judged as a solve
            mark_cut_reason(out)
        print(json_text.dumps(out) if args.json else render(out))
        return solve_exit_code(out) if "q_icrs_to_sensor" in out else 0  # a result: judged as a solve

    return handle


def _console(args) -> int:
    from ground.link.console import Console

    console = Console(open_client(args), as_json=args.json, reopen=lambda: open_client(args))
    try:
        console.run()
    finally:
        if console.client is not None:
            console.client.close()
    return 0


def register(sub) -> None:
    """Called by ``ground.cli.main``: the link subcommands and ``console``."""
    add_commands(sub, _handler)
    p = sub.add_parser("console", help="interactive console (history, help per command, raw hex on request)")
    p.set_defaults(func=_console)
