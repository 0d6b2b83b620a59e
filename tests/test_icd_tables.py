"""docs/ICD.md's tables agree with the declarations in ``protocol/``: every command code with its
name, every NACK reason with its code, every EDAC field at its declared address; the command rows
are those of the command table (``protocol.command_table``), which the device dispatch and the
link subcommands also follow."""

import re
from pathlib import Path

from protocol import edac
from protocol.command_table import COMMANDS, TABLE
from protocol.commands import UNASSIGNED, Code, NackReason

ICD = (Path(__file__).resolve().parents[1] / "docs" / "ICD.md").read_text()


def _rows(pattern: str) -> list:
    return re.findall(pattern, ICD, flags=re.MULTILINE)


def test_every_command_code_is_in_the_icd_with_its_name():
    named = {
        int(code, 16): name.split("**")[0].strip().replace(" ", "_")
        for code, name in _rows(r"^\| 0x([0-9A-F]{2}) \| ([A-Z][A-Z _]+?(?:\*\*\[ours\]\*\*)?) \|")
    }
    for code in Code:
        assert named.get(int(code)) == code.name, (hex(code), named.get(int(code)))
    assert not set(named) & set(UNASSIGNED)


def test_every_nack_reason_is_in_the_icd_with_its_code():
    table = {name: int(code, 16) for code, name in _rows(r"^\| 0x(00[0-9A-F]{2}) \| ([A-Z_]+) \|")}
    for reason in NackReason:
        if reason.name == "VALIDATOR_BASE":
            continue
        assert table.get(reason.name) == int(reason), reason


def test_every_edac_field_is_in_the_icd_at_its_address():
    addresses = {int(a, 16) for a in _rows(r"^\| 0x(00[0-9A-F]{2}) \| (?:u32|\d+ × (?:f32|u32|u8)|64 B) ")}
    for name in ("status", "analog", "framing", "result_length", "total_length", "sequence", "address", "banner"):
        assert edac.offset(name) in addresses, name


def test_the_command_table_has_every_code_once():
    assert [c.code for c in TABLE] == list(Code)
    assert set(COMMANDS) == set(Code) and not set(COMMANDS) & set(UNASSIGNED)


def test_every_command_row_of_the_icd_is_the_command_table_row():
    lines = ICD.splitlines()
    for command in TABLE:
        assert command.icd_row() in lines, f"docs/ICD.md lacks, or differs from:\n{command.icd_row()}"
    coded = _rows(r"^(\| 0x[0-9A-F]{2} \| [A-Z][A-Z ]+(?: \*\*\[ours\]\*\*)? \|.*)$")
    assert sorted(coded) == sorted(c.icd_row() for c in TABLE)


def test_the_device_dispatches_exactly_the_command_table():
    from firmware_model.device.device import Device

    assert set(Device().dispatcher.handlers) == set(COMMANDS)


def test_link_subcommands_take_their_help_from_the_command_table():
    from ground.link.commands import CODES
    from ground.link.commands import COMMANDS as SUBCOMMANDS

    assert set(CODES.values()) <= set(COMMANDS)
    for name, code in CODES.items():
        assert SUBCOMMANDS[name][0] == COMMANDS[code].help, name
