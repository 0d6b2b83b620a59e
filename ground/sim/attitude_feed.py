"""``st16-device --attitude-feed URL``: exposures rendered along the attitude path a dynamics
simulator streams (wire format and URL: ``ground.sim.feed_wire``; docs/hil.md).

A listener thread checks every sample on arrival and keeps the good ones in a ring buffer:

* NaN or infinite values, a quaternion norm off 1 by more than :data:`NORM_TOL`, time not
  advancing: the sample is dropped and the fault recorded;
* an attitude jump larger than the rates allow (:func:`allowed_turn`): recorded, and the path
  restarts at the new sample (no interpolation across it);
* bytes that do not decode: recorded.

Each GO exposes from the GO time ``t0`` for ``exposure`` s. The capture waits (up to ``timeout`` s
past the mid-time ``t0 + exposure / 2``) for a sample at or after the mid-time, slerps the
attitude and interpolates the rate there, and renders the real sky at that attitude with every
star smeared along its track at that rate (``ground.sim.smear``). The frame is refused with the
reason as the result's BAD_FRAME text, never rendered, when the feed is stale, has no sample
before the exposure, a gap over ``max_gap`` s around it, or a fault recorded from ``max_gap`` s
before the mid-time on (the feed is suspect that long after a fault). Registered as the ``attitude_feed`` entry point of
``st16.frame_sources``. URL query options: ``format``, ``exposure`` (s, default the detector's
0.1), ``timeout`` (s, 0.25), ``max_gap`` (s, 0.5), ``pattern`` (RGGB), ``idle`` (s, 60: over TCP a
peer silent that long is closed, and a new connection takes over at once, as on the NSP TCP link),
``clock`` (``wall``, the default, or ``sim``: the device takes its time from the samples and reads
no wall clock for what it reports, ``ground.sim.feed_clock``; docs/hil.md "Simulated time"),
``orbit`` (``ALT_KM[,INC_DEG[,RAAN_DEG[,ARG_LAT_DEG[,EPOCH_UTC]]]]``, ``ground.sim.orbit``: the
spacecraft's position at the mid-time when the samples carry none), and the detector effects over
a mission (``ground.sim.detector_effects.SOURCE_OPTIONS``: ``cosmic_rate``, ``hits_per_frame``,
``saa`` (with ``orbit``), ``dose_krad``, ``temperature_c`` or ``duty``; drawn from the GO's
sequence number).

When the feed knows where the spacecraft is (the samples' ``r`` interpolated linearly to the
mid-time when both samples around it carry one, else the ``orbit`` option's), every frame is
rendered with the Sun's, the Moon's and the Earth's light at the mid-time (``ground.sim.glare``;
no sunlight in the Earth's shadow), stamped with the exposure's start (``timestamp``, ISO-8601 UTC,
docs/CONVENTIONS.md) and the position (``metadata["sc_position_km"]``) for the device's bright-body
check. Without a position the frame holds the stars alone and no timestamp, as before (tracking
takes the GO time): the answers of a run do not depend on the date it runs. A sample whose ``r``
is not finite or lies inside the atmosphere is dropped as a fault, like a bad attitude.

Every time here (arrival of a fault, the capture's wait) is read from one ``clock`` (POSIX s,
``time.time`` unless given), the clock the device stamps its GO with: a test passes a manual clock
to both and decides when a feed is stale or a fault has aged, whatever the machine's load.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from firmware_model.device.device import FrameUnavailable
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.reference_frames import quat_to_matrix
from ground.sim.detector_effects import (
    MAX_SOURCE_HITS_PER_FRAME,
    SOURCE_OPTIONS,
    check_hits,
    effects_from_options,
)
from ground.sim.exposure import ExposureRenderer, noise_cache_dir
from ground.sim.feed_clock import WALL_GUARD_S, FeedClock
from ground.sim.feed_wire import IDLE_S, FeedUrl, Listener, Sample
from ground.sim.nasa42 import Nasa42Options, Reader
from ground.sim.orbit import CircularOrbit, utc_iso
from ground.sim.sensor_sim import DetectorModel
from ground.sim.sky_source import check_position
from ground.sim.smear import SmearPSF, TooFast

NORM_TOL = 1e-6  #: | |q| - 1 | above this is an unnormalised quaternion
JUMP_TOL = 1e-3  #: rad of turn between two samples allowed beyond what their rates explain
RING = 512  #: samples kept (about 5 s at 100 Hz)
MIN_SMEAR_PX = 0.05  #: below this track length the exposure renders without smear
WAIT_SLICE_S = 0.02  #: real seconds a waiting capture sleeps between looks at the clock


def allowed_turn(a: Sample, b: Sample) -> float:
    """Largest turn (rad) from ``a`` to ``b`` that is not a jump: twice the larger rate over the gap, plus JUMP_TOL."""
    return 2.0 * max(float(np.linalg.norm(a.w)), float(np.linalg.norm(b.w))) * abs(b.t - a.t) + JUMP_TOL


def turn_angle(q1: np.ndarray, q2: np.ndarray) -> float:
    """Angle (rad) of the rotation between two unit quaternions."""
    return 2.0 * math.acos(min(1.0, abs(float(np.dot(q1, q2)))))


def slerp(q1: np.ndarray, q2: np.ndarray, f: float) -> np.ndarray:
    """Unit quaternion a fraction ``f`` of the short way from ``q1`` to ``q2``."""
    d = float(np.dot(q1, q2))
    if d < 0.0:
        q2, d = -q2, -d
    if d > 0.9995:
        q = q1 + f * (q2 - q1)
    else:
        th = math.acos(d)
        q = (math.sin((1.0 - f) * th) * q1 + math.sin(f * th) * q2) / math.sin(th)
    return q / np.linalg.norm(q)


#: A sample stamped more than this many seconds ahead of the device clock is refused (it would
#: otherwise make every later, correct sample look as if its time went backwards).
MAX_AHEAD_S = 60.0


def check(sample: Sample, prev: Sample | None, now: float | None = None) -> str | None:
    """Why ``sample`` must be dropped, or None (a jump is not checked here); ``now`` the device
    clock (POSIX s)."""
    if not (math.isfinite(sample.t) and np.all(np.isfinite(sample.q)) and np.all(np.isfinite(sample.w))):
        return "sample holds NaN or infinite values"
    if now is not None and sample.t > now + MAX_AHEAD_S:
        return f"sample time is {sample.t - now:.3g} s ahead of the device clock (more than {MAX_AHEAD_S:g} s)"
    if sample.r is not None:
        why = check_position(sample.r)
        if why:
            return f"sample {why}"
    norm = float(np.linalg.norm(sample.q))
    if abs(norm - 1.0) > NORM_TOL:
        return f"quaternion norm {norm:.9f} is not 1"
    if prev is not None and sample.t <= prev.t:
        return f"time does not advance: t {sample.t:.6f} after {prev.t:.6f}"
    return None


class AttitudeFeed:
    """The checked samples and faults of one feed (module docstring); thread-safe. ``clock``
    (POSIX s) stamps each fault's arrival and bounds :meth:`at`'s wait."""

    def __init__(self, clock: Callable[[], float] = time.time):
        self.clock = clock
        self._ring: deque[Sample] = deque(maxlen=RING)
        self._faults: deque[tuple[float, str]] = deque(maxlen=64)
        self._cond = threading.Condition()
        self._fresh_peer = False  #: a peer connected and has sent no sample yet
        #: real seconds a capture waits at most (simulated time, ``ground.sim.feed_clock``: the clock
        #: stands still while the simulator does); None: the clock alone bounds the wait
        self.wall_guard_s: float | None = None

    def new_peer(self) -> None:
        """A simulator (re)connected: its first sample may start over at an earlier time."""
        with self._cond:
            self._fresh_peer = True

    def offer(self, sample: Sample) -> None:
        with self._cond:
            now = self.clock()
            prev = self._ring[-1] if self._ring else None
            reason = check(sample, prev, now)
            fresh, self._fresh_peer = self._fresh_peer, False
            if reason is not None and prev is not None and sample.t <= prev.t and (fresh or prev.t > now + 1.0):
                # a simulator that reconnected at an earlier time, or kept history ahead of the clock
                # (a clock set back): either would refuse every correct sample from now on
                why = "the feed reconnected at an earlier time" if fresh else "kept samples are ahead of the clock"
                self._faults.append((now, f"{why}: history reset at t {sample.t:.3f}"))
                self._ring.clear()
                prev, reason = None, check(sample, None, now)
            if reason is not None:
                self._faults.append((now, reason))
                return
            if prev is not None and turn_angle(prev.q, sample.q) > allowed_turn(prev, sample):
                turn = math.degrees(turn_angle(prev.q, sample.q))
                self._faults.append((now, f"attitude jumps {turn:.4f} deg in {sample.t - prev.t:.3f} s"))
                self._ring.clear()
            self._ring.append(sample)
            self._cond.notify_all()

    def fault(self, reason: str) -> None:
        with self._cond:
            self._faults.append((self.clock(), reason))

    def newest_t(self) -> float | None:
        """Time of the newest kept sample, None before the first."""
        with self._cond:
            return self._ring[-1].t if self._ring else None

    def faults(self) -> list[tuple[float, str]]:
        """The recorded faults (arrival time by the clock, reason), oldest first."""
        with self._cond:
            return list(self._faults)

    def at(self, t: float, timeout: float, max_gap: float) -> tuple[np.ndarray, np.ndarray]:
        """(q, w) at ``t`` (POSIX s), waiting until the clock reads ``t + timeout`` for a sample at
        or after it; raises FrameUnavailable with the reason when the feed cannot give a sound attitude.
        The wait looks at the clock every :data:`WAIT_SLICE_S` of real time, so with a manual clock
        it lasts until that clock is moved past the deadline (or the sample arrives)."""
        wall_end = None if self.wall_guard_s is None else time.monotonic() + self.wall_guard_s
        with self._cond:
            while not (self._ring and self._ring[-1].t >= t):
                left = t + timeout - self.clock()
                if left <= 0 or (wall_end is not None and time.monotonic() > wall_end):
                    break
                self._cond.wait(min(left, WAIT_SLICE_S))
            if not self._ring:
                if self._faults:  # every sample so far was bad: say why, not that none came
                    raise FrameUnavailable(f"attitude feed: no good sample; last fault: {self._faults[-1][1]}")
                raise FrameUnavailable("attitude feed: no sample received")
            newest = self._ring[-1]
            if newest.t < t:
                raise FrameUnavailable(f"attitude feed stale: newest sample {t - newest.t:.3f} s before the exposure")
            k = next(i for i, s in enumerate(self._ring) if s.t >= t)
            if k == 0 and self._ring[0].t > t:
                raise FrameUnavailable("attitude feed: no sample before the exposure (the path starts after it)")
            a, b = self._ring[max(k - 1, 0)], self._ring[k]
            faults = [reason for when, reason in self._faults if when >= t - max_gap]
            if faults:
                raise FrameUnavailable(f"attitude feed fault during the exposure: {faults[0]}")
        if b.t - a.t > max_gap:
            raise FrameUnavailable(f"attitude feed gap of {b.t - a.t:.3f} s around the exposure")
        f = 0.0 if b.t == a.t else (t - a.t) / (b.t - a.t)
        return slerp(a.q, b.q, f), a.w + f * (b.w - a.w)

    def position_at(self, t: float) -> np.ndarray | None:
        """The samples' GCRS position (km) at ``t``, linear between the two around it; None unless
        both carry one (call after :meth:`at` has accepted ``t``)."""
        with self._cond:
            k = next((i for i, s in enumerate(self._ring) if s.t >= t), None)
            if k is None:
                return None
            a, b = self._ring[max(k - 1, 0)], self._ring[k]
        if a.r is None or b.r is None:
            return None
        f = 0.0 if b.t == a.t else (t - a.t) / (b.t - a.t)
        return a.r + f * (b.r - a.r)


#: The feed's timing options (s): name -> (smallest, largest, whether the smallest is allowed).
#: Documented ceilings: an exposure of 10 s (star trackers expose for up to ~1 s), a capture's wait
#: and a gap of 60 s (the device's reply guard), a silent peer kept for a day.
TIMING_OPTIONS = {
    "exposure": (0.0, 10.0, False),
    "timeout": (0.0, 60.0, True),
    "max_gap": (0.0, 60.0, False),
    "idle": (0.0, 86400.0, False),
}


def _timing(opts: dict[str, str], key: str, default: float) -> float:
    """The timing option ``key`` (s) popped from ``opts``, or ``default``; ValueError for one that
    is not a number or outside :data:`TIMING_OPTIONS` (NaN and infinities too)."""
    if key not in opts:
        return default
    text = opts.pop(key)
    lo, hi, closed = TIMING_OPTIONS[key]
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{key}={text[:40]!r} is not a number of seconds") from None
    if not ((lo <= value if closed else lo < value) and value <= hi):
        raise ValueError(f"{key}={text[:40]} s is outside {'[' if closed else '('}{lo:g}, {hi:g}]")
    return value


class AttitudeFeedSource:
    """Capture source: the exposure at each GO rendered along the fed attitude path. ``clock``
    (POSIX s) must be the device's, whose GO time the exposure starts at (module docstring)."""

    def __init__(
        self, spec: str, camera, renderer: ExposureRenderer | None = None, clock: Callable[[], float] = time.time
    ):
        nasa: Nasa42Options | None = None
        if spec.startswith("42://"):  # NASA 42's IPC socket (ground.sim.nasa42): always simulated time
            try:
                nasa = Nasa42Options(spec)
            except ValueError as exc:
                raise ValueError(f"attitude feed {spec!r}: {exc}") from None
        url = FeedUrl.parse(spec) if nasa is None else None
        opts = dict(url.options if url is not None else nasa.options if nasa is not None else {})
        try:
            self.det = DetectorModel(pattern=opts.pop("pattern", "RGGB"))
            self.exposure_s = _timing(opts, "exposure", self.det.exposure_s)
            self.timeout = _timing(opts, "timeout", 0.25)
            self.max_gap = _timing(opts, "max_gap", 0.5)
            self.idle = _timing(opts, "idle", IDLE_S)
            self.orbit = CircularOrbit.parse(opts.pop("orbit")) if "orbit" in opts else None
            clock_kind = opts.pop("clock", "wall") if nasa is None else "sim"
            if clock_kind not in ("wall", "sim"):
                raise ValueError(f"clock={clock_kind[:40]!r}: wall or sim")
            asked = {k: opts.pop(k) for k in list(opts) if k in SOURCE_OPTIONS}
            self.effects = effects_from_options(asked, self.orbit)
            if opts:
                raise ValueError(f"unknown option(s) {sorted(opts)}")
            self.det = DetectorModel(pattern=self.det.pattern, exposure_s=self.exposure_s)
            check_hits(self.effects, self.det, camera, MAX_SOURCE_HITS_PER_FRAME)
        except ValueError as exc:
            raise ValueError(f"attitude feed {spec!r}: {exc}") from None
        self.camera = camera
        self.renderer = renderer or ExposureRenderer(camera, cache_dir=noise_cache_dir())
        # at start-up, not inside the first GO
        # glare: samples may carry a position, which renders the bright bodies
        self._drawing = self.renderer.draw_bank(self.renderer.effective_detector(self.det, self.effects), glare=True)
        #: simulated time (``clock=sim``, ``ground.sim.feed_clock``): the device's clocks read it
        self.simulated_clock = FeedClock() if clock_kind == "sim" else None
        self.feed = AttitudeFeed(clock if self.simulated_clock is None else self.simulated_clock.posix)
        offer = self.feed.offer if self.simulated_clock is None else self._offer_simulated
        if self.simulated_clock is not None:
            self.feed.wall_guard_s = WALL_GUARD_S
        self.listener: Listener | Reader = (
            Listener(url, offer, self.feed.fault, self.feed.new_peer, idle_s=self.idle)
            if url is not None
            else Reader(nasa, offer, self.feed.fault, self.feed.new_peer)  # type: ignore[arg-type]
        )

    def _offer_simulated(self, sample: Sample) -> None:
        """A sample offered in simulated time: the clock moves to the newest one kept."""
        assert self.simulated_clock is not None
        self.simulated_clock.offering(sample.t)
        self.feed.offer(sample)
        newest = self.feed.newest_t()
        if newest is not None:
            self.simulated_clock.accepted(newest)

    def ready(self) -> None:
        """Return once the source can render at once (its noise bank drawn)."""
        self._drawing.join()

    def close(self) -> None:
        self.listener.close()

    def __call__(self, ctx, mount=None) -> Frame:
        t_mid = ctx.started + self.exposure_s / 2.0
        q, w = self.feed.at(t_mid, self.timeout, self.max_gap)
        try:
            psf = SmearPSF(self.camera, self.det, w, self.exposure_s)
        except TooFast as exc:  # BAD_FRAME at once: the render's work would grow without bound
            raise FrameUnavailable(f"attitude feed: {exc}") from None
        position = self.feed.position_at(t_mid)
        source = "interpolated sample"
        if position is None and self.orbit is not None:
            position, source = self.orbit.position_gcrs_km(t_mid), "orbit"
        if position is not None:
            why = check_position(position, utc_iso(t_mid))  # between two good samples, or the Moon's
            if why:
                raise FrameUnavailable(f"attitude feed: {source} {why}")
        attitude = quat_to_matrix(q)
        if mount is not None:  # a head's body-to-sensor mounting: the source gives the body's attitude (--heads)
            attitude = mount @ attitude
        frame = self.renderer.render(
            attitude,
            self.det,
            seed=ctx.sequence,
            psf=psf if psf.max_track_px >= MIN_SMEAR_PX else None,
            epoch_utc=None if position is None else utc_iso(t_mid),
            sc_position_km=position,
            effects=None if self.effects is None else self.effects.at_time(t_mid),
        )
        frame.metadata["attitude_feed"] = {"q_mid": [float(v) for v in q], "w_mid": [float(v) for v in w]}
        return frame
