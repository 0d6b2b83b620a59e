"""``st16-ground export``: the OpenC3 target parses with openc3's own ``Target`` and ``PacketConfig``
(every command and reply, the result's item offsets those of ``protocol.result``), an openc3
interface built from the generated ``plugin.txt`` talks to a running ``st16-device`` and decodes
what our own client decodes, the XTCE parses back with every parameter, and bad input is refused
in one line. The openc3 and yamcs-pymdb tests skip without the ``[ground-systems]`` extra."""

import importlib.util
import shlex
import struct
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from conftest import required

from ground.cli.main import main
from ground.fuzz.device_proc import DeviceProcess
from ground.link.client import Client
from protocol import edac, result, telemetry_meta
from protocol.command_table import TABLE
from protocol.commands import GO_OPERATIONAL
from protocol.result import Status

TARGET = "ST16"
HEADER_BITS = 40  #: dst, src, MCF, u16 address before the result bytes of a RESULT packet


def _export(tmp_path: Path) -> Path:
    root = tmp_path / "target"
    assert main(["export", "openc3", str(root)]) == 0
    return root


def _packet_config(root: Path):
    from openc3.packets.packet_config import PacketConfig
    from openc3.system.target import Target

    from ground.export.openc3 import quiet_logger

    with quiet_logger():
        config = PacketConfig()
        for path in Target(TARGET, str(root / "targets")).cmd_tlm_files:
            config.process_file(str(path), TARGET)
    assert config.warnings == []
    return config


def _flat_offsets(dt: np.dtype, base: int = 0, prefix: str = "") -> dict[str, tuple[int, np.dtype]]:
    """Byte offset and dtype of every number of a structured dtype, named as the target names
    its items (an array of bytes is one item)."""
    out = {}
    for name in dt.names:
        sub, off = dt.fields[name][:2]
        label = f"{prefix}{name}".upper()
        if sub.subdtype is not None and not (sub.base.kind == "u" and sub.base.itemsize == 1):
            elem, shape = sub.subdtype
            for index in np.ndindex(shape):
                at = base + off + elem.itemsize * int(np.ravel_multi_index(index, shape))
                key = label + "".join(f"_{i}" for i in index)
                if elem.names:
                    out.update(_flat_offsets(elem, at, key + "_"))
                else:
                    out[key] = (at, elem)
        elif sub.names:
            out.update(_flat_offsets(sub, base + off, label + "_"))
        else:
            out[label] = (base + off, sub)
    return out


def _same(decoded, data: bytes, offset: int, dt: np.dtype) -> bool:
    """Whether an item openc3 decoded equals the value at ``offset`` of ``data``."""
    if dt.subdtype is not None:  # bytes
        return bytes(decoded) == data[offset : offset + dt.itemsize]
    value = np.frombuffer(data, dt, 1, offset)[0]
    if dt.kind == "S":
        return decoded == value.decode()
    return decoded == value or (dt.kind == "f" and np.isnan(value) and np.isnan(decoded))


def test_definitions_parse_with_openc3_and_follow_protocol(tmp_path):
    required("openc3")
    from ground.export import model

    config = _packet_config(_export(tmp_path))
    commands, telemetry = config.commands[TARGET], config.telemetry[TARGET]
    for cmd in TABLE:
        forms = len(cmd.request.forms()) if cmd.request else 1
        assert len([n for n in commands if n.startswith(cmd.code.name)]) >= forms, cmd.code.name
        assert f"{cmd.code.name}_REPLY" in telemetry
    system = model.build()
    assert set(commands) == {p.name for p in system.commands}
    assert set(telemetry) == {p.name for p in system.telemetry}
    assert {"RESULT", "NACK", "COMBINATION_QUATERNION", "COMBINATION_EXT", "EDAC_RESULT_LENGTH"} <= set(telemetry)

    packet = telemetry["RESULT"]
    offsets = _flat_offsets(result.RESULT)
    assert len(offsets) > 800
    for name, (offset, dt) in offsets.items():
        item = packet.items[name]
        assert (item.bit_offset, item.bit_size) == (HEADER_BITS + 8 * offset, 8 * dt.itemsize), name
    assert packet.defined_length == HEADER_BITS // 8 + result.TOTAL_LENGTH
    # states, units and limits from protocol/telemetry_meta
    assert packet.items["RETURN_CODE_STATUS"].states == {s.name: s.value for s in Status}
    assert packet.items["EXT_METHOD"].states == {m.name: m.value for m in result.MethodCode}
    assert packet.items["OMEGA_0"].units == "rad_per_s"
    assert telemetry["EDAC_RESULT_LENGTH"].items["ADDRESS"].id_value == edac.RESULT_LENGTH
    current = telemetry["EDAC_ANALOG"].items["ANALOG_CURRENT"]
    assert current.units == "A" and current.limits.values["DEFAULT"] == list(
        telemetry_meta.analog_limits(telemetry_meta.ANALOG[0])
    )
    # the analog frame's declaration is what an idle device reports (within its noise)
    from firmware_model.device.housekeeping import Housekeeping

    idle = Housekeeping().analog_frame()
    assert idle == pytest.approx([a.nominal for a in telemetry_meta.ANALOG], rel=0.05)


# ----------------------------------------------------------------------------- end to end


class Openc3Link:
    """The interface and protocol stack that the generated plugin.txt declares, built as COSMOS's
    interface microservice builds it (class from file name, arguments as written), on ``port``;
    packets built from the generated command definitions, replies identified and decoded by the
    generated telemetry definitions."""

    def __init__(self, root: Path, port: str):
        from openc3.packets.telemetry import Telemetry
        from openc3.top_level import get_class_from_module
        from openc3.utilities.string import filename_to_class_name, filename_to_module

        self.config = _packet_config(root)
        self.telemetry = Telemetry(self.config, None)
        text = (root / "plugin.txt").read_text()
        variables = {w[1]: w[2] for w in map(shlex.split, text.splitlines()) if w[:1] == ["VARIABLE"]}
        variables["port"] = port
        for name, value in variables.items():
            text = text.replace(f"<%= {name} %>", value)
        self.lib = str(root / "targets" / TARGET / "lib")
        sys.path.insert(0, self.lib)  # COSMOS puts a target's lib/ on the path
        self.interface = None
        for words in map(shlex.split, text.splitlines()):
            if words[:1] not in (["INTERFACE"], ["PROTOCOL"]):
                continue
            klass = get_class_from_module(filename_to_module(words[2]), filename_to_class_name(words[2]))
            if words[0] == "INTERFACE":
                self.interface = klass(*words[3:-1], "10.0")  # a read timeout instead of blocking for ever
            else:
                self.interface.add_protocol(klass, words[3:], words[1])
        self.interface.connect()

    def send(self, name: str, **values):
        packet = self.config.commands[TARGET][name].clone()
        packet.restore_defaults()
        for item, value in values.items():
            packet.write(item, value)
        self.interface.write(packet)

    def receive(self):
        raw = self.interface.read()
        assert raw is not None, "no reply"
        packet = self.telemetry.identify_and_define_packet(raw, [TARGET])
        assert packet is not None, bytes(raw.buffer).hex()
        return packet

    def command(self, name: str, **values):
        self.send(name, **values)
        return self.receive()

    def close(self):
        self.interface.disconnect()
        sys.path.remove(self.lib)


def test_openc3_interface_against_the_device_decodes_what_our_client_does(tmp_path):
    required("openc3")
    from ground.export.openc3 import quiet_logger

    root = _export(tmp_path)
    with DeviceProcess("--pty") as device, quiet_logger():
        link = Openc3Link(root, device.path)
        try:
            boot = link.command("PING")
            assert boot.packet_name == "PING_REPLY"
            assert link.command("INIT").packet_name == "INIT_REPLY"
            refused = link.command("INIT")  # already in application mode
            assert refused.packet_name == "NACK" and refused.read("REASON") == "WRONG_MODE"
            app = link.command("PING").read("DATA")
            analog = link.command("READ_EDAC_LONG0", ADDRESS=edac.offset("analog"), COUNT=32)
            assert analog.packet_name == "EDAC_ANALOG"
            assert link.command("READ_EDAC_LONG0", ADDRESS=edac.RESULT_LENGTH, COUNT=4).read("RESULT_LENGTH") == 0
            go = link.command("GO", GO_CODE=GO_OPERATIONAL)
            assert go.packet_name == "GO_REPLY" and go.read("GO_CODE") == GO_OPERATIONAL
            deadline = time.monotonic() + 30
            while (length := link.command("READ_EDAC_LONG0", ADDRESS=edac.RESULT_LENGTH, COUNT=4)).read(
                "RESULT_LENGTH"
            ) == 0:
                assert time.monotonic() < deadline
            assert length.packet_name == "EDAC_RESULT_LENGTH"
            whole = link.command("READ_RESULT_LONG1", ADDRESS=0, COUNT=result.TOTAL_LENGTH)  # 5 parts, joined
            assert whole.packet_name == "RESULT"
            first = bytes(whole.buffer[5:])
            flat = _flat_offsets(result.RESULT)
            decoded_first = {name: whole.read(name, "RAW") for name in flat}
        finally:
            link.close()
        with Client(device.path) as client:
            assert client.ping() == app and boot.read("DATA").startswith("ST16-EMU BOOTLOADER")
            # two reads, possibly of two 1 Hz samples of the supervisor ADC (docs/ICD.md): equal within noise
            assert [analog.read(f"ANALOG_{a.name.upper()}") for a in telemetry_meta.ANALOG] == pytest.approx(
                struct.unpack("<8f", client.read_edac(edac.offset("analog"), 32)), rel=0.05
            )
            assert length.read("RESULT_LENGTH") == client.result_length() == result.STANDARD_LENGTH
            ours = client.read_result()
            rec = result.parse(ours)
        assert first == ours  # every byte of the result
        differ = [n for n in flat if not _same(decoded_first[n], ours, *flat[n])]
        assert differ == []  # every item decoded as protocol.result reads it
        assert decoded_first["SEQUENCE"] == int(rec["sequence"]) >= 1
        assert decoded_first["RETURN_CODE"] == int(rec["return_code"])
        assert whole.read("RETURN_CODE_STATUS") == result.status_of(int(rec["return_code"])).name
        assert [decoded_first[f"QUATERNION_{i}"] for i in range(4)] == list(rec["quaternion"])
        assert decoded_first["EPOCH"] == float(rec["epoch"]) > 0
        assert decoded_first["EXT_MAGIC"] == result.EXT_MAGIC
        assert whole.read("EXT_REASON") == rec["ext"]["reason"].decode() != ""

        # COMBINATION: a sequence, then one message per section (the extension joined from 2 parts)
        link = Openc3Link(root, device.path)
        try:
            mask = 0x0001 | 0x0002 | 0x0004 | 0x1000
            link.send("COMBINATION_MASK_BYTES3", GO_CODE=GO_OPERATIONAL, MASK=mask)
            sections = {p.packet_name: p for p in (link.receive() for _ in range(4))}
        finally:
            link.close()
        with Client(device.path) as client:
            rec = client.read_result_record()
    assert set(sections) == {
        "COMBINATION_SEQUENCE",
        "COMBINATION_RETURN_CODE",
        "COMBINATION_QUATERNION",
        "COMBINATION_EXT",
    }
    assert sections["COMBINATION_SEQUENCE"].read("SEQUENCE") == int(rec["sequence"]) == decoded_first["SEQUENCE"] + 1
    assert sections["COMBINATION_RETURN_CODE"].read("RETURN_CODE") == int(rec["return_code"])
    quaternion = sections["COMBINATION_QUATERNION"]
    assert [quaternion.read(f"QUATERNION_{i}") for i in range(4)] == list(rec["quaternion"])
    ext = sections["COMBINATION_EXT"]
    assert ext.read("EXT_MAGIC") == result.EXT_MAGIC and ext.read("EXT_REASON") == rec["ext"]["reason"].decode()
    assert len(ext.buffer) == 5 + result.EXTENSION.itemsize


# ----------------------------------------------------------------------------- XTCE


def test_xtce_holds_every_parameter(tmp_path):
    required("yamcs.pymdb")
    from ground.export import model

    path = tmp_path / "st16.xml"
    assert main(["export", "xtce", str(path)]) == 0
    schema = _packaged_xtce_schema()
    if schema is not None:  # none of the installed packages ships one (checked: see docs/ground_systems.md)
        import xmlschema

        xmlschema.XMLSchema(schema).validate(str(path))
    ns = {"x": "http://www.omg.org/spec/XTCE/20180204"}
    tree = ET.parse(path).getroot()
    system = model.build()
    header = len(model.header(0, False))
    expected = header + sum(
        # a packet told apart by its address takes ADDRESS from its code's generic reply
        1
        for p in system.telemetry
        for f in p.fields[header:]
        if f.bits and f.id_value is None
    )
    assert len(tree.findall(".//x:ParameterSet/x:Parameter", ns)) == expected
    containers = {c.get("name") for c in tree.findall(".//x:SequenceContainer", ns)}
    assert containers == {"NSP_REPLY", *(p.name for p in system.telemetry)}
    assert {c.get("name") for c in tree.findall(".//x:MetaCommand", ns)} == {p.name for p in system.commands}


def _packaged_xtce_schema() -> Path | None:
    for site in map(Path, sys.path):
        for xsd in site.glob("*/**/SpaceSystem*.xsd") if site.is_dir() else ():
            return xsd
    return None


# ----------------------------------------------------------------------------- bad input


def test_export_into_a_non_empty_directory_needs_force_and_a_file_is_replaced(tmp_path, capsys):
    root = tmp_path / "target"
    root.mkdir()
    (root / "keep.txt").write_text("mine")
    assert main(["export", "openc3", str(root)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"st16-ground: {root} is not an empty directory: add --force to write over it"
    assert [p.name for p in root.iterdir()] == ["keep.txt"]
    existing = tmp_path / "st16.xml"  # a named output file is replaced, as everywhere (docs/cli.md)
    existing.write_text("mine")
    if importlib.util.find_spec("yamcs") is not None:
        assert main(["export", "xtce", "-o", str(existing)]) == 0
        assert existing.read_text() != "mine"


@pytest.mark.parametrize(("fmt", "module"), [("openc3", "openc3"), ("xtce", "yamcs")])
def test_a_missing_extra_is_named(tmp_path, capsys, monkeypatch, fmt, module):
    for name in [module, *(n for n in sys.modules if n.startswith(module + "."))]:
        monkeypatch.setitem(sys.modules, name, None)  # import fails as if not installed
    out = tmp_path / "out"
    assert main(["export", fmt, str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "colour-st16[ground-systems]" in err[0], err
    assert not out.exists()


def test_an_openc3_without_a_needed_feature_names_its_version(tmp_path, capsys, monkeypatch):
    required("openc3")
    from importlib.metadata import version

    from openc3.interfaces.protocols import crc_protocol

    class CrcProtocol:  # an older one: no reflect argument, so no CRC-16/MCRF4XX
        def __init__(self, write_item_name=None, strip_crc=False):
            pass

    monkeypatch.setattr(crc_protocol, "CrcProtocol", CrcProtocol)
    out = tmp_path / "out"
    assert main(["export", "openc3", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"st16-ground: openc3 {version('openc3')}: CrcProtocol has no 'reflect' argument")
    assert not out.exists()


def test_docs_examples_are_what_the_exporter_writes(tmp_path):
    """docs/examples holds the generated target and XTCE; regenerate them when protocol/ changes:
    ``st16-ground export openc3 docs/examples/openc3 --force``, ``export xtce docs/examples/st16.xtce.xml --force``."""
    required("openc3")
    required("yamcs.pymdb")
    import filecmp
    import subprocess

    docs = Path(__file__).resolve().parents[1] / "docs" / "examples"
    for args in (["openc3", str(tmp_path / "openc3")], ["xtce", str(tmp_path / "st16.xtce.xml")]):
        run = subprocess.run([sys.executable, "-m", "ground.cli", "export", *args], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
    assert (tmp_path / "st16.xtce.xml").read_bytes() == (docs / "st16.xtce.xml").read_bytes()
    for path in (docs / "openc3").rglob("*"):
        if path.is_file():
            assert filecmp.cmp(path, tmp_path / "openc3" / path.relative_to(docs / "openc3"), shallow=False), path
