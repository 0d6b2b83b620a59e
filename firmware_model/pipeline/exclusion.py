"""Bright-body exclusion: no attitude while the Sun, the Earth's bright limb or the Moon is inside
its exclusion angle of the boresight, and BLINDED for a blinded image that no attitude explains
(docs/pipeline.md, "Bright-body exclusion"; docs/ICD.md sections 7, 9 and 10).

:func:`check_exclusion` runs on every answer of a frame (``run.run_pipeline``, the tracked ones of
``tracking_run.Tracker``). It judges by the frame's own solved attitude (any confidence) when it
has one, else by a :class:`Recall` the device gives (its last reported attitude, propagated to the
frame's time, when younger than ``ExclusionLimits.memory_s``), else by none. With an attitude
and the frame's ``timestamp`` (UTC; the bodies' ephemerides at that time, ``sky_bodies``) the
angle from the boresight to each body's disc edge (``SkyBody.edge_angle``) is compared with its
limit; the Earth is checked only when the frame carries the spacecraft's GCRS position
(``metadata["sc_position_km"]``, km). Every body inside is flagged (``PipelineOutput.in_fov``,
``hardware.status`` bits 9-11); the status names the first in :data:`protocol.result.EXCLUDED_BODIES`
order (the Sun, then the Earth, then the Moon), the attitude is dropped and the reason says which
attitude decided. A frame without a timestamp cannot be checked: the reason says so when a limit
is set and an attitude exists, and the answer stands.

Without an attitude of its own, a blinded frame (:func:`blinded`: counted statistics of its
pixels) that no attitude puts near a body gets BLINDED; any other failure keeps its status.

Defaults (:class:`ExclusionLimits`): the Sun 30 deg and the Moon 25 deg are the exclusion angles
the Terma HE-5AS star tracker's baffle was designed to on CryoSat (ESA, CryoSat instrument
description, in the GCMD "Star Tracker" concept:
https://gcmd.earthdata.nasa.gov/kms/concept/2380ecc6-b5ae-4ad8-a56a-9740166465aa). The Earth's
25 deg from its bright limb is an assumption (no public ST-16 figure found; the Arcsecond Pico
Star Tracker's baffle has a 27 deg exclusion angle, Muruganandan et al. 2017, Trans. JSASS 60(6)
355-365). The memory's 10 s is an assumption: long enough to bridge a few frames lost to glare at
the device's cadence, short enough that an attitude held without a rate is still near the truth
in inertial pointing. The blinded thresholds (:data:`BLIND_SATURATED_FRACTION`,
:data:`BLIND_BACKGROUND_FRACTION`) are assumptions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from firmware_model.pipeline.raw_frame import Frame
from firmware_model.reference_frames import matrix_to_quat, quat_to_matrix
from protocol.result import EXCLUDED_BODIES, Status

#: A frame is blinded when at least this fraction of its pixels is at the white level (assumption:
#: "most of the array").
BLIND_SATURATED_FRACTION = 0.5
#: ... or when its median pixel above black is at least this fraction of the full scale (white
#: level minus black level; assumption: a background near full scale leaves no star above it).
BLIND_BACKGROUND_FRACTION = 0.8

#: The statuses of a body inside its exclusion angle, by body.
STATUS_OF = {"sun": Status.SUN_IN_FOV, "earth": Status.EARTH_IN_FOV, "moon": Status.MOON_IN_FOV}


@dataclass(frozen=True)
class ExclusionLimits:
    """Exclusion angles (deg, 0 to 90; 0 turns that body's check off) from the boresight to the
    disc edge of the Sun, the Moon and the Earth's bright limb (``sky_bodies.ATMOSPHERE_KM`` above
    the surface), and ``memory_s`` (s, 0 to 3600; 0: none) the age up to which the device's last
    attitude stands in for a frame without its own. Defaults: module docstring."""

    sun_deg: float = 30.0
    moon_deg: float = 25.0
    earth_deg: float = 25.0
    memory_s: float = 10.0

    def limit_deg(self, body: str) -> float:
        """The exclusion angle of ``body`` (deg)."""
        return float(getattr(self, f"{body}_deg"))

    @property
    def any_on(self) -> bool:
        return any(self.limit_deg(b) > 0 for b in EXCLUDED_BODIES)


@dataclass(frozen=True)
class LastAttitude:
    """The last attitude the device reported: ``q`` (scalar-first ``q_icrs_to_sensor``) at ``t``
    (s, the frame's mid-exposure time) and the tracker's rate ``omega`` (rad/s, sensor axes) when
    known."""

    q: np.ndarray
    t: float
    omega: np.ndarray | None = None

    def recall(self, t: float, memory_s: float) -> Recall | None:
        """This attitude at ``t`` (s), turned at ``omega`` when known (``A(t) = R(-omega dt) A``,
        ``ident.tracking``'s kinematics), or None when it is older than ``memory_s`` or from a
        later frame."""
        age = float(t) - self.t
        if not 0.0 <= age <= memory_s:
            return None
        a = quat_to_matrix(self.q)
        if self.omega is not None:
            a = Rotation.from_rotvec(-np.asarray(self.omega, float) * age).as_matrix() @ a
        return Recall(matrix_to_quat(a), age)


@dataclass(frozen=True)
class Recall:
    """An attitude remembered for a frame: ``q`` (scalar-first ``q_icrs_to_sensor``) at the frame's
    time and its ``age_s`` (s)."""

    q: np.ndarray
    age_s: float


def blinded(frame: Frame) -> str | None:
    """Why ``frame`` is blinded (its saturated fraction, or its median level over the full
    scale, past :data:`BLIND_SATURATED_FRACTION` / :data:`BLIND_BACKGROUND_FRACTION`), or None."""
    saturated = float(np.count_nonzero(frame.saturated_mask())) / frame.pixels.size
    black = float(np.mean(frame.black_level))
    level = (float(np.median(frame.pixels)) - black) / (frame.white_level - black)
    if saturated >= BLIND_SATURATED_FRACTION:
        return f"blinded: {100 * saturated:.0f} % of the pixels saturated"
    if level >= BLIND_BACKGROUND_FRACTION:
        return f"blinded: background at {100 * level:.0f} % of full scale"
    return None


def _sc_position(frame: Frame):
    """The spacecraft's GCRS position (km) the frame carries, or None."""
    pos = (frame.metadata or {}).get("sc_position_km")
    return None if pos is None else np.asarray(pos, dtype=float).reshape(3)


def _mid_time(frame: Frame):
    """The frame's time: its ``timestamp`` (the exposure's start) plus half the exposure
    (docs/CONVENTIONS.md), as astropy Time."""
    from astropy import units as u

    from firmware_model.pipeline.planets import _as_time

    return _as_time(frame.timestamp) + 0.5 * (frame.exposure_s or 0.0) * u.s


def bodies_inside(q, frame: Frame, limits: ExclusionLimits) -> list[tuple[str, float, float]]:
    """``(body, edge angle deg, limit deg)`` of every body inside its limit for the attitude ``q``
    at the frame's (mid-exposure) time, in :data:`protocol.result.EXCLUDED_BODIES` order; ValueError when the
    frame's time or position cannot be read."""
    from firmware_model.pipeline.sky_bodies import sky_bodies

    try:
        bodies = sky_bodies(_mid_time(frame), _sc_position(frame))
    except (TypeError, ValueError) as exc:
        raise ValueError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    boresight = quat_to_matrix(q)[2]  # sensor +z in ICRS axes
    found = []
    for name in EXCLUDED_BODIES:
        limit = limits.limit_deg(name)
        if name in bodies and limit > 0:
            edge = math.degrees(bodies[name].edge_angle(boresight))
            if edge < limit:
                found.append((name, edge, limit))
    return found


def _joined(*parts: str) -> str:
    return "; ".join(p for p in parts if p)


def check_exclusion(out, frame: Frame, limits: ExclusionLimits | None, recall: Recall | None = None):
    """``out`` (a ``solve_types.PipelineOutput`` of ``frame``) after the exclusion check (module docstring):
    a body inside its limit turns it into SUN_IN_FOV / EARTH_IN_FOV / MOON_IN_FOV without an
    attitude; a blinded frame without an attitude into BLINDED. ``limits`` None: no check;
    ``recall``: the device's remembered attitude at this frame's time."""
    if limits is None or out.status is Status.BAD_FRAME:
        return out
    sol = out.solution
    q = sol.q_icrs_to_sensor if sol is not None else None
    by = "by the solved attitude"
    if q is None and recall is not None and recall.age_s <= limits.memory_s:
        q, by = recall.q, f"by the last attitude, {recall.age_s:.1f} s old"
    inside: list[tuple[str, float, float]] = []
    if q is not None and limits.any_on:
        if not frame.timestamp:
            out.reason = _joined(out.reason, "bright bodies not checked: the frame has no timestamp")
        else:
            try:
                inside = bodies_inside(q, frame, limits)
            except ValueError as exc:
                out.reason = _joined(out.reason, f"bright bodies not checked: {exc}")
    out.in_fov = tuple(name for name, _, _ in inside)
    if inside:
        name, edge, limit = inside[0]
        also = f"; also {', '.join(out.in_fov[1:])}" if len(inside) > 1 else ""  # last: the 96 bytes may cut it
        out.status = STATUS_OF[name]
        out.reason = (
            f"{name} {max(edge, 0.0):.1f} deg from the boresight, inside its {limit:g} deg exclusion, {by}{also}"
        )
        out.solution = None
        out.omega = out.omega_covariance = None
        out.planets = []
        return out
    if (sol is None or sol.q_icrs_to_sensor is None) and (why := blinded(frame)) is not None:
        out.status = Status.BLINDED
        out.reason = _joined(why, f"no bright body inside its exclusion {by}" if q is not None else "")
    return out
