"""Interactive console for ``st16-ground console``: the link subcommands at a prompt.

``help`` lists commands and ``help NAME`` shows a command's arguments; ``raw on`` also prints
the hex of every frame sent and received; ``reopen`` closes the link and opens it again with the
same settings (after a device restart or a cable swap); ``quit`` or Ctrl-D leaves. With readline,
the command history is kept across sessions in :func:`history_path`; a history file that cannot be
read or written costs the history only.
"""

from __future__ import annotations

import argparse
import cmd
import json
import os
import shlex
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

from ground.atomic_write import atomic_path
from ground.link.client import Client, LinkError
from ground.link.commands import COMMANDS, add_commands, render, report_error

HISTORY_LENGTH = 1000  #: commands kept


def history_path() -> Path:
    """``$XDG_STATE_HOME/st16-ground/history`` (``~/.local/state/st16-ground/history`` by default)."""
    return Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state") / "st16-ground" / "history"


def _readline() -> ModuleType | None:
    """The readline module, or None for a Python without it (then no history)."""
    try:
        import readline
    except ImportError:
        return None
    return readline


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
    intro = "st16-ground console: 'help' lists commands, 'raw on' shows frames, 'reopen' reconnects, 'quit' leaves."
    prompt = "st16> "

    def __init__(self, client: Client | None, as_json: bool = False, reopen: Callable[[], Client] | None = None, **kw):
        """``reopen`` opens a new client with the same settings (the ``reopen`` command); ``client``
        is None while no link is open."""
        super().__init__(**kw)
        self.client = client
        self.as_json = as_json
        self.reopen = reopen
        self.show_raw = False
        self.parser = _Parser(prog="st16>", add_help=False)
        self.sub = self.parser.add_subparsers(dest="command", parser_class=_Parser)
        add_commands(self.sub, lambda run: run)

    def run(self, history: Path | None = None) -> None:
        """The command loop, with the readline history of ``history`` (default :func:`history_path`)."""
        readline = _readline()
        history = history or history_path()
        if readline is not None and history.is_file():
            try:
                readline.read_history_file(history)
            except OSError as exc:
                print(f"st16-ground: history not loaded ({exc})", file=sys.stderr)
        try:
            self.cmdloop()
        except KeyboardInterrupt:
            print()
        finally:
            if readline is not None:
                readline.set_history_length(HISTORY_LENGTH)
                try:
                    history.parent.mkdir(parents=True, exist_ok=True)
                    with atomic_path(history) as tmp:
                        readline.write_history_file(tmp)
                except OSError as exc:
                    print(f"st16-ground: history not saved ({exc})", file=sys.stderr)

    def emptyline(self) -> bool:
        return False

    def default(self, line: str) -> None:
        try:
            args = self.parser.parse_args(shlex.split(line))
        except (_ParseError, ValueError) as exc:
            if str(exc):
                print(exc)
            return
        if args.command is None:
            return
        if self.client is None:
            print("no link: 'reopen' to open it again")
            return
        try:
            out = args.func(self.client, args)
            print(json.dumps(out) if self.as_json else render(out))
        except LinkError as exc:
            report_error(exc, self.as_json)
        except (OSError, ValueError) as exc:
            print(f"error: {exc}")
        if self.show_raw and self.client is not None:
            sent, received = self.client.last_exchange
            print(f"  tx: {sent.hex(' ')}\n  rx: {received.hex(' ')}")

    def do_raw(self, arg: str) -> bool:
        """raw on|off: print the hex of the frames of every exchange."""
        if arg.strip() not in ("on", "off"):
            print("usage: raw on|off")
        else:
            self.show_raw = arg.strip() == "on"
        return False

    def do_reopen(self, arg: str) -> bool:
        """reopen: close the link and open it again with the same settings."""
        if self.reopen is None:
            print("reopen: this console cannot open its link again")
            return False
        if self.client is not None:
            self.client.close()
            self.client = None  # a closed client must not be used
        try:
            self.client = self.reopen()
        except OSError as exc:  # pyserial's errors are OSErrors
            print(f"reopen failed: {exc}; try 'reopen' again")
            return False
        print(f"reopened {self.client.url}")
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
            print(
                f"  {'raw':<{width}}  raw on|off: show frame hex\n"
                f"  {'reopen':<{width}}  close the link and open it again (after a device restart)\n"
                f"  {'quit':<{width}}  leave"
            )
        return False

    def completenames(self, text, *ignored):
        return [n for n in list(COMMANDS) + ["raw", "reopen", "help", "quit"] if n.startswith(text)]

    def do_quit(self, arg: str) -> bool:
        """quit: leave the console."""
        return True

    def do_EOF(self, arg: str) -> bool:
        print()
        return True
