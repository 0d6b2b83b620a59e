"""Interactive console for ``st16-ground console``: the link subcommands at a prompt.

``help`` lists commands and ``help NAME`` shows a command's arguments; ``raw on`` also prints
the hex of every frame sent and received; ``quit`` or Ctrl-D leaves. History is kept in
``~/.st16_ground_history`` when readline is available.
"""

from __future__ import annotations

import argparse
import cmd
import json
import shlex
from pathlib import Path

from .cli_link import COMMANDS, add_commands, render, report_error
from .client import Client, LinkError

HISTORY = Path.home() / ".st16_ground_history"


class _ParseError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise _ParseError(f"{self.prog}: {message}")

    def exit(self, status=0, message=None):
        if message:
            print(message, end="")
        raise _ParseError("")


class Console(cmd.Cmd):
    intro = "st16-ground console: 'help' lists commands, 'raw on' shows frames, 'quit' leaves."
    prompt = "st16> "

    def __init__(self, client: Client, as_json: bool = False, **kw):
        super().__init__(**kw)
        self.client = client
        self.as_json = as_json
        self.show_raw = False
        self.parser = _Parser(prog="st16>", add_help=False)
        self.sub = self.parser.add_subparsers(dest="command", parser_class=_Parser)
        add_commands(self.sub, lambda run: run)

    def run(self) -> None:
        try:
            import readline
        except ImportError:  # pragma: no cover - platform without readline
            readline = None
        if readline is not None and HISTORY.exists():
            readline.read_history_file(HISTORY)
        try:
            self.cmdloop()
        except KeyboardInterrupt:
            print()
        finally:
            if readline is not None:
                readline.set_history_length(1000)
                readline.write_history_file(HISTORY)

    def emptyline(self) -> bool:
        return False

    def default(self, line: str) -> bool:
        try:
            args = self.parser.parse_args(shlex.split(line))
        except (_ParseError, ValueError) as exc:
            if str(exc):
                print(exc)
            return False
        if args.command is None:
            return False
        try:
            out = args.func(self.client, args)
            print(json.dumps(out) if self.as_json else render(out))
        except LinkError as exc:
            report_error(exc, self.as_json)
        except (OSError, ValueError) as exc:
            print(f"error: {exc}")
        if self.show_raw:
            sent, received = self.client.last_exchange
            print(f"  tx: {sent.hex(' ')}\n  rx: {received.hex(' ')}")
        return False

    def do_raw(self, arg: str) -> bool:
        """raw on|off: print the hex of the frames of every exchange."""
        if arg.strip() not in ("on", "off"):
            print("usage: raw on|off")
        else:
            self.show_raw = arg.strip() == "on"
        return False

    def do_help(self, arg: str) -> bool:
        """help [COMMAND]: list commands, or show one command's arguments."""
        name = arg.strip()
        if name in COMMANDS:
            self.sub.choices[name].print_help()
        elif name:
            super().do_help(name)
        else:
            width = max(map(len, COMMANDS))
            for cname, (help_text, _, _) in COMMANDS.items():
                print(f"  {cname:<{width}}  {help_text}")
            print(f"  {'raw':<{width}}  raw on|off: show frame hex\n  {'quit':<{width}}  leave")
        return False

    def completenames(self, text, *ignored):
        return [n for n in list(COMMANDS) + ["raw", "help", "quit"] if n.startswith(text)]

    def do_quit(self, arg: str) -> bool:
        """quit: leave the console."""
        return True

    def do_EOF(self, arg: str) -> bool:
        print()
        return True
