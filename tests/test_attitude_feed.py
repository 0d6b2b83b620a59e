"""The attitude feed (docs/hil.md): wire formats, transports on loopback, the checks that flag a
frame instead of rendering it, smear at a known rate, and the device serving a feed end to end.

The feed and the device run on a manual clock: when a feed is stale or a fault has aged is
decided by the test, not by how fast the machine is. Waits for bytes to arrive are hang guards."""

import math
import socket
import struct
import threading
import time

import guards
import numpy as np
import pytest
from manual_clock import ManualClock
from scipy.spatial.transform import Rotation

from firmware_model.camera import CameraModel
from firmware_model.device.device import Device, FrameUnavailable
from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat, quat_to_matrix, rotation_angle
from ground.sim.attitude_feed import AttitudeFeed, AttitudeFeedSource, slerp
from ground.sim.exposure import ExposureRenderer
from ground.sim.feed_wire import (
    RECORD,
    FeedUrl,
    Listener,
    MalformedSample,
    Sample,
    Sender,
    decode_binary,
    decode_json,
    encode_binary,
    encode_json,
)
from ground.sim.sensor_sim import DetectorModel, Stars, render_frame
from ground.sim.smear import SmearPSF
from protocol import nsp, result, slip
from protocol.commands import Code, NackInfo, NackReason

Q0 = matrix_to_quat(attitude_from_radec_roll(1.0, 0.3, 0.2))
W0 = np.radians([0.0, 0.5, 0.0])
SMALL_CAM = CameraModel.from_fov(320, 240, 2.0)
HANG_GUARD_S = 60.0  #: real seconds after which a wait for bytes or a thread is a failure


def _sample(t, q=Q0, w=W0):
    return Sample(float(t), np.asarray(q, dtype=float), np.asarray(w, dtype=float))


def _path(feed, t0, t1, step=0.02, q=Q0):
    for t in np.arange(t0, t1, step):
        feed.offer(_sample(t, q, np.zeros(3)))


def _free_port(kind) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ---------------------------------------------------------------- wire formats


def test_json_and_binary_round_trip():
    s = _sample(1790000000.125, Q0, W0)
    for enc, dec in ((encode_json, decode_json), (encode_binary, decode_binary)):
        back = dec(enc(s).rstrip(b"\n") if enc is encode_json else enc(s))
        assert back.t == s.t and np.array_equal(back.q, s.q) and np.array_equal(back.w, s.w)
    assert len(encode_binary(s)) == RECORD.size == 64
    assert encode_binary(s) == struct.pack("<8d", s.t, *s.q, *s.w)  # t, qw, qx, qy, qz, wx, wy, wz
    assert encode_json(s).endswith(b"\n") and b'"q": [' in encode_json(s)


@pytest.mark.parametrize(
    "line",
    [
        b"not json",
        b'{"t": 1, "q": [1, 0, 0], "w": [0, 0, 0]}',
        b'{"t": 1, "q": [1, 0, 0, 0]}',
        b"[1, 2]",
        b"[" * 3000,  # RecursionError inside json (issue 29)
        b'{"t": 1' + b"0" * 400 + b', "q": [1, 0, 0, 0], "w": [0, 0, 0]}',  # OverflowError in float()
    ],
)
def test_malformed_json_is_refused(line):
    with pytest.raises(MalformedSample):
        decode_json(line)


def test_one_bad_sample_never_ends_the_listener():
    """Issue 29: a line of 3000 brackets or a 400-digit time used to kill the listener thread."""
    url = f"tcp://127.0.0.1:{_free_port(socket.SOCK_STREAM)}?format=json"
    got, errors = [], []

    def offer(sample):
        if sample.t == 13.0:
            raise ArithmeticError("a checker that fails")
        got.append(sample)

    listener = Listener(FeedUrl.parse(url), offer, errors.append)
    try:
        with Sender(url) as snd:
            snd.send_raw(b"[" * 3000 + b"\n" + b'{"t": 1' + b"0" * 400 + b', "q": [1, 0, 0, 0], "w": [0, 0, 0]}\n')
            snd.send(_sample(13.0), *[_sample(20.0 + k) for k in range(5)])
        deadline = time.monotonic() + HANG_GUARD_S
        while len(got) < 5 and time.monotonic() < deadline:
            time.sleep(0.01)
        with Sender(url) as snd:  # the next connection is served too
            snd.send(_sample(30.0))
        while len(got) < 6 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        listener.close()
    assert [s.t for s in got] == [20.0, 21.0, 22.0, 23.0, 24.0, 30.0]
    assert len(errors) == 3 and "ArithmeticError" in errors[2]


def test_feed_url_parse_and_errors():
    u = FeedUrl.parse("udp://127.0.0.1:5600?format=binary&timeout=0.1")
    assert (u.transport, u.host, u.port, u.format, u.options) == (
        "udp",
        "127.0.0.1",
        5600,
        "binary",
        {"timeout": "0.1"},
    )
    for bad, msg in (
        ("http://127.0.0.1:1", "scheme"),
        ("tcp://127.0.0.1", "HOST:PORT"),
        ("tcp://127.0.0.1:x", "HOST:PORT"),
        ("udp://127.0.0.1:5600?format=xml", "format"),
    ):
        with pytest.raises(ValueError, match=msg):
            FeedUrl.parse(bad)


@pytest.mark.parametrize(
    "query, msg",
    [
        ("foo=1", "unknown option"),
        ("exposure=abc", "exposure=.abc. is not a number of seconds"),
        ("timeout=-1", r"timeout=-1 s is outside \[0, 60\]"),
        ("pattern=XY", "attitude feed"),
    ],
)
def test_bad_source_options_are_one_line_errors(query, msg):
    with pytest.raises(ValueError, match=msg):
        AttitudeFeedSource(f"udp://127.0.0.1:1?{query}", SMALL_CAM)


@pytest.mark.parametrize("transport", ["tcp", "udp"])
@pytest.mark.parametrize("fmt", ["json", "binary"])
def test_listener_receives_over_loopback(transport, fmt):
    kind = socket.SOCK_STREAM if transport == "tcp" else socket.SOCK_DGRAM
    url = f"{transport}://127.0.0.1:{_free_port(kind)}?format={fmt}"
    got, errors = [], []
    listener = Listener(FeedUrl.parse(url), got.append, errors.append)
    try:
        sent = [_sample(1000.0 + 0.02 * k) for k in range(50)]
        with Sender(url) as snd:
            snd.send(*sent[:20])
            if transport == "tcp":  # a stream may cut a record anywhere
                raw = b"".join((encode_binary if fmt == "binary" else encode_json)(s) for s in sent[20:])
                snd.send_raw(raw[:37])
                time.sleep(0.05)
                snd.send_raw(raw[37:])
            else:
                snd.send(*sent[20:])
            snd.send_raw(b"\x01\x02\x03" if fmt == "binary" else b"garbage\n")  # TCP: a cut record at close
        deadline = time.monotonic() + HANG_GUARD_S
        while (len(got) < 50 or not errors) and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        listener.close()
    assert [s.t for s in got] == [s.t for s in sent] and len(errors) == 1


def test_a_silent_feed_peer_holds_nobody_out():
    """Issue 29: the feed served one connection with no idle timeout, so a peer that sent nothing
    kept the simulator out. Now, as on the NSP TCP link, the newest connection takes over and a
    silent one is closed after ``idle_s``."""
    url = f"tcp://127.0.0.1:{_free_port(socket.SOCK_STREAM)}?format=json"
    got, errors, connects = [], [], []
    listener = Listener(FeedUrl.parse(url), got.append, errors.append, lambda: connects.append(1), idle_s=1.5)
    deadline = time.monotonic() + HANG_GUARD_S
    try:
        silent = socket.create_connection(listener.address)
        while not connects and time.monotonic() < deadline:
            time.sleep(0.01)
        with Sender(url) as snd:  # the simulator: served at once, the silent peer closed
            snd.send(*[_sample(50.0 + k) for k in range(3)])
            while len(got) < 3 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert silent.recv(1) == b""  # the silent peer was closed (EOF)
        silent.close()
        quiet = socket.create_connection(listener.address)  # a peer that never speaks: closed after 1.5 s
        while not any("silent" in e for e in errors) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert quiet.recv(1) == b""
        quiet.close()
    finally:
        listener.close()
    assert [s.t for s in got] == [50.0, 51.0, 52.0] and len(connects) == 3
    assert any("took over" in e for e in errors) and any("silent for 1.5 s" in e for e in errors)


# ---------------------------------------------------------------- checks that flag a frame


def test_slerp_interpolates_the_short_way():
    a = Rotation.from_rotvec([0.0, 0.0, 0.2]).as_quat(scalar_first=True)
    mid = slerp(Q0, -a, 0.5)  # -a is a: the short way
    assert np.degrees(2 * np.arccos(abs(mid @ a))) == pytest.approx(
        np.degrees(2 * np.arccos(abs(Q0 @ a))) / 2, abs=1e-9
    )


def _feed() -> tuple[AttitudeFeed, ManualClock, float]:
    clock = ManualClock()
    return AttitudeFeed(clock), clock, clock.now


def test_good_feed_interpolates_at_mid_time():
    feed, _, now = _feed()
    omega = np.radians([0.0, 0.0, 2.0])
    a0 = quat_to_matrix(Q0)
    for t in np.arange(now - 1, now + 1, 0.1):
        q = matrix_to_quat(Rotation.from_rotvec(-omega * (t - now)).as_matrix() @ a0)
        feed.offer(Sample(t, q, omega))
    q, w = feed.at(now + 0.05, timeout=0.0, max_gap=0.5)
    truth = Rotation.from_rotvec(-omega * 0.05).as_matrix() @ a0
    assert np.degrees(rotation_angle(quat_to_matrix(q), truth)) < 1e-6 and np.allclose(w, omega)


BAD_SAMPLES = {
    "NaN": lambda t: _sample(t, [np.nan, 0, 0, 0]),
    "infinite": lambda t: _sample(t, Q0, [np.inf, 0, 0]),
    "unnormalised": lambda t: _sample(t, Q0 * 1.00001),
    "backwards": lambda t: _sample(t - 5.0),
    "future": lambda t: _sample(t + 1e6),
    "jump": lambda t: _sample(t, matrix_to_quat(attitude_from_radec_roll(1.1, 0.3, 0.2)), np.zeros(3)),
}


@pytest.mark.parametrize("case", sorted(BAD_SAMPLES))
def test_bad_sample_flags_the_frame_then_the_feed_recovers(case):
    feed, _, now = _feed()
    _path(feed, now - 1, now)  # arrived before the exposure
    feed.offer(BAD_SAMPLES[case](now))  # arrives at `now` by the feed's clock
    _path(feed, now, now + 0.5)
    with pytest.raises(FrameUnavailable, match="fault during the exposure"):
        feed.at(now + 0.25, timeout=0.0, max_gap=0.5)
    _path(feed, now + 0.5, now + 1.0)  # good samples: the path after max_gap is sound again
    q, _ = feed.at(now + 0.75, timeout=0.0, max_gap=0.5)
    assert np.all(np.isfinite(q))


def test_a_future_sample_is_refused_and_the_feed_goes_on():
    """Issue 29: one sample stamped 1e6 s ahead made every later correct one 'go backwards'."""
    feed, _, now = _feed()
    _path(feed, now - 1, now)
    feed.offer(_sample(now + 1e6))
    assert "ahead of the device clock" in feed.faults()[-1][1]
    _path(feed, now, now + 1.0)  # every correct sample kept (it used to refuse them all)
    q, _ = feed.at(now + 0.75, timeout=0.0, max_gap=0.5)  # past the fault's max_gap: sound again
    assert np.all(np.isfinite(q)) and now + 0.9 < feed.newest_t() < now + 1


def test_a_simulator_that_reconnects_at_an_earlier_time_resets_the_history():
    feed, _, now = _feed()
    _path(feed, now - 1, now)
    feed.offer(_sample(now - 30.0))  # without a reconnect: refused
    assert "time does not advance" in feed.faults()[-1][1]
    feed.new_peer()
    _path(feed, now - 30.0, now - 29.0)
    assert "reconnected at an earlier time: history reset" in feed.faults()[-1][1]
    assert now - 29.1 < feed.newest_t() < now - 28.9


def test_stale_gap_and_no_history_are_flagged():
    feed, clock, now = _feed()
    with pytest.raises(FrameUnavailable, match="no sample received"):
        feed.at(now, timeout=0.0, max_gap=0.5)
    _path(feed, now - 2, now - 1)
    clock.advance(0.06)  # past the wait's end (now + 0.05): nothing newer arrived
    with pytest.raises(FrameUnavailable, match="stale"):
        feed.at(now, timeout=0.05, max_gap=0.5)
    feed.offer(_sample(now + 1, Q0, np.zeros(3)))  # the feed resumes after a 2 s silence
    with pytest.raises(FrameUnavailable, match="gap"):
        feed.at(now, timeout=0.0, max_gap=0.5)
    late = AttitudeFeed()
    _path(late, now + 1, now + 2)
    with pytest.raises(FrameUnavailable, match="no sample before"):
        late.at(now, timeout=0.0, max_gap=0.5)


def _waiting_at(feed, t, timeout) -> tuple[threading.Thread, list]:
    """``feed.at(t, timeout, 0.5)`` in a thread; the list gets its (q, w) or its exception."""
    out: list = []

    def run():
        try:
            out.append(feed.at(t, timeout=timeout, max_gap=0.5))
        except FrameUnavailable as exc:
            out.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, out


def test_a_capture_waits_by_the_clock_and_takes_a_sample_that_arrives_in_time():
    feed, clock, now = _feed()
    _path(feed, now - 1, now)
    thread, out = _waiting_at(feed, now + 0.05, timeout=0.25)
    thread.join(0.3)
    assert thread.is_alive() and not out  # the clock has not moved: still waiting, however long that is
    feed.offer(_sample(now + 0.1, Q0, np.zeros(3)))  # the sample the exposure needs
    thread.join(HANG_GUARD_S)
    assert len(out) == 1 and not isinstance(out[0], Exception) and np.allclose(out[0][0], Q0)
    thread, out = _waiting_at(feed, now + 0.2, timeout=0.25)  # nothing after now + 0.1 will come
    clock.advance(0.46)  # the clock passes now + 0.2 + 0.25: the wait ends
    thread.join(HANG_GUARD_S)
    assert len(out) == 1 and isinstance(out[0], FrameUnavailable) and "stale" in str(out[0])


def test_undecodable_bytes_flag_the_frame():
    feed, _, now = _feed()
    _path(feed, now - 1, now + 1)
    feed.fault("not a JSON sample")
    with pytest.raises(FrameUnavailable, match="not a JSON sample"):
        feed.at(now, timeout=0.0, max_gap=0.5)


# ---------------------------------------------------------------- smear


def test_smear_streak_length_at_a_known_rate():
    cam = CameraModel.from_fov(400, 300, 3.0)
    det = DetectorModel(pattern="MONO", psf_sigma_px=1.0)
    att = attitude_from_radec_roll(0.3, -0.4, 0.1)
    rate, t_exp = np.radians(3.0), 0.1  # 3 deg/s about sensor y: a streak along x
    psf = SmearPSF(cam, det, [0.0, rate, 0.0], t_exp)
    x0, y0 = cam.cx, cam.cy
    star = Stars([1], cam.pixel_to_vector([x0], [y0]) @ att, [3.0], [1.0], [1.0])
    e = render_frame(star, att, cam, det, psf=psf).electrons
    cols = np.arange(cam.width)
    px = e.sum(axis=0) / e.sum()
    mean = px @ cols
    var_x = px @ (cols - mean) ** 2
    length = np.sqrt(12.0 * (var_x - 1.0 - 1.0 / 12.0))  # uniform streak (+) Gaussian (+) pixel
    expected = cam.f * np.tan(rate * t_exp / 2) * 2
    assert length == pytest.approx(expected, rel=0.02) and expected > 10
    assert mean == pytest.approx(x0, abs=0.05)  # centred on the mid-exposure position
    var_y = (e.sum(axis=1) / e.sum()) @ (np.arange(cam.height) - y0) ** 2
    assert var_y == pytest.approx(1.0 + 1.0 / 12.0, rel=0.05)  # no smear across the track
    xs, _ = psf.track(x0, y0)
    assert xs[0] > xs[-1]  # stars move against the rotation: dv/dt = -omega x v


@pytest.mark.parametrize("rate", [[0.0, 1.0, 0.0], [0.0, 0.0, 100.0], [0.0, 2 * np.pi / 0.1, 0.0]])
def test_a_rate_beyond_the_renderers_reach_is_refused_before_any_work(rate):
    """Issue 29: 1 rad/s (or 100 rad/s of roll) made the smear render unbounded (no result after
    60-90 s, 600 MB); a whole revolution in the exposure (whose track ends where it began) too."""
    from ground.sim.smear import MAX_TRACK_PX, TooFast

    det = DetectorModel(pattern="MONO", psf_sigma_px=1.0)
    with pytest.raises(TooFast, match=f"beyond the {MAX_TRACK_PX:g} px the renderer draws"):
        SmearPSF(SMALL_CAM, det, rate, 0.1)


def test_device_answers_bad_frame_at_once_for_a_rate_beyond_the_renderers_reach(feed_device):
    dev, snd, solver, clock = feed_device
    now = clock.now
    ts = np.arange(now - 1, now + 1, 0.02)
    snd.send(*(_sample(t, Q0, [0.0, 1.0, 0.0]) for t in ts))
    _wait_for_samples(dev, float(ts[-1]))
    status, reason = _go(dev)
    assert status == result.Status.BAD_FRAME and "smears stars over" in reason, reason
    assert not solver.frames
    (rep,) = _send(dev, Code.PING)
    assert rep.ack and b"IDLE" in rep.data


# ---------------------------------------------------------------- the device keeps serving


def _send(dev, code, data=b""):
    frames = dev.receive(nsp.command(0x0E, 0x11, code, data).frame())
    return [nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(f)[0].data) for f in frames]


class _OkSolver:
    def __init__(self):
        self.frames = []

    def __call__(self, ctx):
        self.frames.append(ctx.frame)
        return {"return_code": result.make_return_code(result.Status.OK), "quaternion": [1, 0, 0, 0]}


@pytest.fixture
def feed_device():
    """(device, sender, solver, clock): an in-process device capturing from a UDP feed, the device
    and its feed on one manual clock."""
    url = f"udp://127.0.0.1:{_free_port(socket.SOCK_DGRAM)}?timeout=0.2"
    clock = ManualClock()
    renderer = ExposureRenderer(SMALL_CAM)
    source = AttitudeFeedSource(url, SMALL_CAM, renderer=renderer, clock=clock)
    solver = _OkSolver()
    dev = Device(solver=solver, frame_source=source, sensor_shape=(SMALL_CAM.height, SMALL_CAM.width), clock=clock)
    dev.runner.transfers.objects[0] = "catalog"  # any catalog object: the stub solver ignores it
    (rep,) = _send(dev, Code.INIT, struct.pack("<I", 0x2000))
    assert rep.ack
    try:
        with Sender(url) as snd:
            yield dev, snd, solver, clock
    finally:
        clock.advance(3600.0)  # a capture still waiting gives up at once
        dev.wait_idle(HANG_GUARD_S)
        source.close()


def _go(dev, clock=None, waited=0.0):
    """GO; with ``clock``, the clock moves on ``waited`` s once the GO is stamped (a capture
    waiting for the feed sees that much time pass)."""
    (rep,) = _send(dev, Code.GO, b"\x0b")
    assert rep.ack
    if clock is not None:
        clock.advance(waited)
    assert dev.wait_idle(HANG_GUARD_S)
    rec = result.parse(dev.runner.result)
    return result.status_of(int(rec["return_code"])), bytes(rec["ext"]["reason"]).rstrip(b"\0").decode()


def _stream(snd, t0, t1, step=0.02) -> float:
    """Samples from t0 to before t1; returns the last t sent."""
    ts = np.arange(t0, t1, step)
    snd.send(*(_sample(t, Q0, np.zeros(3)) for t in ts))
    return float(ts[-1])


def _wait_for(dev, arrived, what: str) -> None:
    """Until ``arrived(feed)`` holds (the listener thread has taken what was sent): a hang guard."""
    deadline = time.monotonic() + HANG_GUARD_S
    while not arrived(dev.frame_source.feed):
        if time.monotonic() > deadline:
            raise AssertionError(f"the feed did not receive {what}")
        time.sleep(0.005)


def _wait_for_samples(dev, t) -> None:
    _wait_for(dev, lambda feed: (feed.newest_t() or -math.inf) >= t, f"samples up to {t}")


@pytest.mark.parametrize("case", sorted(BAD_SAMPLES) + ["stale", "malformed"])
def test_device_flags_a_bad_feed_and_keeps_serving(feed_device, case):
    dev, snd, solver, clock = feed_device
    now = clock.now
    last = _stream(snd, now - 1, now + 1)
    _wait_for_samples(dev, last)
    assert _go(dev)[0] == result.Status.OK and len(solver.frames) == 1  # a good feed renders and solves
    if case == "stale":
        # the feed stops: GO at now + 1.1 (exposure mid-time now + 1.15, after the newest sample);
        # the capture waits until the clock passes now + 1.35, then gives up
        clock.advance(1.1)
        status, reason = _go(dev, clock, waited=0.3)
        assert "stale" in reason, reason
    else:
        if case == "malformed":
            snd.send_raw(b'{"t": 1, "q": "oops"}\n')
        else:
            snd.send(BAD_SAMPLES[case](now + 1.0))
        _wait_for(dev, lambda feed: bool(feed.faults()), "the bad sample")  # a fault at `now`
        last = _stream(snd, last + 0.02, now + 3)  # the feed goes on
        _wait_for_samples(dev, last)
        status, reason = _go(dev)  # GO at `now`: the fault is within max_gap of the exposure
    assert status == result.Status.BAD_FRAME and "attitude feed" in reason, reason
    assert len(solver.frames) == 1  # nothing rendered went to the solver
    (rep,) = _send(dev, Code.PING)
    assert rep.ack and b"IDLE" in rep.data
    # a fault makes the feed suspect for max_gap (0.5 s); a jump restarts the path at now + 1
    clock.set(max(clock.now, now + 1.1))
    if case == "stale":  # the stale feed resumes
        last = _stream(snd, last + 0.02, now + 3)
        _wait_for_samples(dev, last)
    assert _go(dev)[0] == result.Status.OK and len(solver.frames) == 2  # and recovers


def test_busy_nack_while_a_feed_exposure_waits(feed_device):
    dev, snd, _, clock = feed_device
    (rep,) = _send(dev, Code.GO, b"\x0b")  # no samples: the exposure waits for the feed
    assert rep.ack
    (busy,) = _send(dev, Code.GO, b"\x0b")  # the clock has not moved: the capture still waits
    info = NackInfo.unpack(busy.data)
    assert not busy.ack and info.reason == NackReason.BUSY and "sequence 1" in info.text
    clock.advance(1.0)  # past the exposure's wait: the capture gives up
    assert dev.wait_idle(HANG_GUARD_S)
    rec = result.parse(dev.runner.result)
    assert result.status_of(int(rec["return_code"])) == result.Status.BAD_FRAME
    assert b"no sample received" in bytes(rec["ext"]["reason"])


# ---------------------------------------------------------------- end to end: st16-device --attitude-feed


class _RealTimeStream(threading.Thread):
    """A dynamics simulator: samples of ``truth(t)`` stamped with the time they are sent
    (``time.time``, the device's clock), every ``step`` s until stopped; :meth:`inject` sends one
    extra sample between two of them. A sample at or after an exposure's mid-time is sent after
    that time, so everything sent before it has reached the device's feed first (one TCP stream)."""

    def __init__(self, sender, truth, omega, step=0.02):
        super().__init__(daemon=True)
        self.sender, self.truth, self.omega, self.step = sender, truth, omega, step
        self.stop = threading.Event()
        self._lock = threading.Lock()

    def run(self):
        while not self.stop.is_set():
            t = time.time()
            with self._lock:
                self.sender.send(Sample(t, matrix_to_quat(self.truth(t)), self.omega))
            self.stop.wait(self.step)

    def inject(self, sample):
        with self._lock:
            self.sender.send(sample)


def test_device_cli_solves_along_a_fed_path(tmp_path):
    from firmware_model.catalog.image_io import catalog_to_image
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.link.client import Client
    from ground.link.solve_report import solve_record
    from ground.sim.device_process import pick_attitudes, start_device, stop_device

    cam = CameraModel.reference_design()
    catalog = build_catalog(CatalogDesign())
    (a0,) = pick_attitudes(catalog, cam, 1, np.random.default_rng(4))
    omega = np.radians([0.3, -0.2, 0.5])  # deg/s: a few px of smear in 0.1 s
    # the capture waits up to 60 s for its sample and takes gaps and faults from 60 s before it as
    # its own: hang guards, so a starved stream thread is neither a gap nor a missed fault
    url = f"tcp://127.0.0.1:{_free_port(socket.SOCK_STREAM)}?format=binary&timeout=60&max_gap=60"
    proc, pty = start_device(tmp_path / "state", "--attitude-feed", url)
    t0 = time.time()

    def truth(t):
        return Rotation.from_rotvec(-omega * (t - t0)).as_matrix() @ a0

    try:
        with Client(pty, timeout=guards.REPLY_S) as c, Sender(url) as snd:
            c.init()
            c.upload(0, catalog_to_image(catalog), progress=False)
            stream = _RealTimeStream(snd, truth, omega)
            stream.start()
            try:
                raw = c.go_and_wait(timeout=120)
                rec, mid = solve_record(raw), float(raw["ext"]["utc_epoch"])  # the exposure's mid-time, UTC
                stream.inject(Sample(time.time(), Q0 * 2, omega))  # unnormalised
                flagged = solve_record(c.go_and_wait(timeout=120))
            finally:
                stream.stop.set()
                stream.join(HANG_GUARD_S)
            assert "APPLICATION" in c.ping()
    finally:
        assert stop_device(proc) == 0
    assert rec["status"] == "OK", rec
    a = quat_to_matrix(rec["q_icrs_to_sensor"])
    err = np.degrees(rotation_angle(a, truth(mid)))
    # the attitude at the exposure mid-time, GO + 50 ms (0.031 deg from the GO-time attitude at this
    # rate); the solve's own error (roll sigma ~20") is what is left
    assert err < 0.015 and err < np.degrees(rotation_angle(a, truth(mid - 0.05)))
    assert flagged["status"] == "BAD_FRAME" and "quaternion norm" in flagged["reason"]


# ---------------------------------------------------------------- issue 33: time and position


def _feed_source(query: str = "") -> tuple[AttitudeFeedSource, ManualClock]:
    clock = ManualClock()
    port = _free_port(socket.SOCK_DGRAM)
    renderer = ExposureRenderer(SMALL_CAM, stars=Stars([], np.zeros((0, 3)), [], [], []))
    src = AttitudeFeedSource(f"udp://127.0.0.1:{port}?pattern=MONO{query}", SMALL_CAM, renderer, clock)
    src.ready()
    return src, clock


def test_feed_frames_carry_the_mid_time_and_the_samples_position():
    from types import SimpleNamespace

    from ground.sim.sky_source import utc_iso

    src, clock = _feed_source()
    try:
        now = clock.now
        for k, t in enumerate(np.arange(now - 1, now + 1, 0.1)):
            src.feed.offer(Sample(t, Q0, np.zeros(3), np.array([7000.0 + 10.0 * k, 0.0, 0.0])))
        t_mid = now + 0.05
        frame = src(SimpleNamespace(started=now, sequence=1))
        assert frame.timestamp == utc_iso(t_mid - 0.05)  # the exposure's start (docs/CONVENTIONS.md)
        # linear between the samples at now (k = 10) and now + 0.1 (k = 11)
        assert frame.metadata["sc_position_km"] == pytest.approx([7105.0, 0.0, 0.0], abs=1e-3)
        assert {"sun", "moon", "earth"} <= set(frame.metadata["glare"])
    finally:
        src.close()


def test_feed_orbit_option_places_the_spacecraft_when_samples_carry_no_position():
    from types import SimpleNamespace

    from ground.sim.orbit import CircularOrbit

    src, clock = _feed_source("&orbit=550,97.6,30,0,2026-06-01T00:00:00")
    try:
        now = clock.now
        _path(src.feed, now - 1, now + 1, step=0.1)
        frame = src(SimpleNamespace(started=now, sequence=2))
        expect = CircularOrbit.parse("550,97.6,30,0,2026-06-01T00:00:00").position_gcrs_km(now + 0.05)
        assert frame.metadata["sc_position_km"] == pytest.approx(list(expect), abs=1e-6)
    finally:
        src.close()
    plain, clock = _feed_source()
    try:
        _path(plain.feed, clock.now - 1, clock.now + 1, step=0.1)
        frame = plain(SimpleNamespace(started=clock.now, sequence=3))
        # no position: the stars alone, no timestamp (the answers do not depend on the date)
        assert "sc_position_km" not in frame.metadata and frame.timestamp is None
        assert "glare" not in frame.metadata
    finally:
        plain.close()


@pytest.mark.parametrize(
    "query, msg",
    [("&orbit=50", "orbit altitude 50 km is outside"), ("&orbit=550,x", "altitude and angles must be numbers")],
)
def test_bad_orbit_option_is_a_one_line_error(query, msg):
    with pytest.raises(ValueError, match=msg) as info:
        _feed_source(query)
    assert "\n" not in str(info.value)


def test_a_sample_with_a_bad_position_is_a_fault():
    feed, _, now = _feed()
    _path(feed, now - 1, now)
    feed.offer(Sample(now, Q0, np.zeros(3), np.array([6000.0, 0.0, 0.0])))
    feed.offer(Sample(now + 0.01, Q0, np.zeros(3), np.array([np.nan, 0.0, 0.0])))
    reasons = [r for _, r in feed.faults()]
    assert any("inside the atmosphere" in r for r in reasons) and any("NaN" in r for r in reasons)
