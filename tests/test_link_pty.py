"""End to end over a real pty between two processes: ``st16-device --pty`` and the ground Client."""

import os
import signal
import struct
import subprocess
import sys

import guards
import pytest
from interrupt import default_sigint

from ground.link.client import Client, Nack, ReplyTimeout
from ground.testing.device_proc import device_command as _device_command
from protocol import nsp, result, slip
from protocol.commands import Code, NackReason, XferState
from protocol.crc import crc32


class DeviceProcess:
    """``st16-device ARGS`` in its own session with SIGINT at its default (a test stops it with
    SIGINT or SIGTERM; a runner started in the background would hand it SIGINT ignored)."""

    def __init__(self, *args: str):
        self.proc = subprocess.Popen(
            _device_command() + list(args),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            preexec_fn=default_sigint,
        )
        line = self.proc.stdout.readline().strip()
        assert line.startswith("listening on "), (line, self.proc.stderr.read() if self.proc.poll() else "")
        self.path = line[len("listening on ") :]

    def stop(self, sig=signal.SIGTERM) -> int:
        """Its exit code after ``sig``; killed if it has not ended within a minute (a hang guard)."""
        try:
            if self.proc.poll() is None:
                self.proc.send_signal(sig)
            return self.proc.wait(timeout=60)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
            self.proc.stdout.close()
            self.proc.stderr.close()


@pytest.fixture
def device(tmp_path):
    dev = DeviceProcess("--pty", "--state", str(tmp_path / "state"))
    yield dev
    assert dev.stop() == 0


def test_ping_modes_init_edac_and_files(device):
    with Client(device.path, timeout=guards.REPLY_S) as c:
        boot = c.ping()
        c.init(0x2000)
        app = c.ping()
        assert "BOOTLOADER" in boot and "APPLICATION" in app
        assert c.write_edac(0x120, b"round trip") == 10
        assert c.read_edac(0x120, 10) == b"round trip"
        c.write_file(0x140, b"\x01\x02\x03\x04")
        assert c.read_file(0x140) == c.read_file(0x140, long=True) == b"\x01\x02\x03\x04"
        assert c.read_edac(0x000, 512)[0x140:0x144] == b"\x01\x02\x03\x04"
        assert c.peek(0x20000000, 4) == bytes(4)
        c.poke(0x20000000, b"\xaa\xbb")
        assert c.peek(0x20000000, 2) == b"\xaa\xbb"


def test_fault_counters_poll0_silence_and_nacks(device):
    with Client(device.path, timeout=guards.REPLY_S) as c:
        ping = nsp.command(0x0E, 0x11, Code.PING).encode()
        c.write_raw(slip.encode(ping[:-1] + bytes([ping[-1] ^ 0xFF])))  # bad CRC
        c.write_raw(b"\xc0\x0e\x11\xc0")  # runt
        c.write_raw(b"\xc0\x0e\x11\x80\xdb\x01\xc0")  # bad escape
        c.write_raw(b"\xc0" + b"\x0e" * 5000 + b"\xc0")  # oversize
        c.write_raw(nsp.command(0x22, 0x11, Code.PING).frame())  # another address
        assert c.read_raw(0.2) == b""  # none of those is answered
        c.send_silent(Code.WRITE_EDAC, struct.pack("<H", 0x1F0) + b"silent")
        assert c.read_raw(0.2) == b""
        assert c.read_edac(0x1F0, 6) == b"silent"
        d = c.diagnostic()
        assert (d.bad_crc, d.runt, d.framing, d.oversize, d.other_address) == (1, 1, 1, 1, 1)
        assert d.silent == 1
        with pytest.raises(Nack) as exc:
            c.write_edac(0x0010, b"x")
        assert exc.value.reason == NackReason.READ_ONLY and exc.value.raw.startswith(b"\xc0\x11\x0e")
        with pytest.raises(Nack) as exc:
            c.transact(0x05)
        assert exc.value.reason == NackReason.UNKNOWN_COMMAND
        assert "BOOTLOADER" in c.ping()  # still serving


def test_combination_and_go_over_the_link(device):
    with Client(device.path, timeout=guards.REPLY_S) as c:
        c.init()
        parts = c.combination(0x0B, 0x0007)
        assert sorted(parts) == [0x000, 0x004, 0x008]
        rc = struct.unpack("<I", parts[0x004])[0]
        assert result.status_of(rc) == result.Status.NO_CATALOG and parts[0x008] == bytes(32)
        rec = c.go_and_wait()
        assert result.status_of(int(rec["return_code"])) == result.Status.NO_CATALOG
        assert int(rec["sequence"]) == 2


def _small_catalog_image(n: int = 300) -> bytes:
    """A valid catalog image of a random ``n``-star sky (the device validates slot 0)."""
    import numpy as np

    from firmware_model.catalog.image_io import catalog_to_image
    from firmware_model.catalog.onboard import OnboardCatalog

    rng = np.random.default_rng(7)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    cat = OnboardCatalog.build(
        np.arange(1, n + 1),
        v,
        rng.uniform(1, 5, n),
        rng.uniform(0.3, 1.5, n),
        rng.uniform(0.2, 1.4, n),
        phi_min=0.002,
        phi_max=np.radians(15.0),
        meta={"epoch": 2025.0},
    )
    return catalog_to_image(cat, created_unix=0)


def test_upload_interrupted_resumed_and_persisted(tmp_path):
    state = tmp_path / "state"
    image = _small_catalog_image()
    assert len(image) > 20_000
    dev = DeviceProcess("--pty", "--state", str(state))
    with Client(dev.path, timeout=guards.REPLY_S) as c:
        c.xfer_begin(0, len(image), crc32(image))
        for off in range(0, 12_288, 4096):
            c.xfer_data(0, off, image[off : off + 4096])
    assert dev.stop(signal.SIGINT) == 0  # interrupted mid-transfer
    dev = DeviceProcess("--pty", "--state", str(state))
    with Client(dev.path, timeout=guards.REPLY_S) as c:
        st = c.xfer_status(0)
        assert (st.state, st.contiguous, st.length) == (XferState.RECEIVING, 12_288, len(image))
        report = c.upload(0, image, progress=False)
        assert report.resumed_from == 12_288 and report.sent == len(image) - 12_288
        info = c.slot_info(0)
        assert info.active and info.crc32 == crc32(image)
    assert dev.stop() == 0
    dev = DeviceProcess("--pty", "--state", str(state))  # restart keeps the committed image
    with Client(dev.path, timeout=guards.REPLY_S) as c:
        info = c.slot_info(0)
        assert info.active and (info.length, info.crc32) == (len(image), crc32(image))
        c.init()
        rec = c.go_and_wait()
        assert result.status_of(int(rec["return_code"])) == result.Status.NO_FRAME
    assert dev.stop() == 0


def test_late_reply_is_never_taken_for_the_current_one():
    dev = DeviceProcess("--pty", "--pace", "--baud", "115200", "--turnaround-ms", "1000")  # 20 x the first timeout
    try:
        with Client(dev.path, timeout=0.05, retries=0) as c:
            with pytest.raises(ReplyTimeout):
                c.ping()  # its reply arrives late, during the next transaction
            c.timeout = guards.REPLY_S
            assert c.read_edac(0x0100, 4) == bytes(4)
            assert c.stale_replies == 1
    finally:
        assert dev.stop() == 0


def test_tcp_transport():
    dev = DeviceProcess("--tcp", "127.0.0.1:0")
    try:
        assert dev.path.startswith("socket://127.0.0.1:")
        with Client(dev.path, timeout=guards.REPLY_S) as c:
            assert "BOOTLOADER" in c.ping()
    finally:
        assert dev.stop() == 0


def test_short_soak_no_lost_or_misattributed_reply(device):
    """A short version of the benchmark soak: every reply checked against a model of the device."""
    import random

    rng = random.Random(7)
    scratch = bytearray(256)
    with Client(device.path, timeout=guards.REPLY_S, retries=0) as c:
        c.init()
        for _ in range(1500):
            a = rng.randrange(0x100, 0x1F0)
            kind = rng.randrange(4)
            if kind == 0:
                v = rng.randbytes(rng.randrange(1, 0x200 - a))
                assert c.write_edac(a, v) == len(v)
                scratch[a - 0x100 : a - 0x100 + len(v)] = v
            elif kind == 1:
                k = rng.randrange(1, 0x200 - a)
                assert c.read_edac(a, k) == scratch[a - 0x100 : a - 0x100 + k]
            elif kind == 2:
                v = rng.randbytes(4)
                c.send_silent(Code.WRITE_EDAC, struct.pack("<H", a) + v)
                scratch[a - 0x100 : a - 0x100 + 4] = v
            else:
                with pytest.raises(Nack):
                    c.transact(0x0E)
        d = c.diagnostic()
        assert c.stale_replies == 0
    assert d.accepted == 1502 and d.framing == d.runt == d.bad_crc == d.oversize == 0


def test_serial_port_transport():
    """``--port``: the device opens a serial device (here the slave side of a pty we own)."""
    import select
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    dev = DeviceProcess("--port", os.ttyname(slave), "--baud", "57600")
    try:
        os.write(master, bytes.fromhex("C00E11806921C0"))
        reply = b""
        while not reply.endswith(b"\xc0") or len(reply) < 8:
            assert select.select([master], [], [], 2.0)[0], reply
            reply += os.read(master, 4096)
        (frame,) = slip.Decoder().feed(reply)
        msg = nsp.decode(frame.data)
        assert (msg.dst, msg.src, msg.mcf) == (0x11, 0x0E, 0xA0) and b"BOOTLOADER" in msg.data
    finally:
        assert dev.stop() == 0
        os.close(master)
        os.close(slave)


def test_link_is_served_while_a_combination_waits_for_its_sequence():
    """COMBINATION with GO waits for its sequence (here a capture that blocks): meanwhile the
    link answers other commands, and the COMBINATION reply follows when the sequence ends.
    In-process device on a real pty (the capture is held by the test)."""
    import threading

    from firmware_model.device.device import Device
    from firmware_model.device.link import PtyLink, serve
    from protocol.commands import Combination

    release = threading.Event()

    def capture(ctx):
        release.wait(10.0)
        return None  # "no more frames": the sequence ends with NO_FRAME

    dev = Device(frame_source=capture)
    link, stop = PtyLink(), threading.Event()
    server = threading.Thread(target=serve, args=(dev, link, stop), daemon=True)
    server.start()
    try:
        with Client(link.path, timeout=guards.REPLY_S, retries=0) as c:
            c.upload(0, _small_catalog_image(), progress=False)
            c.init()
            c.write_raw(
                nsp.command(
                    c.device_address, c.host_address, Code.COMBINATION, Combination(0x0B, 0x0007).pack()
                ).frame()
            )
            assert "APPLICATION" in c.ping() and dev.busy  # answered while the sequence runs
            assert c.read_edac(0x0100, 4) == bytes(4)
            release.set()
            raw = c.read_raw(2.0)
            replies = [nsp.decode(f.data) for f in slip.Decoder(nsp.MAX_MESSAGE).feed(raw)]
            # one message (ICD page 1-35918): u16 0 bytes already transmitted, then the 40 bytes
            (reply,) = replies
            assert reply.code == Code.COMBINATION and reply.ack and reply.final and len(reply.data) == 2 + 40
            assert struct.unpack_from("<H", reply.data)[0] == 0
            assert result.status_of(struct.unpack_from("<I", reply.data, 2 + 4)[0]) == result.Status.NO_FRAME
    finally:
        release.set()
        stop.set()
        server.join(5.0)
        link.close()


def test_ctrl_c_during_an_upload_keeps_what_was_sent_and_the_next_upload_resumes(tmp_path):
    """``st16-ground upload`` interrupted half-way over a paced line: exit 130 with one line, the
    device keeps the bytes received, and the next upload sends only the rest."""
    import json
    import time

    image = _small_catalog_image(600)
    (tmp_path / "cat.img").write_bytes(image)
    partial = tmp_path / "state" / "slot0" / "partial.json"
    dev = DeviceProcess("--pty", "--pace", "--baud", "115200", "--state", str(tmp_path / "state"))
    try:
        cmd = [
            sys.executable,
            "-m",
            "ground.cli",
            "--port",
            dev.path,
            "--timeout",
            "30",  # a hang guard: the paced device answers each chunk however loaded the machine
            "upload",
            "0",
            str(tmp_path / "cat.img"),
        ]
        proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            preexec_fn=default_sigint,
        )
        try:
            deadline = time.monotonic() + 120  # a hang guard
            while not (partial.exists() and json.loads(partial.read_text() or "{}").get("ranges")):
                assert time.monotonic() < deadline and proc.poll() is None
                time.sleep(0.05)
            proc.send_signal(signal.SIGINT)  # the first chunk is in, most of the image is not
            _, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        assert proc.returncode == 130 and err.strip().splitlines()[-1] == "st16-ground: interrupted", err
        with Client(dev.path, timeout=guards.REPLY_S) as c:
            st = c.xfer_status(0)
            assert st.state == XferState.RECEIVING and 0 < st.contiguous < len(image)
            report = c.upload(0, image, progress=False)
            assert report.resumed_from == st.contiguous and c.slot_info(0).crc32 == crc32(image)
    finally:
        assert dev.stop() == 0


def test_open_link_makes_each_transport_from_a_url():
    from firmware_model.device.link import PtyLink, SerialLink, TcpLink, open_link

    links = [open_link("pty://"), open_link("tcp://127.0.0.1:0", tcp_idle=5.0), open_link("loop://")]
    try:
        assert [type(link) for link in links] == [PtyLink, TcpLink, SerialLink]
        assert links[0].describe().startswith("/dev/") and links[1].describe().startswith("socket://127.0.0.1:")
        assert links[2].write(b"\xc0") and links[2].read(0.5) == b"\xc0"  # loop:// echoes
    finally:
        for link in links:
            link.close()
    with pytest.raises(ValueError, match="bad TCP address"):
        open_link("tcp://nowhere")
