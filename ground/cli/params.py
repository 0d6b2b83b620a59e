"""``st16-ground params upload FILE``: validate a device parameter set (JSON, slot 2) as the device
would, then upload and commit it."""

from __future__ import annotations

from ground import json_text
from ground.arg_types import InputError, progress_on
from protocol.commands import Slot


def _params_upload(args) -> int:
    from firmware_model import user_files
    from firmware_model.device.sensor_input import DeviceParams
    from ground.cli.link import open_client, render, report_error
    from ground.link.client import LinkError
    from protocol.commands import SlotRejected

    try:  # a FIFO or a device refused, the size bounded before reading
        data = user_files.read_bytes(args.file, user_files.MAX_JSON_BYTES)
    except user_files.UserFileError as exc:
        raise InputError(str(exc)) from None
    try:
        DeviceParams.from_json(data)  # refuse locally what the device would refuse
    except SlotRejected as exc:
        raise InputError(f"{args.file}: {exc.message}") from None
    with open_client(args) as client:
        try:
            client.upload(Slot.PARAMS, data, progress=progress_on(args))
            info = client.slot_info(Slot.PARAMS)
        except LinkError as exc:
            return report_error(exc, args.json)
    out = {"slot": 2, "active": info.active, "length": info.length, "crc32": f"0x{info.crc32:08X}"}
    print(json_text.dumps(out) if args.json else render(out))
    return 0


def register(sub) -> None:
    params = sub.add_parser("params", help="device parameter sets (slot 2)")
    psub = params.add_subparsers(dest="params_command", metavar="ACTION")
    psub.required = True
    p = psub.add_parser("upload", help="validate and upload a JSON parameter set")
    p.add_argument("file", help="parameter set JSON (e.g. colour fit's .params.json)")
    p.set_defaults(func=_params_upload)
