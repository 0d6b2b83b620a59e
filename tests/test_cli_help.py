"""``st16-ground --help``: every option's default is shown, and the parser is built without the
heavy packages (each command imports what it needs when it runs)."""

import argparse
import json
import subprocess
import sys

from ground.cli.main import HelpFormatter, _leaf_parsers, build_parser

HEAVY = ("numpy", "scipy", "astropy", "matplotlib", "serial", "tqdm")


def test_help_imports_no_heavy_package():
    script = f"""
import json, sys
from ground.cli.main import _leaf_parsers, build_parser, main
parser = build_parser()
for child in _leaf_parsers(parser):
    child.format_help()
try:
    main(["--help"])
except SystemExit:
    pass
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r})))
"""
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True)
    assert json.loads(run.stdout.strip().splitlines()[-1]) == []


def _helps():
    parser = build_parser()
    for child in [parser, *_leaf_parsers(parser)]:
        formatter = HelpFormatter(child.prog)
        for action in child._actions:
            if not isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                yield child.prog, action, formatter._expand_help(action) if action.help else ""


def test_every_option_with_a_default_shows_it():
    missing = [
        f"{prog} {action.option_strings or action.dest}"
        for prog, action, text in _helps()
        if all(action.default is not v for v in (None, False, argparse.SUPPRESS))
        and "default" not in text
        and (action.option_strings or action.nargs == "?")
    ]
    assert missing == []
    shown = {f"{prog} {action.dest}": text for prog, action, text in _helps()}
    assert shown["st16-ground frame render roll"] == "roll, deg (default: 0.0)"  # a zero is a default too
    assert shown["st16-ground catalog build m_thresh"].endswith("(default: 5.0, or the --design file's)")
    assert "(default: 115200)" in shown["st16-ground ping baud"]  # the global options after the command too
    assert not [k for k, text in shown.items() if "default: None" in text or "default: False" in text]


def test_one_version_number_in_both_command_lines_and_the_ping_banner():
    import subprocess
    import sys

    from firmware_model.device.device import Device
    from protocol import __version__

    assert __version__ != "0+unknown"  # read from the installed package's metadata
    for module, prog in (("ground.cli", "st16-ground"), ("firmware_model.device.cli", "st16-device")):
        run = subprocess.run([sys.executable, "-m", module, "--version"], capture_output=True, text=True, timeout=60)
        assert run.returncode == 0 and run.stdout.strip() == f"{prog} {__version__}", run
    assert f" {__version__} " in Device().boot_banner
