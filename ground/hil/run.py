"""The tracker in a closed attitude loop (docs/hil.md), as ``st16-ground hil demo`` runs it.

A device on a pty paced at 115 200 baud renders each exposure from the attitude a dynamics
simulation streams to its ``--attitude-feed`` (UDP on loopback); a flight-software loop reads the
tracker's attitude with a minimal COMBINATION and feeds it back to an MRP feedback controller
that slews the spacecraft from a few degrees off to a target attitude. Dynamics: Basilisk
(``bsk``, the ``[hil]`` extra) or, without it, a numpy stand-in, labelled so in every output.
Writes ``hil_log.jsonl`` (truth vs measured per update), ``summary.json`` and ``hil.png``.
A scenario (``ground.hil.scenarios``: ``eclipse-exit``, ``moon-slew``) replaces the random target
with a planned slew past a bright body, in orbit, and the plot with the scenario's
(``ground.hil.scenario_report``); ``none`` is the plain demo.
"""

from __future__ import annotations

import importlib.util
from datetime import UTC

from ground.arg_types import InputError

#: The runs' default start (simulated time): 2026-12-01 00:00 UTC, a waning gibbous Moon, at which
#: both scenarios plan (docs/hil.md "Scenarios"); a fixed epoch, so a run is the same on any date.
DEFAULT_EPOCH_UTC = "2026-12-01T00:00:00"


def free_udp_port() -> int:
    """A UDP port on loopback that no one holds now (the attitude feed's)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_tcp_port() -> int:
    """A TCP port on loopback that no one holds now (the lockstep feed's)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def parse_epoch(text: str) -> float:
    """POSIX s of an ISO-8601 UTC time (``2026-12-01T00:00:00``, a trailing ``Z`` allowed);
    InputError (one line) for one that does not parse or lies outside 1990-2100."""
    from datetime import datetime

    try:
        dt = datetime.fromisoformat(text.strip().removesuffix("Z"))
    except ValueError:
        raise InputError(f"--epoch {text[:40]!r}: not an ISO-8601 UTC time (e.g. {DEFAULT_EPOCH_UTC})") from None
    if dt.tzinfo is not None and dt.utcoffset() != UTC.utcoffset(None):
        raise InputError(f"--epoch {text[:40]!r}: give UTC (no offset, or Z)")
    posix = dt.replace(tzinfo=UTC).timestamp()
    if not 631152000.0 <= posix < 4102444800.0:
        raise InputError(f"--epoch {text[:40]!r}: outside 1990-2100")
    return posix


def make_dynamics(kind: str, q0, w0, q_target, dt: float):
    """(dynamics, note): ``kind`` basilisk, standin or auto (Basilisk when installed)."""
    import numpy as np

    from ground.sim.hil_dynamics import BasiliskDynamics, StandInDynamics, gains

    inertia = np.diag([10.0, 9.0, 8.0])  # kg m^2: a small satellite
    k, p = gains(inertia, omega_n=0.3, zeta=0.9)
    have_bsk = importlib.util.find_spec("Basilisk") is not None
    if kind == "basilisk" and not have_bsk:
        raise InputError("--dynamics basilisk needs bsk: pip install 'colour-st16[hil]'")
    if kind == "basilisk" or (kind == "auto" and have_bsk):
        return BasiliskDynamics(inertia, q0, w0, q_target, k, p, dt), ""
    note = "" if kind == "standin" else " (bsk not installed: pip install 'colour-st16[hil]' for Basilisk)"
    return StandInDynamics(inertia, q0, w0, q_target, k, p), note


def run_hil(
    out,
    duration_s: float | None,
    dynamics_kind: str = "auto",
    seed: int = 15,
    progress: bool = True,
    scenario: str = "none",
    limits_deg: dict[str, float] | None = None,
    epoch_utc: str = DEFAULT_EPOCH_UTC,
    speed: float = 0.0,
    gyro_spec=None,
    tracker_off_after: float | None = None,
    read_heads: tuple[int, ...] | None = None,
) -> dict:
    """The closed loop of the module docstring; returns the summary (also written to ``out``).
    ``duration_s`` None: 30 s, or the scenario's own length; ``limits_deg`` a scenario's exclusion
    angles (default ``scenarios.LIMITS_DEG``); ``epoch_utc`` the simulated start; ``speed`` simulated
    s per real s (0: unpaced); ``gyro_spec`` the gyro class (``ground.sim.gyro.DEFAULT``);
    ``tracker_off_after`` s of simulated time after which the flight side gets no answer;
    ``read_heads`` the addresses the flight side reads in a scenario with heads (default all: the
    control run reads one)."""
    import json
    import tempfile
    from pathlib import Path

    import numpy as np
    from scipy.spatial.transform import Rotation

    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_to_image
    from firmware_model.reference_frames import matrix_to_quat, quat_to_matrix
    from ground.atomic_write import write_text
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.hil import scenarios
    from ground.link.client import Client
    from ground.sim.device_process import pick_attitudes, start_device, stop_device
    from ground.sim.gyro import DEFAULT, Gyro
    from ground.sim.hil_loop import MINIMAL_MASK, Head, run_closed_loop
    from protocol.commands import Slot

    start_posix = parse_epoch(epoch_utc)
    gyro_spec = DEFAULT if gyro_spec is None else gyro_spec
    Gyro(gyro_spec)  # a spec out of range: ValueError before anything starts
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    catalog = build_catalog(CatalogDesign())
    plan = None
    if scenario == "none":
        (a_target,) = pick_attitudes(catalog, CameraModel.reference_design(), 1, rng)
        axis = rng.normal(size=3)
        a0 = Rotation.from_rotvec(np.radians(4.0) * axis / np.linalg.norm(axis)).as_matrix() @ a_target
        q0, q_target, w0 = matrix_to_quat(a0), matrix_to_quat(a_target), np.radians([0.05, -0.05, 0.02])
        duration_s = 30.0 if duration_s is None else duration_s
    else:
        try:
            plan = scenarios.plan(scenario, start_posix, limits_deg)
        except ValueError as exc:
            raise InputError(f"--scenario {exc}") from None  # the reason starts with the name
        q0, w0 = plan.slew.target(0.0), np.zeros(3)
        duration_s = plan.duration_s if duration_s is None else duration_s
        q_target = plan.slew.target(duration_s)
        print(f"hil: scenario {scenario}, exclusion {plan.params()}", flush=True)
    dt = 0.02
    dynamics, note = make_dynamics(dynamics_kind, q0, w0, q_target, dt)
    print(f"hil: dynamics {dynamics.label}{note}", flush=True)
    url = f"tcp://127.0.0.1:{free_tcp_port()}?clock=sim"  # lockstep: the device on simulated time
    heads = [] if plan is None else [Head(a, quat_to_matrix(q)) for a, q in plan.heads]
    with tempfile.TemporaryDirectory() as state:
        bus: list[str] = []
        if heads:  # one device process, a head per address (st16-device --heads)
            heads_file = Path(state) / "heads.json"
            heads_file.write_text(
                json.dumps({"heads": [{"address": h.address, "mount_q": list(matrix_to_quat(h.mount))} for h in heads]})
            )
            bus = ["--heads", str(heads_file)]
        proc, pty = start_device(Path(state) / "device", *bus)  # the catalog goes up unpaced, persisted
        try:
            with Client(pty, timeout=5.0) as c:
                for address in [h.address for h in heads] or [c.device_address]:
                    c.device_address = address
                    c.init()
                    c.upload(0, catalog_to_image(catalog), progress=progress)
                    if plan is not None:
                        c.upload(Slot.PARAMS, json.dumps(plan.params()).encode(), progress=False)
        finally:
            stop_device(proc)
        # unpaced: a paced link stamps arrivals with the machine's clock, simulated time with the feed's
        proc, pty = start_device(Path(state) / "device", *bus, "--attitude-feed", url)
        try:
            with Client(pty, timeout=5.0) as c:
                for address in [h.address for h in heads] or [c.device_address]:
                    c.device_address = address
                    c.init()
                log = run_closed_loop(
                    dynamics,
                    c,
                    url,
                    q0,
                    w0,
                    q_target,
                    duration_s,
                    dt=dt,
                    progress=progress,
                    target_at=None if plan is None else plan.slew.target,
                    position_at=None if plan is None else plan.position_at,
                    start_posix=start_posix,
                    speed=speed,
                    gyro_spec=gyro_spec,
                    gyro_seed=seed,
                    tracker_off_after=tracker_off_after,
                    heads=[h for h in heads if read_heads is None or h.address in read_heads],
                )
        finally:
            stop_device(proc)
    rows = log.rows()
    write_text(out / "hil_log.jsonl", "".join(json.dumps(r) + "\n" for r in rows))
    summary = summarise(log, rows, duration_s, MINIMAL_MASK) | {
        "epoch_utc": epoch_utc,
        "speed": speed,
        "gyro": vars(gyro_spec) | {"class": "tactical FOG (LN-200 class; ground.sim.gyro)"},
        "tracker_off_after_s": tracker_off_after,
    }
    if plan is None:
        _plot(log, rows, out / "hil.png")
    else:
        summary |= plan.report(log, rows, out / "hil.png")
    write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary


def summarise(log, rows: list[dict], duration_s: float, mask: int) -> dict:
    """The run's figures: rates, latency, tracker vs truth, and the pointing error (truth to
    target) at the start, the end and 30, 60, 300 s; the acquisition time and the estimate's error."""
    import math

    import numpy as np

    from firmware_model.reference_frames import quat_to_matrix, rotation_angle

    ok = [r for r in rows if "latency_s" in r]
    lat = np.array([r["latency_s"] for r in ok]) * 1e3
    wall = np.array([u.wall_latency_s for u in log.updates if u.wall_latency_s is not None]) * 1e3
    err = np.array([r["measured_error_arcsec"] for r in ok])
    t0 = log.truth_t[0] if log.truth_t else 0.0

    def pointing(k: int) -> float:
        target = log.target_q[k] if log.target_q else log.q_target
        return math.degrees(rotation_angle(quat_to_matrix(log.truth_q[k]), quat_to_matrix(target)))

    at = {}
    for s in (30, 60, 300):
        k = int(np.searchsorted(log.truth_t, t0 + s - 1e-9))
        if k < len(log.truth_t):
            at[str(s)] = pointing(k)
    est_err = None
    if log.estimate_q and log.estimate_q[-1] is not None and log.truth_q:
        est_err = (
            math.degrees(rotation_angle(quat_to_matrix(log.estimate_q[-1]), quat_to_matrix(log.truth_q[-1]))) * 3600
        )
    oks = [u.received for u in log.updates if u.used]
    end = log.truth_t[-1] if log.truth_t else t0
    return {
        "dynamics": log.dynamics,
        "link": "pty, unpaced; lockstep in simulated time",
        "mask": f"0x{mask:04X}",
        "duration_s": duration_s,
        "updates": len(rows),
        "ok_updates": len(ok),
        "update_rate_hz": len(rows) / duration_s,
        "ok_rate_hz": len(ok) / duration_s,
        "latency_ms_p50": float(np.median(lat)) if ok else None,
        "latency_ms_p99": float(np.percentile(lat, 99)) if ok else None,
        "go_to_result_wall_ms_p50": float(np.median(wall)) if len(wall) else None,
        "go_to_result_wall_ms_p99": float(np.percentile(wall, 99)) if len(wall) else None,
        "measured_error_arcsec_p50": float(np.median(err)) if ok else None,
        "measured_error_arcsec_p99": float(np.percentile(err, 99)) if ok else None,
        "acquisition_s": None if log.first_fix_t is None else log.first_fix_t - t0,
        "last_fix_age_s": None if not oks else end - oks[-1],
        "estimate_error_arcsec_last": est_err,
        "pointing_error_deg_at": at,
        "pointing_error_deg_first": pointing(0) if log.truth_q else None,
        "pointing_error_deg_last": pointing(len(log.truth_q) - 1) if log.truth_q else None,
        "statuses": {s: sum(r["status"] == s for r in rows) for s in sorted({r["status"] for r in rows})},
    }


def _plot(log, rows: list[dict], path) -> None:
    import logging

    from ground.optional import MissingExtra, pyplot

    try:
        plt = pyplot()
    except MissingExtra as exc:
        logging.getLogger(__name__).warning("no plot: %s", exc)
        return
    import numpy as np

    from firmware_model.reference_frames import quat_to_matrix, rotation_angle

    ok = [r for r in rows if "latency_s" in r]
    t = np.array([r["t_mid"] for r in ok])
    target = quat_to_matrix(log.q_target)
    measured_to_target = [np.degrees(rotation_angle(quat_to_matrix(r["q_measured"]), target)) for r in ok]
    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    ax1.semilogy(t, [r["pointing_error_deg"] for r in ok], "-", label="truth")
    ax1.semilogy(t, measured_to_target, ".", ms=3, label="tracker")
    ax1.set_ylabel("attitude to target (deg)")
    ax1.set_title(f"HIL closed loop: {log.dynamics}", fontsize=9)
    ax1.legend(fontsize=8)
    ax2.plot(t, [r["measured_error_arcsec"] for r in ok], ".", ms=3)
    ax2.set_ylabel("tracker vs truth (arcsec)")
    for key, style, label in (("q_truth", "-", "truth"), ("q_measured", ".", "from successive tracker attitudes")):
        a = [quat_to_matrix(r[key]) for r in ok]
        rate = [np.degrees(rotation_angle(a[k], a[k - 1])) / (t[k] - t[k - 1]) for k in range(1, len(a))]
        ax3.plot(t[1:], rate, style, ms=3, label=label)
    ax3.set_ylabel("body rate (deg/s)")
    ax3.set_xlabel("exposure mid-time since start (s)")
    ax3.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
