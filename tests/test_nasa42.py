"""NASA 42 as the attitude feed's dynamics simulator (ground.sim.nasa42; docs/hil.md "NASA 42").

The parser and the quaternion convention against 42's own ``Q2C`` (``Kit/Source/dcmkit.c``,
transcribed), bad messages, and (marked ``hil``) the device fed by a real 42 built from
``../shared/tools/nasa42``: every OK answer against the body attitude 42 itself wrote to
``qbn.42`` at the exposure's mid-time, which fails on a transposed (conjugate) or reordered
quaternion. The built 42 is ``$ST16_NASA42_DIR`` (CI builds it, .ci/run) or built here.
"""

from __future__ import annotations

import math
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from firmware_model.reference_frames import quat_to_matrix, rotation_angle
from ground.sim import nasa42
from tests.conftest import require_shared

ROOT = Path(__file__).resolve().parents[1]
BUILD_SH = ROOT.parent / "shared" / "tools" / "nasa42" / "build.sh"
START_UTC = datetime(2024, 4, 8, tzinfo=UTC).timestamp()  #: the default scenario's start (Inp_Sim.txt)


def q2c_42(q) -> np.ndarray:
    """42's ``Q2C`` (dcmkit.c), transcribed: the matrix of its scalar-last ``qn``."""
    q0, q1, q2, q3 = q
    return np.array(
        [
            [1 - 2 * (q1 * q1 + q2 * q2), 2 * (q0 * q1 + q2 * q3), 2 * (q0 * q2 - q1 * q3)],
            [2 * (q0 * q1 - q2 * q3), 1 - 2 * (q2 * q2 + q0 * q0), 2 * (q1 * q2 + q0 * q3)],
            [2 * (q0 * q2 + q1 * q3), 2 * (q1 * q2 - q0 * q3), 1 - 2 * (q0 * q0 + q1 * q1)],
        ]
    )


def _message(q=(2.97e-01, 7.07e-02, 2.836e-01, 9.0903e-01), w=(4.87e-03, 6.72e-03, 8.26e-03), extra=()):
    qn = np.asarray(q) / np.linalg.norm(q)
    return [
        "TIME 2024-099-00:00:00.100000000",
        "SC[0].qn = [" + " ".join(f"{v:.12e}" for v in qn) + "]",
        "SC[0].B[0].wn = [" + " ".join(f"{v:.12e}" for v in w) + "]",
        "SC[0].B[0].qn = [" + " ".join(f"{v:.12e}" for v in qn) + "]",
        "Orb[0].PosN = [6.369110518417e+06 1.427708321263e+06 1.827383319013e+06]",
        *extra,
    ]


def test_time_and_the_quaternion_are_42s():
    assert nasa42.parse_time("TIME 2024-099-00:00:00.100000000") == pytest.approx(START_UTC + 0.1)
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        ours = quat_to_matrix(nasa42.body_quaternion(q))
        assert np.allclose(ours, q2c_42(q), atol=1e-12)  # v_body = C v_N: the same matrix
        assert not np.allclose(quat_to_matrix(q), q2c_42(q), atol=1e-3)  # read scalar first: wrong
        assert not np.allclose(quat_to_matrix([q[3], q[0], q[1], q[2]]), q2c_42(q), atol=1e-3)  # not conjugated


def test_a_message_becomes_one_sensor_sample_through_the_mounting():
    mount = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])  # 90 deg about body x
    opts = nasa42.Nasa42Options(f"42://127.0.0.1:1?mount={mount[0]:.17g},{mount[1]:.17g},0,0")
    reader = nasa42.Reader.__new__(nasa42.Reader)
    reader.opts, reader._m = opts, quat_to_matrix(opts.mount)
    msg = nasa42.parse_message(_message())
    s = reader.sample(msg)
    a_body = q2c_42(np.asarray(msg["SC[0].B[0].qn"]))
    assert s.t == pytest.approx(START_UTC + 0.1)
    assert np.allclose(quat_to_matrix(s.q), quat_to_matrix(mount) @ a_body, atol=1e-9)
    assert np.allclose(s.w, quat_to_matrix(mount) @ np.asarray(msg["SC[0].B[0].wn"]))
    assert s.r is not None and np.allclose(s.r, [6369.110518417, 1427.708321263, 1827.383319013])


@pytest.mark.parametrize(
    "spec, why",
    [
        ("42://127.0.0.1:1?mount=1,0,0,0.1", "not a unit quaternion"),
        ("42://127.0.0.1:1?mount=1,0,0", "four"),
        ("42://127.0.0.1:1?speed=-1", "speed"),
        ("42://127.0.0.1?speed=1", "HOST:PORT"),
    ],
)
def test_bad_42_urls_are_one_line(spec, why):
    with pytest.raises(ValueError, match=why):
        nasa42.Nasa42Options(spec)


def test_bad_mounting_is_one_line_exit_2(tmp_path):
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "firmware_model.device.cli",
            "--pty",
            "--attitude-feed",
            "42://127.0.0.1:9?mount=2,0,0,0",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1 and "unit quaternion" in run.stderr


class _Fake42:
    """A server speaking 42's protocol from a script: each item bytes to send, then (if wanted) an
    Ack awaited; ``None`` closes the connection (the reader reconnects)."""

    def __init__(self, script):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.port = self.sock.getsockname()[1]
        self.acks = 0
        self.script = script
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self):
        conn, _ = self.sock.accept()
        for data, ack in self.script:
            if data is None:
                conn.close()
                conn, _ = self.sock.accept()
                continue
            conn.sendall(data)
            if ack:
                got = b""
                while len(got) < 4:
                    got += conn.recv(4 - len(got))
                assert got == nasa42.ACK
                self.acks += 1


def _msg_bytes(t: float, broken: str | None = None) -> bytes:
    lines = _message()
    lines[0] = f"TIME 2024-099-00:00:{t:012.9f}"
    if broken:
        lines.insert(2, broken)
    return ("\n".join(lines) + "\n[ENDMSG]\n").encode()


def test_bad_messages_are_counted_and_never_half_used():
    whole = [(_msg_bytes(1.0), True)]
    script = (
        whole
        + [
            (_msg_bytes(1.1, broken="SC[0].B[0].qn = [1 2"), True),  # a malformed line: dropped, acknowledged
            (_msg_bytes(1.2)[:120], False),  # stops mid-message, then closes
            (None, False),
            (_msg_bytes(1.3), True),  # served on after reconnecting
        ]
    )
    fake = _Fake42(script)
    samples, faults = [], []
    opts = nasa42.Nasa42Options(f"42://127.0.0.1:{fake.port}?speed=0")
    reader = nasa42.Reader(opts, samples.append, faults.append)
    try:
        end = time.monotonic() + 10
        while len(samples) < 2 and time.monotonic() < end:
            time.sleep(0.02)
    finally:
        reader.close()
    assert [round(s.t - START_UTC, 3) for s in samples] == [1.0, 1.3]
    assert "dropped" in faults[0] and "inside a message" in faults[1]  # (then the fake closes: a third)
    assert fake.acks == 3


# ---------------------------------------------------------------------------- with a real 42


def _built_42(tmp_path_factory) -> Path:
    given = os.environ.get("ST16_NASA42_DIR")
    if given:
        return Path(given)
    require_shared(BUILD_SH)
    if shutil.which("gcc") is None or shutil.which("make") is None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail("42 needs gcc and make, and CI=true (.ci/run installs them)", pytrace=False)
        pytest.skip("gcc or make absent: 42 cannot be built")
    dest = tmp_path_factory.mktemp("nasa42")
    subprocess.run(["sh", str(BUILD_SH), str(dest), "10001", "FAST"], check=True, capture_output=True, timeout=600)
    return dest


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_folder(dest: Path, port: int, seconds: float) -> str:
    from ground.sim.nasa42 import run_folder

    return run_folder(dest, f"run-{os.getpid()}-{port}", port, seconds).name


def _truth(run: Path):
    """42's own record: (POSIX s, scalar-last qn) per output step (time.42, qbn.42)."""
    t = np.loadtxt(run / "time.42", ndmin=1) + START_UTC
    q = np.loadtxt(run / "qbn.42", ndmin=2)
    n = min(len(t), len(q))
    return t[:n], q[:n]


def _at(t_rec, q_rec, t) -> np.ndarray:
    """42's matrix at ``t``: the nearer steps' quaternions interpolated (0.1 s apart)."""
    k = int(np.clip(np.searchsorted(t_rec, t), 1, len(t_rec) - 1))
    f = (t - t_rec[k - 1]) / (t_rec[k] - t_rec[k - 1])
    qa, qb = q_rec[k - 1], q_rec[k]
    qb = qb if np.dot(qa, qb) >= 0 else -qb
    q = (1 - f) * qa + f * qb
    return q / np.linalg.norm(q)


def angle_arcsec(a, b) -> float:
    return math.degrees(rotation_angle(a, b)) * 3600


@pytest.mark.hil
@pytest.mark.parametrize("mount", [(1.0, 0.0, 0.0, 0.0), (math.cos(math.pi / 8), 0.0, math.sin(math.pi / 8), 0.0)])
def test_the_tracker_answers_42s_body_attitude(tmp_path, tmp_path_factory, mount):
    from firmware_model.catalog.image_io import catalog_to_image
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.link.client import Client
    from ground.sim.device_process import start_device, stop_device
    from protocol import result

    dest = _built_42(tmp_path_factory)
    port, seconds = _free_port(), 16.0
    name = _run_folder(dest, port, seconds)
    state = tmp_path / "state"
    state.mkdir()
    proc, pty = start_device(state)
    try:
        with Client(pty, timeout=10.0) as c:
            c.init()
            c.upload(0, catalog_to_image(build_catalog(CatalogDesign())), progress=False)
    finally:
        stop_device(proc)
    log = open(tmp_path / "42.log", "w")
    sim = subprocess.Popen([str(dest / "42"), name], cwd=dest, stdout=log, stderr=subprocess.STDOUT)
    url = f"42://127.0.0.1:{port}?speed=1&position=off&mount={','.join(f'{v:.17g}' for v in mount)}"
    answers = []
    try:
        proc, pty = start_device(state, "--attitude-feed", url)
        try:
            with Client(pty, timeout=30.0) as c:
                c.init()
                end = time.monotonic() + seconds - 3.0  # GOs while 42 runs (real time: speed=1)
                while time.monotonic() < end and len(answers) < 16:
                    r = c.go_and_wait(0x0B, timeout=60.0)
                    status = result.status_of(int(r["return_code"]))
                    answers.append((status, np.array(r["quaternion"], float), float(r["ext"]["utc_epoch"])))
                # 42 runs its 16 s to the end and exits, its files flushed (the device still reading)
                assert sim.wait(timeout=120) == 0
        finally:
            stop_device(proc)
    finally:
        if sim.poll() is None:
            sim.kill()
        log.close()
    t_rec, q_rec = _truth(dest / name)
    m = quat_to_matrix(np.asarray(mount))
    ok = [(q, t) for s, q, t in answers if s == result.Status.OK and t_rec[0] <= t <= t_rec[-1]]
    assert len(ok) >= 5, f"{len(ok)} OK answers of {len(answers)}: {[str(s) for s, _, _ in answers]}"
    errors, conj, swapped = [], [], []
    for q, t in ok:
        qn = _at(t_rec, q_rec, t)
        errors.append(angle_arcsec(quat_to_matrix(q), m @ q2c_42(qn)))
        conj.append(angle_arcsec(quat_to_matrix(q), m @ q2c_42(qn).T))  # a transposed reading
        swapped.append(angle_arcsec(quat_to_matrix(q), m @ quat_to_matrix(qn)))  # scalar taken first
        swapped.append(angle_arcsec(quat_to_matrix(q), m @ quat_to_matrix([qn[3], *qn[:3]])))  # not conjugated
    assert float(np.median(errors)) < 30.0 and max(errors) < 300.0, errors
    assert min(conj) > 3600.0 and min(swapped) > 3600.0  # either mistake fails by more than a degree
