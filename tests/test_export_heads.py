"""Exports of several heads on one line (ground/export/heads.py, issue 45): one OpenC3 target or
XTCE subsystem per NSP address, commands sent to it, replies identified by it."""

import subprocess
import sys

import pytest

from ground.export import heads, model


def test_each_heads_system_sends_to_and_identifies_by_its_address():
    system = heads.for_address(model.build(), 0x0F)
    for p in system.commands:
        assert next(f for f in p.fields if f.name == "DST").default == 0x0F
    for p in system.telemetry:
        assert next(f for f in p.fields if f.name == "SRC").id_value == 0x0F
    plugin = heads.plugin(["ST16_0E", "ST16_0F"])
    assert "TARGET ST16_0E" in plugin and "TARGET ST16_0F" in plugin
    assert plugin.count("MAP_TARGET") == 2 and plugin.count("INTERFACE ST16_BUS_INT") == 2  # serial or tcp


@pytest.mark.parametrize("bad", [[], [1, 2, 3, 4, 5], [14, 14], [0x100]])
def test_bad_head_lists_are_refused(bad):
    with pytest.raises(ValueError):
        heads.check_addresses(bad)


def test_the_openc3_plugin_of_two_heads_parses(tmp_path):
    pytest.importorskip("openc3")
    out = tmp_path / "plugin"
    run = subprocess.run(
        [sys.executable, "-m", "ground.cli", "export", "openc3", str(out), "--heads", "0x0E,0x0F"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    assert sorted(p.name for p in (out / "targets").iterdir()) == ["ST16_0E", "ST16_0F"]
    assert "ID_ITEM SRC 8 8 UINT 15" in (out / "targets" / "ST16_0F" / "cmd_tlm" / "tlm.txt").read_text()


def test_the_xtce_of_two_heads_has_a_subsystem_each():
    pytest.importorskip("yamcs.pymdb")
    text = heads.xtce_dumps(model.build(), [0x0E, 0x0F])
    assert 'name="ST16_BUS"' in text and 'name="ST16_0E"' in text and 'name="ST16_0F"' in text
