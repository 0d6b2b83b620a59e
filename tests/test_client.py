"""Ground client error handling (NACK, timeout, malformed replies, retries) and the exchange log."""

import json
import threading

import pytest

from firmware_model.device.link import PtyLink
from ground.link.client import Client, MalformedReply, Nack, ReplyTimeout
from protocol import nsp, slip
from protocol.commands import Code, NackReason


class Responder:
    """A fake device on a real pty: ``script(message) -> bytes to send back`` per command."""

    def __init__(self, script):
        self.link = PtyLink()
        self.script = script
        self.stop = threading.Event()
        self.seen: list[nsp.Message] = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        dec = slip.Decoder()
        while not self.stop.is_set():
            for event in dec.feed(self.link.read(0.05)):
                msg = nsp.decode(event.data)
                self.seen.append(msg)
                out = self.script(msg)
                if out:
                    self.link.write(out)

    def close(self):
        self.stop.set()
        self.thread.join(2)
        self.link.close()


@pytest.fixture
def responder():
    made = []

    def make(script):
        made.append(Responder(script))
        return made[-1]

    yield make
    for r in made:
        r.close()


def test_timeout_carries_raw_bytes_and_ignores_own_echo():
    with Client("loop://", timeout=0.1, retries=0) as c:  # loop:// echoes our command back
        with pytest.raises(ReplyTimeout) as exc:
            c.ping()
    assert exc.value.raw == nsp.command(0x0E, 0x11, Code.PING, b=True).frame()


def test_bad_crc_reply_is_malformed_with_raw(responder):
    def script(msg):
        raw = bytearray(nsp.reply_to(msg, b"pong").encode())
        raw[-1] ^= 0x55
        return slip.encode(bytes(raw))

    r = responder(script)
    with Client(r.link.path, timeout=0.3, retries=0) as c:
        with pytest.raises(MalformedReply) as exc:
            c.ping()
    assert "bad CRC" in str(exc.value) and exc.value.raw.startswith(b"\xc0\x11\x0e")


def test_wrong_code_and_bad_echo_are_malformed(responder):
    r = responder(lambda msg: nsp.Message(msg.src, msg.dst, 0xA0 | 0x07 | (msg.mcf & 0x40)).frame())
    with Client(r.link.path, timeout=0.3, retries=0) as c:
        with pytest.raises(MalformedReply, match="code 0x07"):
            c.ping()
    r2 = responder(lambda msg: nsp.reply_to(msg, b"\x01\x00abcd").frame())  # echoes EDAC 0x0001, not 0x0100
    with Client(r2.link.path, timeout=0.3, retries=0) as c:
        with pytest.raises(MalformedReply) as exc:
            c.read_edac(0x100, 4)
    assert b"abcd" in exc.value.raw


def test_idempotent_reads_are_retried_with_a_new_b_bit(responder):
    calls = []

    def script(msg):
        calls.append(msg.b)
        return b"" if len(calls) == 1 else nsp.reply_to(msg, b"pong").frame()

    r = responder(script)
    with Client(r.link.path, timeout=0.2, retries=2) as c:
        assert c.ping() == "pong"
        assert calls[:2] in ([True, False], [False, True])
        calls.clear()
        with pytest.raises(ReplyTimeout):
            c.go(0x0B)  # GO is not idempotent: no retry
        assert len(calls) == 1


def test_stale_b_bit_reply_is_discarded(responder):
    def script(msg):
        stale = nsp.Message(msg.src, msg.dst, msg.mcf ^ 0x40 | 0xA0, b"old").frame()
        return stale + nsp.reply_to(msg, b"new").frame()

    r = responder(script)
    with Client(r.link.path, timeout=0.5) as c:
        assert c.ping() == "new"
        assert c.stale_replies == 1


def test_multipart_reply_and_nack(responder):
    def script(msg):
        if msg.code == Code.READ_RESULT:
            return nsp.reply_to(msg, b"\x00\x00ab", final=False).frame() + nsp.reply_to(msg, b"\x02\x00cd").frame()
        return nsp.reply_to(msg, b"\x07\x00nope", ack=False).frame()

    r = responder(script)
    with Client(r.link.path, timeout=0.5) as c:
        assert c.read_result(0, 4) == b"abcd"
        with pytest.raises(Nack) as exc:
            c.go()
    assert (exc.value.reason, exc.value.text) == (NackReason.BAD_PARAMETER, "nope")
    assert exc.value.raw.endswith(nsp.reply_to(r.seen[-1], b"\x07\x00nope", ack=False).frame())


def test_exchange_log_records_both_directions(served_device, tmp_path):
    log = tmp_path / "x.jsonl"
    with Client(served_device, log=log) as c:
        c.ping()
        with pytest.raises(Nack):
            c.write_edac(0, b"x")
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert [e["dir"] for e in lines] == ["tx", "rx", "tx", "rx"]
    assert (
        lines[0]["name"] == "PING" and lines[0]["poll_final"] and lines[0]["hex"].startswith("0e11c0")
    )  # first command has B set
    assert lines[3]["ack"] is False and lines[3]["name"] == "WRITE_EDAC"
    assert all(e["t"].endswith("+00:00") for e in lines)


def test_upload_progress_resumes_from_device_status(served_device):
    data = bytes(range(256)) * 50
    with Client(served_device) as c:
        c.xfer_begin(2, len(data), 0)  # a different pending transfer is replaced by upload()
        c.xfer_data(2, 0, b"x" * 100)
        with pytest.raises(Nack) as exc:
            c.upload(2, data, progress=False)
        assert exc.value.reason == 0x0101  # default params validator: not JSON; nothing committed
        assert not c.slot_info(2).active
        report = c.upload(1, data, progress=False)
        assert (report.resumed_from, report.sent) == (0, len(data))
        assert c.slot_info(1).active


def test_dead_port_raises_link_down():
    from ground.link.client import LinkDown

    link = PtyLink()
    c = Client(link.path, timeout=0.3, retries=0)
    link.close()  # the device side disappears
    with pytest.raises(LinkDown):
        for _ in range(3):
            c.ping()
    c.close()


def test_noise_before_a_multipart_reply_is_harmless_but_a_damaged_part_is_not(responder):
    def script(msg):
        first, last = nsp.reply_to(msg, b"\x00\x00ab", final=False), nsp.reply_to(msg, b"\x02\x00cd")
        if msg.b:
            return b"\xc0\xdb\x01\xc0" + first.frame() + last.frame()  # a bad escape, then both parts
        damaged = bytearray(first.encode())
        damaged[-1] ^= 1
        return slip.encode(bytes(damaged)) + last.frame()

    r = responder(script)
    with Client(r.link.path, timeout=0.3, retries=0) as c:
        assert c.read_result(0, 4) == b"abcd"  # first command: B set
        with pytest.raises(MalformedReply):
            c.read_result(0, 4)


def test_a_closed_client_and_a_failing_log_are_named_for_what_they_are(tmp_path, monkeypatch):
    """Using a closed client is LinkDown (pyserial raised TypeError); an exchange log that cannot
    be written is LogWriteError, not a link failure, and a log that cannot be opened leaves no
    port open."""
    import serial

    from ground.link.client import Client, LinkDown
    from ground.link.exchange_log import LogWriteError

    c = Client("loop://", timeout=0.05, retries=0)
    c.close()
    with pytest.raises(LinkDown, match="is closed"):
        c.ping()
    opened = []
    real = serial.serial_for_url
    monkeypatch.setattr(serial, "serial_for_url", lambda *a, **k: opened.append(real(*a, **k)) or opened[-1])
    (tmp_path / "log_dir").mkdir()
    with pytest.raises(LogWriteError):
        Client("loop://", log=tmp_path / "log_dir")  # a directory: cannot be opened for appending
    assert not opened
    with Client("loop://", timeout=0.05, retries=0, log=tmp_path / "x.jsonl") as c:

        class FullDisk:
            def write(self, text):
                raise OSError(28, "No space left on device")

            def close(self):
                pass

        c.log._fh = FullDisk()
        with pytest.raises(LogWriteError):
            c.ping()
