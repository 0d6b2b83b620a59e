"""The ground's link command table: one entry per NSP command (and the transfer helpers), shared
by the ``st16-ground`` link subcommands and the interactive console.

Each command is described once in :data:`COMMANDS` as ``(help, add_arguments, run)``, where
``run(client, args)`` returns a JSON-able dict and the help of a subcommand that sends one command
(:data:`CODES`) is that command's line in the protocol's command table
(``protocol.command_table``); :func:`render` prints it for people,
:func:`report_error` and :func:`exit_code` turn a failed exchange into one line and an exit code.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ground import json_text
from ground.arg_types import SECONDS, U8, U16, U32, InputError, progress_on, ranged
from protocol.command_table import COMMANDS as COMMAND_TABLE
from protocol.commands import GO_OPERATIONAL, Code, DarkWindow

if TYPE_CHECKING:  # the client imports numpy and pyserial: only when a command runs
    from ground.link.client import Client, LinkError


def _int(text: str) -> int:
    return int(text, 0)


def _hex(text: str) -> bytes:
    try:
        return bytes.fromhex(text.replace(":", "").replace(" ", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not hex bytes: {text!r}") from None


def _args_none(p: argparse.ArgumentParser) -> None:
    pass


def _args_addr_count(p):
    p.add_argument("address", type=U32, help="start address (0x.. for hex)")
    p.add_argument("count", type=ranged(int, 1, 1 << 20, "a byte count (1 to 1048576)"), help="bytes to read")


def _args_addr_data(p):
    p.add_argument("address", type=U32, help="start address (0x.. for hex)")
    p.add_argument("data", type=_hex, help="hex bytes, e.g. 01020304")


def _args_slot(p):
    p.add_argument("slot", type=U8, help="0 catalog, 1 frame, 2 parameters")


def _bytes_out(address: int, data: bytes) -> dict:
    return {"address": address, "count": len(data), "hex": data.hex()}


def _run_ping(c: Client, a) -> dict:
    return {"banner": c.ping()}


def _run_time(c: Client, a) -> dict:
    micros = c.time()
    return {"time_us": micros, "time_s": micros / 1e6}


def _run_init(c, a):
    c.init(a.address)
    return {"init": a.address, "banner": c.ping()}


def _run_diag(c, a):
    return c.diagnostic(clear=a.clear).as_dict()


def _run_peek(c, a):
    return _bytes_out(a.address, c.peek(a.address, a.count))


def _run_poke(c, a):
    return {"address": a.address, "written": c.poke(a.address, a.data)}


def _run_read_edac(c, a):
    return _bytes_out(a.address, c.read_edac(a.address, a.count))


def _run_write_edac(c, a):
    return {"address": a.address, "written": c.write_edac(a.address, a.data)}


def _run_read_file(c, a):
    return _bytes_out(a.address, c.read_file(a.address, long=a.long))


def _run_write_file(c, a):
    c.write_file(a.address, a.data, long=a.long)
    return {"address": a.address, "written": 4}


def _run_crc(c, a):
    return {"space": a.space, "address": a.address, "length": a.length, "crc16": c.crc(a.space, a.address, a.length)}


class _Decoded(dict):
    """A decoded result (``ground.link.solve_report``), rendered by its ``format_record``."""


def _run_go(c, a):
    from ground.link.solve_report import result_record

    if a.wait:
        return _Decoded(result_record(c.go_and_wait(a.code, timeout=a.wait_timeout)))
    return {"go": c.go(a.code)}


def _run_result(c, a):
    from ground.link.solve_report import result_record

    if a.count is not None:
        return _bytes_out(a.address, c.read_result(a.address, a.count))
    return _Decoded(result_record(c.read_result_record()))


def _run_combination(c, a):
    from ground.link.solve_report import combination_record

    return _Decoded(combination_record(c.combination(a.go_code, a.mask, timeout=a.wait_timeout)))


def _run_dark_window(c, a):
    values = tuple(a.values) + (0,) * (8 - len(a.values))
    c.dark_window(DarkWindow(a.buffer, a.row, a.col, a.rows, a.cols, values))
    return {"dark_window": [a.buffer, a.row, a.col, a.rows, a.cols, list(values)]}


def _run_upload(c, a):
    data = Path(a.file).read_bytes()
    report = c.upload(a.slot, data, progress=progress_on(a), commit=not a.no_commit)
    seconds = max(report.seconds, 1e-9)
    return {**report.__dict__, "bytes_per_second": report.sent / seconds}


def _status_dict(st) -> dict:
    return {
        "slot": st.slot,
        "state": int(st.state),
        "length": st.length,
        "crc32": st.crc32,
        "contiguous": st.contiguous,
        "received": st.received,
        "n_missing": st.n_missing,
        "missing": [list(r) for r in st.missing],
    }


def _run_slot_status(c, a):
    return _status_dict(c.xfer_status(a.slot))


def _run_slot_abort(c, a):
    return _status_dict(c.xfer_abort(a.slot))


def _run_slot_info(c, a):
    info = c.slot_info(a.slot)
    out = {"slot": info.slot, "active": info.active, "length": info.length, "crc32": info.crc32}
    try:
        out["info"] = json.loads(info.info.decode("utf-8")) if info.info else None
    except (UnicodeDecodeError, ValueError):
        out["info_hex"] = info.info.hex()
    return out


def _fault_file(path: str) -> str:
    """The text of the fault script at ``path``, parsed here first: a file that does not parse is a
    usage error naming its line (exit 2), before anything is sent."""
    from firmware_model import user_files
    from firmware_model.device.faults import FaultScriptError, parse_script
    from protocol.commands import MAX_FAULT_SCRIPT

    why = user_files.problem(path)  # a FIFO hung the read; /dev/zero was read to 3.7 GB
    if why is not None:
        raise argparse.ArgumentTypeError(f"fault file {path}: {why}")
    size = Path(path).stat().st_size
    if size > MAX_FAULT_SCRIPT:  # before it is read
        raise argparse.ArgumentTypeError(
            f"fault file {path}: {size} bytes, one FAULT load carries at most {MAX_FAULT_SCRIPT}"
        )
    try:
        text = user_files.read_text(path, MAX_FAULT_SCRIPT)
        parse_script(text, path)
    except user_files.UserFileError as exc:
        raise argparse.ArgumentTypeError(f"fault file {exc}") from None
    except FaultScriptError as exc:  # a 5000-digit count was echoed whole
        raise argparse.ArgumentTypeError(user_files.shorten_words(str(exc))) from None
    return text


def _run_fault(c, a):
    from protocol.commands import FaultAction
    from protocol.edac import FAULT_COUNTERS

    action = FaultAction[a.action.upper()]
    st = c.fault(action, a.file if action == FaultAction.LOAD else "")
    return {"action": a.action, "armed": st.armed, "counters": dict(zip(FAULT_COUNTERS, st.counters))}


def _run_send(c, a):
    parts = c.transact(a.code, a.data, poll=not a.silent)
    return {"replies": [{"mcf": p.mcf, "final": p.final, "ack": p.ack, "data": p.data.hex()} for p in parts]}


def _a_init(p):
    p.add_argument("--address", type=U32, default=0x2000, help="application start address (default: 0x2000)")


def _a_diag(p):
    p.add_argument("--clear", action="store_true", help="reset the counters after reading")


def _a_file(p, data: bool):
    p.add_argument("address", type=U32, help="EDAC address (multiple of 4)")
    if data:
        p.add_argument("data", type=_hex, help="4 hex bytes")
    p.add_argument("--long", action="store_true", help="long form (u16 address) instead of the file index")


def _a_crc(p):
    p.add_argument("space", type=U8, help="0 EDAC, 1 memory map, 2 result")
    p.add_argument("address", type=U32, help="start address (0x.. for hex)")
    p.add_argument("length", type=U32, help="bytes")


def _a_go(p):
    p.add_argument("code", type=U8, nargs="?", default=GO_OPERATIONAL, help="go code (default: 0x0B, routine attitude)")
    p.add_argument("--wait", action="store_true", help="poll until the result is ready and print it")
    p.add_argument("--wait-timeout", type=SECONDS, default=30.0, help="give up waiting for the result after, s")


def _a_result(p):
    p.add_argument("--address", type=U32, default=0, help="result offset of the raw bytes (with --count)")
    p.add_argument(
        "--count",
        type=ranged(int, 1, 1 << 20, "a byte count (1 to 1048576)"),
        help="raw bytes instead of the decoded summary",
    )


def _a_combination(p):
    p.add_argument("go_code", type=U8, help="go code of the sequence, e.g. 0x0B")
    p.add_argument("mask", type=U16, help="section mask, e.g. 0x0007 (protocol.result.SECTIONS; 0x1000 ours)")
    p.add_argument("--wait-timeout", type=SECONDS, default=30.0, help="give up waiting for the sequence after, s")


def _a_dark(p):
    for name in ("buffer", "row", "col", "rows", "cols"):
        p.add_argument(name, type=U16, help="window " + name)
    p.add_argument("values", type=U16, nargs="*", help="up to 8 dark values")


def _a_upload(p):
    _args_slot(p)
    p.add_argument("file", help="image to upload")
    p.add_argument("--no-commit", action="store_true", help="leave the transfer pending")


def _a_fault(p):
    sub = p.add_subparsers(dest="action", required=True, metavar="{load,clear,status}")
    load = sub.add_parser("load", help="arm the fault script FILE, replacing the armed one")
    load.add_argument("file", type=_fault_file, help="fault script (docs/ICD.md section 13), checked here first")
    sub.add_parser("clear", help="disarm every fault (the counters stay)")
    sub.add_parser("status", help="faults armed and the fault counters")


def _a_image_poke(p):
    p.add_argument("buffer", type=ranged(int, 0, 1, "an image buffer (0 or 1)"), help="image buffer 0 or 1")
    p.add_argument("row", type=U16, help="first row")
    p.add_argument("col", type=U16, help="first column")
    p.add_argument("file", help="a .npy file of a 2-D array of pixel values 0..65535")


def _run_image_poke(c, a):
    import numpy as np

    try:
        with open(a.file, "rb") as f:
            pixels = np.load(f, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"{a.file}: not a .npy array: {exc}") from None
    c.poke_image(a.buffer, a.row, a.col, pixels)
    return {"buffer": a.buffer, "row": a.row, "col": a.col, "rows": int(pixels.shape[0]), "cols": int(pixels.shape[1])}


def _a_flash(p):
    from protocol.flash import Sub

    names = ", ".join(f"{s.name.lower().replace('_', '-')} ({int(s)})" for s in Sub)
    p.add_argument("sub", help=f"the FLASH subcommand, by name or number: {names}")
    p.add_argument("fields", type=_int, nargs="*", help="its fields in order (docs/ICD.md section 15)")
    p.add_argument("--data", type=_hex, default=b"", help="write-buffer: the bytes, as hex")
    p.add_argument("--long", action="store_true", help="read-buffer: the long form (u16 count)")


def _run_flash(c: Client, a) -> dict:
    """FLASH in maintenance mode (enter it with init --address 0x4000): the reply after byte 0 as
    hex, or the failure reply's kind and page."""
    from ground.link.flash_ops import FlashFailed, flash_command
    from protocol.flash import Sub

    key = a.sub.replace("-", "_").upper()
    try:
        sub = Sub(int(a.sub, 0)) if a.sub[:1].isdigit() else Sub[key]
    except (KeyError, ValueError):
        raise InputError(
            f"unknown FLASH subcommand {a.sub!r}; known: {', '.join(s.name.lower() for s in Sub)}"
        ) from None
    try:
        reply = flash_command(c, sub, *a.fields, data=a.data, long=a.long)
    except FlashFailed as exc:
        return {"sub": sub.name.lower(), "ok": False, "failure": exc.kind.name.lower(), "page": exc.page}
    return {"sub": sub.name.lower(), "ok": True, "reply_hex": reply.hex()}


def _a_heads(p):
    p.add_argument(
        "addresses",
        type=U8,
        nargs="+",
        help="the heads' NSP addresses (st16-device --heads; docs/ICD.md section 14)",
    )


def _run_heads(c: Client, a) -> dict:
    """Each head's state from its EDAC memory (one READ EDAC of 0x00-0x5C each) and, when a result
    is ready, its status; a head that does not answer is shown as such, the others still read."""
    import numpy as np

    from ground.link.client import LinkError
    from protocol import edac

    heads: dict[str, dict] = {}
    own = c.device_address
    try:
        for address in a.addresses:
            c.device_address = address
            name = f"0x{address:02X}"
            try:
                raw = c.read_edac(0, edac.offset("banner"))
            except LinkError as exc:
                heads[name] = {"answers": False, "error": str(exc)}
                continue
            rec = np.frombuffer(raw + bytes(edac.SIZE - len(raw)), dtype=edac.EDAC_DTYPE)[0]
            heads[name] = {
                "answers": True,
                "mode": "application" if rec["app_mode"] else "bootloader",
                "busy": bool(rec["busy"]),
                "result_ready": bool(int(rec["status"]) & edac.STATUS_RESULT_READY),
                "sequence": int(rec["sequence"]),
                "accepted": int(rec["accepted"]),
                "nacked": int(rec["nacked"]),
                "bad_crc": int(rec["bad_crc"]),
                "other_address": int(rec["other_address"]),
            }
            if heads[name]["result_ready"]:  # the last result's status (READ RESULT of the return code)
                from protocol import result

                try:
                    rc = int.from_bytes(c.read_result(4, 4), "little")
                except LinkError:
                    rc = None
                status = None if rc is None else result.status_of(rc)
                heads[name]["status"] = getattr(status, "name", status)
    finally:
        c.device_address = own
    return {"heads": heads}


def _a_send(p):
    p.add_argument("code", type=ranged(int, 0, 0x1F, "a command code (0x00-0x1F)"), help="command code 0x00-0x1F")
    p.add_argument("data", type=_hex, nargs="?", default=b"", help="data field as hex (default: empty)")
    p.add_argument("--silent", action="store_true", help="Poll = 0 (no reply expected)")


Run = Callable[["Client", argparse.Namespace], dict]


#: name -> (the command code the subcommand sends, whose one-line help in the protocol's command
#: table is the subcommand's; or, for a ground helper over several commands or any, its help;
#: add_arguments; run)
_SUBCOMMANDS: dict[str, tuple[Code | str, Callable, Run]] = {
    "ping": (Code.PING, _args_none, _run_ping),
    "time": (Code.TIME, _args_none, _run_time),
    "init": (Code.INIT, _a_init, _run_init),
    "diag": (Code.DIAGNOSTIC, _a_diag, _run_diag),
    "peek": (Code.PEEK, _args_addr_count, _run_peek),
    "poke": (Code.POKE, _args_addr_data, _run_poke),
    "read-edac": (Code.READ_EDAC, _args_addr_count, _run_read_edac),
    "write-edac": (Code.WRITE_EDAC, _args_addr_data, _run_write_edac),
    "read-file": (Code.READ_FILE, lambda p: _a_file(p, False), _run_read_file),
    "write-file": (Code.WRITE_FILE, lambda p: _a_file(p, True), _run_write_file),
    "crc": (Code.CRC, _a_crc, _run_crc),
    "go": (Code.GO, _a_go, _run_go),
    "result": (Code.READ_RESULT, _a_result, _run_result),
    "combination": (Code.COMBINATION, _a_combination, _run_combination),
    "dark-window": (Code.IMAGE, _a_dark, _run_dark_window),
    "image-poke": (Code.IMAGE, _a_image_poke, _run_image_poke),
    "upload": ("upload FILE into SLOT (resumable, then commit)", _a_upload, _run_upload),
    "slot-status": (Code.XFER_STATUS, _args_slot, _run_slot_status),
    "slot-abort": (Code.XFER_ABORT, _args_slot, _run_slot_abort),
    "slot-info": (Code.SLOT_INFO, _args_slot, _run_slot_info),
    "fault": (Code.FAULT, _a_fault, _run_fault),
    "send": ("send any command code with a hex data field", _a_send, _run_send),
    "heads": ("each head's state on a shared line (READ EDAC of every address given)", _a_heads, _run_heads),
    "flash": ("FLASH SUBCOMMAND [FIELDS]: the NAND in maintenance mode (docs/ICD.md section 15)", _a_flash, _run_flash),
}

#: name -> the command code the subcommand sends (the others are ground helpers)
CODES: dict[str, Code] = {name: what for name, (what, _, _) in _SUBCOMMANDS.items() if isinstance(what, Code)}

#: name -> (help, add_arguments, run)
COMMANDS: dict[str, tuple[str, Callable, Run]] = {
    name: (COMMAND_TABLE[what].help if isinstance(what, Code) else what, add_args, run)
    for name, (what, add_args, run) in _SUBCOMMANDS.items()
}


def render(obj: dict) -> str:
    """Human-readable rendering of a command's output dict."""
    if isinstance(obj, _Decoded):
        from ground.link.solve_report import format_record

        return format_record(obj)
    if set(obj) == {"banner"}:
        return obj["banner"]
    lines = []
    for key, value in obj.items():
        if isinstance(value, float):
            value = f"{value:.6g}"
        elif isinstance(value, int) and not isinstance(value, bool) and key in ("address", "crc32", "crc16"):
            value = f"0x{value:X}"
        elif isinstance(value, (dict, list)):
            value = json_text.dumps(value)
        lines.append(f"{key}: {value}")
    return "\n".join(lines)


def report_error(exc: LinkError, as_json: bool) -> int:
    """Report a failed exchange (one line on stderr, or a JSON object on stdout with every byte
    received) and return its exit code: 5 when the device refused (NACK), 4 for the link (no
    reply, a garbled one, a port gone)."""
    from ground.link.client import Nack

    payload: dict[str, Any] = {"error": type(exc).__name__, "message": str(exc), "raw": exc.raw.hex()}
    if isinstance(exc, Nack):
        payload["reason"] = exc.reason
    if as_json:
        print(json_text.dumps(payload))
    else:
        raw = payload["raw"]
        seen = f" (received {len(exc.raw)} B: {raw[:64]}{'...' if len(raw) > 64 else ''})" if raw else ""
        print(f"st16-ground: {payload['error']}: {payload['message']}{seen}", file=sys.stderr)
    return exit_code(exc)


def exit_code(exc: BaseException) -> int:
    """The documented exit code of a failure (``ground.cli.main.EXIT_CODES``): 5 the device refused
    (NACK), 4 the link (no reply, a garbled one, a port that fails or times out), 2 any other
    file or system error."""
    from serial import SerialException

    from ground.link.client import LinkError, Nack

    if isinstance(exc, Nack):
        return 5
    return 4 if isinstance(exc, (LinkError, SerialException, TimeoutError)) else 2


def add_commands(sub, handler_factory) -> None:
    """Add every command of :data:`COMMANDS` to ``sub`` with ``func=handler_factory(run)``."""
    for name, (help_text, add_args, run) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        add_args(p)
        p.set_defaults(func=handler_factory(run))
