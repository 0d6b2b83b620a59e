"""``st16-ground export``: the OpenC3 target parses with openc3's own ``Target`` and ``PacketConfig``
(every command and reply, the result's item offsets those of ``protocol.result``), an openc3
interface built from the generated ``plugin.txt`` talks to a running ``st16-device`` and decodes
what our own client decodes, the XTCE parses back with every parameter, and bad input is refused
in one line. The openc3 and yamcs-pymdb tests skip without the ``[ground-systems]`` extra."""

import enum
import importlib.util
import re
import shlex
import struct
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest
from conftest import SHARED, require_shared, required

from ground.cli.main import main
from ground.link.client import Client
from ground.testing.device_proc import DeviceProcess
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
    assert len(offsets) > 750  # every scalar of the structure (29 extension stars of 10 fields among them)
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


def render_plugin(text: str, values: dict[str, str]) -> str:
    """plugin.txt as COSMOS renders it on install (Ruby ERB with the VARIABLEs as local
    variables): the subset the generated file uses, ``<%= name %>`` and one level of
    ``<% if name == "value" %>`` / ``<% else %>`` / ``<% end %>``; anything else fails."""
    variables = {w[1]: w[2] for w in map(shlex.split, text.splitlines()) if w[:1] == ["VARIABLE"]}
    assert set(values) <= set(variables), set(values) - set(variables)
    variables.update(values)
    out, taking = [], []
    for line in text.splitlines():
        if m := re.fullmatch(r'<% if (\w+) == "([^"]*)" %>', line.strip()):
            assert not taking, "nested condition"
            taking.append(variables[m[1]] == m[2])
        elif line.strip() == "<% else %>":
            taking[-1] = not taking[-1]
        elif line.strip() == "<% end %>":
            taking.pop()
        elif all(taking):
            line = re.sub(r"<%= (\w+) %>", lambda m: variables[m[1]], line)
            assert "<%" not in line, line
            out.append(line)
    assert not taking
    return "\n".join(out) + "\n"


class Openc3Link:
    """The interface and protocol stack that the generated plugin.txt declares for the variables
    ``values`` (rendered as COSMOS renders it), built as COSMOS's interface microservice builds
    it (class from file name, arguments as written: the read timeout too); packets built from
    the generated command definitions, replies identified and decoded by the generated telemetry
    definitions. Interface OPTIONs are kept in :attr:`options`, not applied: the keep-alive PING
    goes through COSMOS's command API, which needs a server."""

    def __init__(self, root: Path, values: dict[str, str]):
        from openc3.packets.telemetry import Telemetry
        from openc3.top_level import get_class_from_module
        from openc3.utilities.string import filename_to_class_name, filename_to_module

        self.config = _packet_config(root)
        self.telemetry = Telemetry(self.config, None)
        text = render_plugin((root / "plugin.txt").read_text(), values)
        self.lib = str(root / "targets" / TARGET / "lib")
        sys.path.insert(0, self.lib)  # COSMOS puts a target's lib/ on the path
        self.interface = None
        self.interfaces, self.options = [], []
        for words in map(shlex.split, text.splitlines()):
            if words[:1] == ["INTERFACE"]:
                self.interfaces.append(words)
                klass = get_class_from_module(filename_to_module(words[2]), filename_to_class_name(words[2]))
                self.interface = klass(*words[3:])
            elif words[:1] == ["OPTION"]:
                self.options.append(words[1:])
            elif words[:1] == ["PROTOCOL"]:
                klass = get_class_from_module(filename_to_module(words[2]), filename_to_class_name(words[2]))
                self.interface.add_protocol(klass, words[3:], words[1])
        assert len(self.interfaces) == 1, self.interfaces  # the link variable picks one
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


LINKS = {"serial": ("--pty",), "tcp": ("--tcp", "127.0.0.1:0")}


def _values(link: str, path: str) -> dict[str, str]:
    """plugin.txt's variables for a device serving ``path`` (a pty, or socket://HOST:PORT)."""
    if link == "serial":
        return {"link": "serial", "port": path}
    url = urlsplit(path)
    assert url.scheme == "socket" and url.hostname and url.port, path
    return {"link": "tcp", "host": url.hostname, "tcp_port": str(url.port)}


def test_plugin_declares_both_links_with_a_finite_read_timeout_and_a_keepalive(tmp_path):
    required("openc3")
    from ground.export.openc3 import PROTOCOLS

    root = _export(tmp_path)
    text = (root / "plugin.txt").read_text()
    for link, file in (("serial", "serial_interface.py"), ("tcp", "tcpip_client_interface.py")):
        rendered = render_plugin(text, {"link": link})
        (interface,) = [shlex.split(line) for line in rendered.splitlines() if line.startswith("INTERFACE")]
        assert interface[2] == f"openc3/interfaces/{file}"
        write_timeout, read_timeout = map(float, interface[-2:])  # both interfaces end with them
        assert 0 < read_timeout < 60 and write_timeout > 0
        (option,) = [shlex.split(line) for line in rendered.splitlines() if "PERIODIC_CMD" in line]
        assert option[:3] == ["OPTION", "PERIODIC_CMD", "DONT_LOG"] and option[4] == f"{TARGET} PING"
        assert 0 < float(option[3]) < read_timeout  # the keep-alive comes before the timeout
        assert [w[2] for w in map(shlex.split, rendered.splitlines()) if w[:1] == ["PROTOCOL"]] == [
            path for path, _ in PROTOCOLS
        ]
    assert "nil" not in render_plugin(text, {}).split("INTERFACE", 1)[1].split("\n", 1)[0]


@pytest.mark.parametrize("link", LINKS)
def test_openc3_interface_against_the_device_decodes_what_our_client_does(tmp_path, link):
    """Over a pty (the serial interface) and over TCP (``st16-device --tcp 127.0.0.1:0``, the
    TCP client interface): the same plugin.txt, its link variable set."""
    required("openc3")
    from ground.export.openc3 import quiet_logger

    root = _export(tmp_path)
    transport = link
    with DeviceProcess(*LINKS[transport]) as device, quiet_logger():
        values = _values(transport, device.path)
        link = Openc3Link(root, values)
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

        # COMBINATION: a sequence, then one packet per section bit (the device sends the 1 544
        # bytes as one stream in 2 messages counting bytes already transmitted, ICD page 1-35918;
        # NspProtocol splits them by the mask it wrote), nothing more (the next packet is the next
        # command's); a mask of 0: one empty COMBINATION_REPLY (the target's README says so)
        link = Openc3Link(root, values)
        try:
            mask = 0x0001 | 0x0002 | 0x0004 | 0x1000
            link.send("COMBINATION_MASK_BYTES3", GO_CODE=GO_OPERATIONAL, MASK=mask & 0xFFFF, MASK_HIGH=mask >> 16)
            sections = {p.packet_name: p for p in (link.receive() for _ in range(bin(mask).count("1")))}
            assert link.command("PING").packet_name == "PING_REPLY"
            empty = link.command("COMBINATION_MASK_BYTES3", GO_CODE=0, MASK=0, MASK_HIGH=0)
            assert empty.packet_name == "COMBINATION_REPLY" and len(empty.buffer) == 3
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


def test_nsp_protocol_splits_a_counted_combination_reply_by_the_mask_it_wrote(tmp_path):
    """The generated lib/nsp_protocol.py alone: a COMBINATION command written with mask
    0x1000 | 0x0400 | 0x0001 (3-byte form), then the device's reply (ICD page 1-35918: counts 0
    and 1 024) gives one message per section, the section's address in bytes 0-1, Final on the
    last (one per read: the blank-string read drains them); without a remembered mask, or with
    a count that does not continue, the reply passes joined; a zero mask gives no data."""
    required("openc3")
    from firmware_model.device.device import Device
    from protocol import nsp
    from protocol.commands import Code, Combination

    root = _export(tmp_path)
    spec = importlib.util.spec_from_file_location("nsp_protocol", root / "targets" / TARGET / "lib" / "nsp_protocol.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    dev = Device()
    dev.handle(nsp.command(0x0E, 0x02, Code.INIT, (0x2000).to_bytes(4, "little")))

    def wire(mask):
        command = nsp.command(0x0E, 0x02, Code.COMBINATION, Combination(0x00, mask, 3).pack())
        return command.encode()[:-2], [m.encode()[:-2] for m in dev.handle(command)]  # CRC stripped

    def read_all(protocol, messages):
        out = []
        for m in messages:
            data, _ = protocol.read_data(m)
            while data not in ("STOP", b""):  # alone, not last of an interface's chain: b"", not STOP
                out.append(bytes(data))
                data, _ = protocol.read_data(b"")
        return out

    mask = 0x1000 | 0x0400 | 0x0001
    command, reply = wire(mask)
    assert [int.from_bytes(m[3:5], "little") for m in reply] == [0, 1024]
    stream = b"".join(m[5:] for m in reply)
    protocol = module.NspProtocol()
    assert protocol.write_data(command) == (command, None)
    out = read_all(protocol, reply)
    sections = [(0x000, 4), (0x7E8, 352), (0xA38, 1504)]
    assert [int.from_bytes(m[3:5], "little") for m in out] == [a for a, _ in sections]
    assert [m[2] & 0x80 for m in out] == [0, 0, 0x80] and all(m[2] & 0x20 for m in out)
    assert b"".join(m[5:] for m in out) == stream and [len(m) - 5 for m in out] == [n for _, n in sections]
    assert read_all(module.NspProtocol(), reply) == [reply[-1][:3] + bytes(2) + stream]  # no mask: joined
    protocol.write_data(command)
    assert read_all(protocol, reply[1:]) == [reply[-1][:3] + (1024).to_bytes(2, "little") + reply[1][5:]]
    command, reply = wire(0)
    protocol.write_data(command)
    assert read_all(protocol, reply) == [reply[0][:3]]


def test_the_target_readme_says_what_the_operator_must_know(tmp_path):
    """README.md of the plugin: the packets a COMBINATION returns per mask bit (the end-to-end
    test checks them on a device), the MASK / MASK_HIGH split, how lib/nsp_protocol.py loads."""
    required("openc3")
    from firmware_model.device.sequence import RESULT_PART
    from ground.export.openc3 import DEVICE_PART

    assert DEVICE_PART == RESULT_PART
    root = _export(tmp_path)
    text = (root / "README.md").read_text()
    telemetry = _packet_config(root).telemetry[TARGET]
    rows = re.findall(r"^\| 0x([0-9A-F]{4}) \| `(\w+)` \| 0x([0-9A-F]{3}) \| (\d+) \|$", text, re.M)
    assert len(rows) == len(result.SECTIONS)
    for mask, name, address, length in rows:
        assert result.SECTIONS[int(mask, 16)] == (int(address, 16), int(length))
        assert telemetry[name].items["ADDRESS"].id_value == int(address, 16)
    assert f"at most {RESULT_PART} result bytes" in text and "ICD page 1-35918" in text
    assert "one telemetry packet per bit set in the mask" in text
    assert "`MASK = mask & 0xFFFF` and `MASK_HIGH = mask >> 16`" in text
    assert max(result.SECTIONS) <= 0xFFFF  # so MASK_HIGH is 0, as the README says
    assert "`targets/ST16/lib/nsp_protocol.py`" in text and "PROTOCOL" in text and "NspProtocol" in text
    assert "scalar_last" in text


# ----------------------------------------------------------------------------- XTCE


def test_xtce_holds_every_parameter(tmp_path):
    required("yamcs.pymdb")
    from ground.export import model, xtce

    path = tmp_path / "st16.xml"
    assert main(["export", "xtce", str(path)]) == 0
    ns = {"x": "http://www.omg.org/spec/XTCE/20180204"}
    tree = ET.parse(path).getroot()
    system = model.build()
    header = len(model.header(0, False))
    # COMBINATION_<SECTION> is the OpenC3 target's (its NspProtocol re-addresses the sections); on
    # the wire a COMBINATION reply counts bytes already transmitted (ICD page 1-35918)
    telemetry = xtce.wire_telemetry(system)
    assert {p.name for p in system.telemetry} - {p.name for p in telemetry} == {
        p.name for p in system.telemetry if p.name.startswith("COMBINATION_") and p.name != "COMBINATION_REPLY"
    }
    assert len(telemetry) == len(system.telemetry) - len(result.SECTIONS)
    expected = header + sum(
        # a packet told apart by its address takes ADDRESS from its code's generic reply
        1
        for p in telemetry
        for f in p.fields[header:]
        if f.bits and f.id_value is None
    )
    assert len(tree.findall(".//x:ParameterSet/x:Parameter", ns)) == expected
    containers = {c.get("name") for c in tree.findall(".//x:SequenceContainer", ns)}
    assert containers == {"NSP_REPLY", *(p.name for p in telemetry)}
    assert {c.get("name") for c in tree.findall(".//x:MetaCommand", ns)} == {p.name for p in system.commands}


XTCE_SCHEMA = SHARED / "data" / "xtce" / "SpaceSystemV1.2.xsd"


def test_xtce_validates_against_the_xtce_1_2_schema(tmp_path, capsys):
    """0 errors against the OMG schema (there were 26: every command's CODE initialValue was
    the code's name, an enum member as yamcs-pymdb writes it), said by the export itself."""
    required("yamcs.pymdb")
    required("xmlschema")
    schema = require_shared(XTCE_SCHEMA)
    from ground.export import model, xtce

    path = tmp_path / "st16.xml"
    assert main(["export", "xtce", str(path), "--schema", str(schema)]) == 0
    assert capsys.readouterr().out.strip().endswith(f"0 errors against {schema.name}")
    assert xtce.schema_errors(path.read_text(), schema) == []
    import xmlschema

    xmlschema.XMLSchema(str(schema)).validate(str(path))  # and as xmlschema's own validate sees it
    # the command codes are numbers in the file, each its command's
    ns = {"x": "http://www.omg.org/spec/XTCE/20180204"}
    types = {t.get("name"): t for t in ET.parse(path).getroot().iterfind(".//x:IntegerArgumentType", ns)}
    for p in model.build().commands:
        (code,) = [f for f in p.fields if f.name == "CODE"]
        assert types[f"{p.name}__CODE"].get("initialValue") == str(code.default)
    # no field of the description holds an enum member (a writer may spell it by its name)
    for p in model.build().commands + model.build().telemetry:
        for f in p.fields:
            assert not isinstance(f.default, enum.Enum) and not isinstance(f.id_value, enum.Enum), (p.name, f.name)


def test_an_xtce_that_breaks_the_schema_is_refused_naming_its_first_errors(tmp_path, capsys, monkeypatch):
    required("yamcs.pymdb")
    schema = require_shared(XTCE_SCHEMA)
    from ground.export import xtce

    dumps = xtce.dumps

    def broken(system, name=xtce.SYSTEM):  # the bug of issue 31: initialValue="PING"
        return re.sub(r'(name="PING__CODE"[^>]*initialValue=)"\d+"', r'\1"PING"', dumps(system, name))

    monkeypatch.setattr(xtce, "dumps", broken)
    path = tmp_path / "st16.xml"
    assert main(["export", "xtce", str(path), "--schema", str(schema)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("st16-ground: XTCE not written: 1 errors against")
    assert "(PING__CODE): attribute initialValue='PING'" in err
    assert not path.exists() and list(tmp_path.iterdir()) == []
    assert main(["export", "xtce", str(path), "--schema", str(tmp_path / "none.xsd")]) == 2
    assert "no such file" in capsys.readouterr().err


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
    written = sorted(str(p.relative_to(tmp_path / "openc3")) for p in (tmp_path / "openc3").rglob("*"))
    assert sorted(str(p.relative_to(docs / "openc3")) for p in (docs / "openc3").rglob("*")) == written
    for path in (docs / "openc3").rglob("*"):
        if path.is_file():
            assert filecmp.cmp(path, tmp_path / "openc3" / path.relative_to(docs / "openc3"), shallow=False), path
