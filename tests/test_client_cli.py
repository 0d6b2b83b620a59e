"""``st16-ground`` link subcommands and the console, against a device served on a pty."""

import io
import json
from datetime import UTC

import pytest

from ground.cli.main import main
from ground.link.client import Client
from ground.link.console import Console


@pytest.fixture
def port(served_device):
    return served_device


def run_json(port, capsys, *argv):
    rc = main(["--port", port, "--json", *argv])
    return rc, json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_cli_commands_json(port, capsys, tmp_path):
    assert run_json(port, capsys, "ping")[1]["banner"].startswith("ST16-EMU BOOTLOADER")
    assert run_json(port, capsys, "init")[1]["banner"].startswith("ST16-EMU APPLICATION")
    assert run_json(port, capsys, "write-edac", "0x100", "dead")[1]["written"] == 2
    assert run_json(port, capsys, "read-edac", "0x100", "2")[1]["hex"] == "dead"
    rc, out = run_json(port, capsys, "write-edac", "0x10", "00")
    assert rc == 5 and out["error"] == "Nack" and out["reason"] == 4 and out["raw"].startswith("c0110e")
    assert run_json(port, capsys, "go", "--wait")[1]["status"] == "NO_CATALOG"
    image = tmp_path / "params.json"
    image.write_text('{"fov_deg": 20}')
    assert run_json(port, capsys, "upload", "2", str(image), "--no-progress")[1]["sent"] == image.stat().st_size
    assert run_json(port, capsys, "slot-info", "2")[1]["info"] == {"keys": ["fov_deg"]}
    assert run_json(port, capsys, "diag")[1]["nacked"] == 1
    rc, out = run_json(port, capsys, "send", "0x1f")
    assert rc == 5 and out["reason"] == 1  # refused by the device: exit 5


def test_cli_log_file(port, capsys, tmp_path):
    log = tmp_path / "log.jsonl"
    assert main(["--port", port, "--log", str(log), "ping"]) == 0
    assert [json.loads(x)["dir"] for x in log.read_text().splitlines()] == ["tx", "rx"]


def test_console_session(port, capsys):
    script = io.StringIO("help\nhelp peek\nraw on\nping\npeek 0x20000000 2\npeek 1\nbogus\nwrite-edac 0 00\nquit\n")
    with Client(port) as client:
        console = Console(client, stdin=script, stdout=io.StringIO())
        console.use_rawinput = False
        console.cmdloop()
    out = capsys.readouterr()
    text = out.out + console.stdout.getvalue()
    assert "read-edac" in text and "PEEK ADDRESS COUNT" in text
    assert "ST16-EMU BOOTLOADER" in text and "tx: c0 0e 11" in text and "hex: 0000" in text
    assert "required: count" in text and "invalid choice: 'bogus'" in text
    assert "READ_ONLY" in out.err


@pytest.mark.parametrize("url", ["/dev/no-such-port", "socket://127.0.0.1:1"])
def test_a_port_that_cannot_be_opened_is_one_line_and_exit_4(url, capsys):
    for command in (["ping"], ["init"], ["read-edac", "0x4C", "4"]):
        assert main(["--port", url, *command]) == 4
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("st16-ground: ") and url.split("//")[-1] in err[0], err


def test_debug_shows_the_traceback():
    from serial import SerialException

    with pytest.raises(SerialException):
        main(["--debug", "--port", "/dev/no-such-port", "ping"])


@pytest.mark.parametrize(
    "argv",
    [
        ["read-edac", "-1", "4"],
        ["go", "999"],
        ["--baud", "-5", "ping"],
        ["--timeout", "-1", "ping"],
        ["--timeout", "nan", "ping"],
        ["frame", "render", "--random", "-5", "-o", "x.dng"],
        ["frame", "render", "--width", "100000", "-o", "x.dng"],
        ["frame", "render", "--exposure", "-1", "-o", "x.dng"],
        ["frame", "render", "--dec", "200", "-o", "x.dng"],
        ["send", "0x20"],
        ["combination", "11", "0x10000"],
    ],
)
def test_out_of_range_values_are_refused_before_any_work(argv, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(["--port", "/dev/no-such-port", *argv])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "error: argument" in err[-1] and "must be" in err[-1], err
    assert not list(tmp_path.iterdir())  # nothing rendered, no port opened


def test_global_options_are_accepted_after_the_command(port, capsys):
    assert main(["ping", "--port", port, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["banner"].startswith("ST16-EMU")
    assert main(["read-edac", "0x4C", "4", "--json", "--port", port]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["count"] == 4
    assert main(["--port", "/dev/no-such-port", "ping", "--port", port]) == 0  # the later one wins
    capsys.readouterr()


def test_result_and_combination_print_decoded_fields(port, capsys):
    from datetime import datetime

    assert main(["--port", port, "go", "--wait"]) == 3  # a result with no attitude exits 3, as solve
    for argv in (["result"], ["combination", "0x0B", "0x1017"]):
        assert main(["--port", port, *argv]) == 3
        text = capsys.readouterr().out
        assert "status NO_CATALOG (no catalog" in text and "no attitude" in text, text
        assert " UTC" in text and "e+09" not in text and "{" not in text, text  # no epoch as 1.79e+09, no JSON
        rc, out = run_json(port, capsys, *argv)
        assert out["status"] == "NO_CATALOG" and out["n_matched"] == 0 and out["q_icrs_to_sensor"] is None
        when = datetime.fromisoformat(out["epoch_utc"].replace("Z", "+00:00"))
        assert abs(when.timestamp() - out["utc_epoch"]) < 1e-3
        assert abs((datetime.now(UTC) - when).total_seconds()) < 120
        assert 0 <= out["epoch"] < 3600  # the device clock: seconds since its power-on (epoch 0)


def test_combination_sections_decode_to_attitude_and_time():
    import numpy as np

    from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat
    from ground.link.solve_report import combination_record, format_record
    from protocol import result

    q = matrix_to_quat(attitude_from_radec_roll(*np.radians([83.8, -5.4, 10.0])))
    data = result.build(
        {
            "return_code": result.make_return_code(result.Status.OK, result.ReturnBits.IMAGE1_SUCCESS),
            "quaternion": q,
            "epoch": 12.5,  # the device clock
            "ext.utc_epoch": 1795495102.25,
            "ext.n_matched": 7,
            "ext.n_detected": 9,
        },
        sequence=4,
    )
    parts = {
        addr: data[addr : addr + n] for mask, (addr, n) in result.SECTIONS.items() if mask in (2, 4, 0x10, 0x20, 0x1000)
    }
    out = combination_record(parts)
    assert out["status"] == "OK" and out["bits"] == ["IMAGE1_SUCCESS"] and "sequence" not in out
    assert out["ra_deg"] == pytest.approx(83.8) and out["dec_deg"] == pytest.approx(-5.4)
    assert out["roll_deg"] == pytest.approx(10.0) and out["n_matched"] == 7
    assert out["epoch_utc"] == "2026-11-24T04:38:22.250Z" and out["epoch"] == 12.5 and "raw" not in out
    assert out["hardware"]["quaternion_order"] == "scalar_first"  # the hardware section flags the order
    text = format_record(out)
    assert "RA 83.80000 deg, Dec -5.40000 deg, roll 10.0000 deg" in text and "detected 9, matched 7" in text
    assert "epoch 2026-11-24T04:38:22.250Z UTC" in text and "standard quaternions scalar_first" in text


def _console(port, script: str, **kw) -> Console:
    console = Console(Client(port), stdin=io.StringIO(script), stdout=io.StringIO(), **kw)
    console.use_rawinput = False
    return console


def test_console_reopens_the_link(port, capsys):
    opened = []

    def reopen():
        opened.append(Client(port))
        return opened[-1]

    first = Client(port, device_address=0x33, timeout=0.1)  # a link the device does not answer on
    console = Console(first, stdin=io.StringIO("ping\nreopen\nping\nquit\n"), stdout=io.StringIO(), reopen=reopen)
    console.use_rawinput = False
    console.cmdloop()
    out = capsys.readouterr()
    assert "ReplyTimeout" in out.err and f"reopened {port}" in out.out
    assert out.out.count("ST16-EMU BOOTLOADER") == 1  # the second ping, on the new link
    assert console.client is opened[0] and not first._ser.is_open

    def refuse():
        raise OSError(2, "No such file or directory", port)

    console.reopen = refuse
    console.cmdqueue = ["reopen", "ping", "quit"]
    console.cmdloop()
    out = capsys.readouterr().out
    assert "reopen failed: [Errno 2]" in out and "no link: 'reopen'" in out and not opened[0]._ser.is_open


def test_console_history_survives_sessions_and_bad_files(port, capsys, tmp_path, monkeypatch):
    import readline
    import sys

    from ground.link.console import history_path

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    history = history_path()
    assert history == tmp_path / "st16-ground" / "history"
    history.parent.mkdir()
    history.write_text("peek 0x20000000 2\n")
    readline.clear_history()
    console = _console(port, "quit\n")
    console.preloop = lambda: readline.add_history("diag --clear")  # what a typed command leaves
    console.run()
    assert history.read_text().split("\n")[:2] == ["peek 0x20000000 2", "diag --clear"]

    monkeypatch.setenv("XDG_STATE_HOME", str(history))  # a file where the directory should be
    _console(port, "quit\n").run()
    assert "history not saved" in capsys.readouterr().err

    monkeypatch.setitem(sys.modules, "readline", None)  # a Python without readline
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "none"))
    _console(port, "ping\nquit\n").run()
    assert not (tmp_path / "none").exists()
