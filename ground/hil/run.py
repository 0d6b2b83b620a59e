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

from ground.arg_types import InputError


def free_udp_port() -> int:
    """A UDP port on loopback that no one holds now (the attitude feed's)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
) -> dict:
    """The closed loop of the module docstring; returns the summary (also written to ``out``).
    ``duration_s`` None: 30 s, or the scenario's own length; ``limits_deg`` a scenario's exclusion
    angles (default ``scenarios.LIMITS_DEG``)."""
    import json
    import tempfile
    import time
    from pathlib import Path

    import numpy as np
    from scipy.spatial.transform import Rotation

    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_to_image
    from firmware_model.reference_frames import matrix_to_quat
    from ground.atomic_write import write_text
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.hil import scenario_report, scenarios
    from ground.link.client import Client
    from ground.sim.device_process import pick_attitudes, start_device, stop_device
    from ground.sim.hil_loop import MINIMAL_MASK, run_closed_loop
    from protocol.commands import Slot

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
            plan = scenarios.plan(scenario, time.time(), limits_deg)
        except ValueError as exc:
            raise InputError(f"--scenario {exc}") from None  # the reason starts with the name
        q0, w0 = plan.slew.target(0.0), np.zeros(3)
        duration_s = plan.duration_s if duration_s is None else duration_s
        q_target = plan.slew.target(duration_s)
        print(f"hil: scenario {scenario}, exclusion {plan.params()}", flush=True)
    dt = 0.02
    dynamics, note = make_dynamics(dynamics_kind, q0, w0, q_target, dt)
    print(f"hil: dynamics {dynamics.label}{note}", flush=True)
    url = f"udp://127.0.0.1:{free_udp_port()}"
    with tempfile.TemporaryDirectory() as state:
        proc, pty = start_device(Path(state))  # the catalog goes up unpaced, persisted in the state
        try:
            with Client(pty, timeout=5.0) as c:
                c.init()
                c.upload(0, catalog_to_image(catalog), progress=progress)
                if plan is not None:
                    c.upload(Slot.PARAMS, json.dumps(plan.params()).encode(), progress=False)
        finally:
            stop_device(proc)
        proc, pty = start_device(Path(state), "--pace", "--baud", "115200", "--attitude-feed", url)
        try:
            with Client(pty, timeout=5.0) as c:
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
                    position_at=None if plan is None else plan.position_km,
                )
        finally:
            stop_device(proc)
    rows = log.rows()
    write_text(out / "hil_log.jsonl", "".join(json.dumps(r) + "\n" for r in rows))
    summary = summarise(log, rows, duration_s, MINIMAL_MASK)
    if plan is None:
        _plot(log, rows, out / "hil.png")
    else:
        tr = scenario_report.track(log)
        summary |= scenario_report.summarise_scenario(plan, log, rows, tr)
        scenario_report.plot_scenario(plan, log, rows, tr, out / "hil.png")
    write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary


def summarise(log, rows: list[dict], duration_s: float, mask: int) -> dict:
    import numpy as np

    ok = [r for r in rows if "latency_s" in r]
    lat = np.array([r["latency_s"] for r in ok]) * 1e3
    err = np.array([r["measured_error_arcsec"] for r in ok])
    pointing = [r["pointing_error_deg"] for r in ok]
    return {
        "dynamics": log.dynamics,
        "link": "pty paced at 115200 baud",
        "mask": f"0x{mask:04X}",
        "duration_s": duration_s,
        "updates": len(rows),
        "ok_updates": len(ok),
        "update_rate_hz": len(rows) / duration_s,
        "ok_rate_hz": len(ok) / duration_s,
        "latency_ms_p50": float(np.median(lat)) if ok else None,
        "latency_ms_p99": float(np.percentile(lat, 99)) if ok else None,
        "measured_error_arcsec_p50": float(np.median(err)) if ok else None,
        "measured_error_arcsec_p99": float(np.percentile(err, 99)) if ok else None,
        "pointing_error_deg_first": pointing[0] if ok else None,
        "pointing_error_deg_last": pointing[-1] if ok else None,
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
