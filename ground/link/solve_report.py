"""Decode a solve result (READ RESULT record) into what users read and log.

``solve_record(rec)`` returns the ``--json`` form of ``st16-ground solve``: status, the
quaternion ``q_icrs_to_sensor`` [w, x, y, z], boresight RA/Dec/roll in degrees
(docs/CONVENTIONS.md), detected and matched counts, the brightest detections the result holds
(pixel position, colour ratios; catalog id and residual when matched), attitude 1-sigma per sensor axis (arcsec), the time per
pipeline stage, and ``bodies_in_fov``: the bright bodies inside their exclusion angles
(``hardware.status`` bits 9-11, whatever the status). The same function serves offline runs through :func:`record_from_output`.
:func:`result_record` adds what READ RESULT carries besides (COSMOS bits, epoch, omega and its sigma, the
hardware section), :func:`combination_record` decodes the sections a COMBINATION returned (the
standard quaternion in the order the hardware section flags, docs/ICD.md section 10.2), and
:func:`format_record` renders any of these for people.
"""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np

from firmware_model.ident.solver import Method
from firmware_model.pipeline.result_fields import result_fields, star_entries
from firmware_model.pipeline.solve_types import STAGES, PipelineOutput
from firmware_model.reference_frames import quat_to_matrix, radec_roll_from_attitude
from protocol import result

ARCSEC = 180.0 / np.pi * 3600.0
#: Method name per ``ext.method`` code (``protocol.result.MethodCode``; 0: none).
METHODS = {int(result.MethodCode.NONE): "", **{int(m.code): str(m) for m in Method}}


def _num(v) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None


def _is_unit(q: np.ndarray) -> bool:
    """A quaternion that holds an attitude: finite and of unit norm (a zeroed one holds none)."""
    return bool(np.isfinite(q).all() and abs(np.linalg.norm(q) - 1) < 1e-6)


def _attitude(q: np.ndarray) -> dict:
    """``q_icrs_to_sensor`` and boresight RA/Dec/roll (deg) of the scalar-first unit quaternion ``q``."""
    ra, dec, roll = (float(np.degrees(v)) for v in radec_roll_from_attitude(quat_to_matrix(q)))
    return {"q_icrs_to_sensor": [float(v) for v in q], "ra_deg": ra, "dec_deg": dec, "roll_deg": roll}


def _body(flags: int) -> str | None:
    """The planet or moon a star's flags name (protocol.result.EXT_STAR), or None."""
    code = (flags >> 8) & 0xF
    return result.BODIES[code - 1] if flags & 4 and 1 <= code <= len(result.BODIES) else None


def _optics(ext) -> dict:
    """PSF and optics block of the extension (``None`` for values the device did not set)."""
    flags = int(ext["optics_flags"])
    fitted = bool(flags & result.OPTICS_FITTED)
    return {
        "psf_sigma_px": _num(ext["psf_sigma"]),
        "psf_measured": bool(flags & result.PSF_MEASURED),
        "focal_px": _num(ext["focal_px"]),
        "focal_sigma_px": _num(ext["focal_sigma"]) if fitted else None,
        "k1": _num(ext["k1"]),
        "k1_sigma": _num(ext["k1_sigma"]) if fitted else None,
        "fit_rms_px": _num(ext["optics_rms"]) if fitted else None,
        "fit_stars": int(ext["optics_stars"]) if fitted else 0,
        "fitted": fitted,
        "searched": bool(flags & result.OPTICS_SEARCHED),
        "focal_scale": _num(ext["focal_scale"]) if flags & result.OPTICS_SEARCHED else None,
    }


def _search(ext) -> dict:
    """The extension's search block: the frame's counted work and what stopped a search early."""
    flags = int(ext["search_flags"])
    return {
        "verifications": int(ext["verifications"]),
        "seeds": int(ext["seeds"]),
        "budget_reached": bool(flags & result.SEARCH_BUDGET_REACHED),
        "deadline_missed": bool(flags & result.DEADLINE_MISSED),
    }


def _star(s) -> dict:
    """One extension star entry (``protocol.result.EXT_STAR``) as the record lists it."""
    return {
        "x": _num(s["x"]),
        "y": _num(s["y"]),
        "flux": _num(s["flux"]),
        "rg": _num(s["rg"]),
        "bg": _num(s["bg"]),
        "rg_sigma": _num(s["rg_sigma"]),
        "bg_sigma": _num(s["bg_sigma"]),
        "catalog_id": int(s["catalog_id"]) if int(s["catalog_id"]) >= 0 else None,
        "residual_arcsec": _num(s["residual"] * ARCSEC) if int(s["flags"]) & 1 else None,
        "saturated": bool(int(s["flags"]) & 2),
        "body": _body(int(s["flags"])),
    }


def solve_record(rec: np.ndarray) -> dict:
    """JSON-ready dict of a parsed result record (protocol.result.RESULT)."""
    rc = int(rec["return_code"])
    st = result.status_of(rc)
    ext = rec["ext"]
    stars: list[dict] = []
    out = {
        "sequence": int(rec["sequence"]),
        "status": st.name if isinstance(st, result.Status) else f"UNKNOWN_{st}",
        "return_code": rc,
        "reason": bytes(ext["reason"]).rstrip(b"\0").decode("utf-8", "replace"),
        "method": METHODS.get(int(ext["method"]), ""),
        "n_detected": int(ext["n_detected"]),
        "n_matched": int(ext["n_matched"]),
        "q_icrs_to_sensor": None,
        "ra_deg": None,
        "dec_deg": None,
        "roll_deg": None,
        "sigma_arcsec": None,
        "residual_rms_arcsec": None,
        "timings_s": {name: float(t) for name, t in zip(STAGES, ext["stage_times"])},
        "optics": _optics(ext),
        "search": _search(ext),
        "n_planets": int(ext["n_planets"]),
        "bodies_in_fov": result.bodies_in_fov(int(rec["hardware"]["status"])),
        "stars": stars,
    }
    q = np.asarray(ext["quaternion"], dtype=float)
    if rc & result.ReturnBits.IMAGE1_SUCCESS and _is_unit(q):
        out.update(
            _attitude(q),
            sigma_arcsec=[float(s * ARCSEC) for s in ext["sigma"]],
            residual_rms_arcsec=_num(ext["residual_rms"] * ARCSEC),
        )
    stars.extend(_star(s) for s in ext["stars"][: int(ext["n_reported"])])
    return out


def record_from_output(out: PipelineOutput, sequence: int = 0, every_star: bool = False) -> dict:
    """The same dict for an in-process pipeline run (offline replay); its ``timings_s`` are the
    run's own (``StageTimings.to_dict``: full precision, with the set-up stages such as the
    pattern index that the wire's six leave out). Its ``stars`` are the result record's, the
    :data:`protocol.result.EXT_MAX_STARS` brightest detections, as a device would report them;
    with ``every_star`` every detection (``solve-file``, ``solve_image``: no record in between),
    so that the matched ones among them are ``n_matched``."""
    fields = result_fields(out)
    fields["ext.reason"] = out.reason.encode()[: result.EXT_REASON_BYTES]
    rec = solve_record(result.parse(result.build(fields, sequence)))
    rec["timings_s"] = out.timings.to_dict()
    rest = len(out.stars) - result.EXT_MAX_STARS if out.stars is not None else 0
    if every_star and rest > 0:
        rec["stars"].extend(_star(s) for s in star_entries(out, result.EXT_MAX_STARS, rest))
    return rec


def add_setup_stages(rec: dict, **seconds: float) -> dict:
    """``rec`` with the set-up seconds a solve waited for before its frame (``catalog``: building
    or loading the catalog, ``compile``: loading or compiling the kernels; ``run.SETUP_STAGES``)
    added to its ``timings_s`` and to their ``total``, which is then the whole time waited."""
    timings = rec["timings_s"]
    for name, value in seconds.items():
        if value > 0:
            timings[name] = timings.get(name, 0.0) + value
            timings["total"] = timings.get("total", 0.0) + value
    return rec


def standard_quaternion(rec: np.ndarray) -> np.ndarray:
    """Scalar-first ``[w, x, y, z]`` of the standard structure's ``quaternion``, read in the order
    ``hardware.status`` flags (the device parameter ``quaternion_order``)."""
    return result.QuaternionOrder.of_hardware_status(int(rec["hardware"]["status"])).from_wire(rec["quaternion"])


def hardware_record(rec: np.ndarray) -> dict:
    """The hardware section: temperatures in degC as COSMOS converts them, the status mirrored
    into ``hardware.status`` and the order of the standard quaternions."""
    hw = rec["hardware"]
    word = int(hw["status"])
    st = result.status_of((word & result.HW_STATUS_MIRROR) << 8)
    return {
        "detector_temp_c": result.detector_temp_c(int(hw["detector_temp_raw"])),
        "processor_temp_c": result.processor_temp_c(int(hw["processor_temp_raw"])),
        "status": st.name if isinstance(st, result.Status) else f"UNKNOWN_{st}",
        "quaternion_order": result.QuaternionOrder.of_hardware_status(word).value,
    }


def _standard_attitude(rec: np.ndarray, order_known: bool) -> dict:
    """``q_icrs_to_sensor`` and boresight RA/Dec/roll (deg) from the quaternion section: None when
    it is not a unit quaternion (no attitude, whatever the order); the numbers as sent
    (``quaternion_wire``) when the hardware section that flags the order is missing."""
    wire = np.asarray(rec["quaternion"], dtype=float)
    if not _is_unit(wire):
        return {"q_icrs_to_sensor": None}
    if not order_known:
        return {"q_icrs_to_sensor": None, "quaternion_wire": [float(v) for v in wire]}
    return _attitude(standard_quaternion(rec))


def utc_iso(epoch_s: float) -> str | None:
    """ISO-8601 UTC time of POSIX seconds (ms resolution); None for 0 (not set) or out of range."""
    if not (np.isfinite(epoch_s) and 0 < epoch_s < 253402300800):  # year 10000
        return None
    return datetime.fromtimestamp(epoch_s, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _header(rec: np.ndarray) -> dict:
    rc = int(rec["return_code"])
    return {
        "bits": [b.name for b in result.ReturnBits if rc & b],
        "epoch": float(rec["epoch"]),
        "utc_epoch": float(rec["ext"]["utc_epoch"]),
        "epoch_utc": utc_iso(float(rec["ext"]["utc_epoch"])),
        "omega_rad_s": [float(v) for v in rec["omega"]],
        "omega_sigma_rad_s": [float(np.sqrt(max(v, 0.0))) for v in rec["ext"]["omega_covariance"][:3]],
        "hardware": hardware_record(rec),
    }


def result_record(rec: np.ndarray) -> dict:
    """:func:`solve_record` plus the COSMOS return bits, the epoch (device clock s; ``utc_epoch``
    POSIX s and ``epoch_utc`` ISO UTC of the same instant), omega and
    its 1-sigma per axis (rad/s; the sigma from ``ext.omega_covariance``, 0 when not tracking)."""
    return {**solve_record(rec), **_header(rec)}


#: Keys of :func:`result_record` decoded from each COMBINATION section (by its result address).
_SECTION_KEYS = {
    0x000: ("sequence",),
    0x004: ("return_code", "status", "bits"),
    0x028: ("omega_rad_s",),
    0x040: ("epoch",),
    0x048: ("hardware", "bodies_in_fov"),
    result.EXT_OFFSET: (
        "utc_epoch",
        "epoch_utc",
        "omega_sigma_rad_s",
        "reason",
        "method",
        "n_detected",
        "n_matched",
        "sigma_arcsec",
        "residual_rms_arcsec",
        "timings_s",
        "optics",
        "n_planets",
        "stars",
    ),
}


def combination_record(parts: dict[int, bytes]) -> dict:
    """Readable fields of the result sections a COMBINATION returned (result address -> bytes):
    those of :func:`result_record` that the sections hold, the attitude from the quaternion section
    (``q_icrs_to_sensor``, boresight RA/Dec/roll in degrees) when the hardware section says its
    order (else ``quaternion_wire``, the four numbers as sent, and ``q_icrs_to_sensor`` None), the
    matching section's consensus, and the hex of the sections not decoded (``raw``, by address)."""
    buf = bytearray(result.TOTAL_LENGTH)
    for address, data in parts.items():
        buf[address : address + len(data)] = data
    rec = result.parse(bytes(buf))
    full = result_record(rec)
    out: dict = {}
    for address in sorted(parts):
        if address in _SECTION_KEYS:
            out.update({k: full[k] for k in _SECTION_KEYS[address]})
        elif address == 0x008:
            out.update(_standard_attitude(rec, order_known=0x048 in parts))
        elif address == 0x7E8:
            m = rec["matching"][0]
            out["matching"] = {
                "consensus_size": int(m["consensus_size"]),
                "confidence": _num(m["confidence"]),
                "matched_stars": [int(i) for i in m["matched_stars"] if i >= 0],
            }
        else:
            out.setdefault("raw", {})[f"0x{address:04X}"] = parts[address].hex()
    return out


def _optics_line(o: dict) -> str:
    psf = "PSF sigma " + (
        "-"
        if o["psf_sigma_px"] is None
        else f"{o['psf_sigma_px']:.2f} px ({'measured' if o['psf_measured'] else 'set'})"
    )
    if not o["fitted"]:
        return f"optics: {psf}; focal {o['focal_px'] or float('nan'):.1f} px (nominal, not fitted)"
    k1 = f"k1 {o['k1']:+.4f}" + (f" +- {o['k1_sigma']:.4f}" if o["k1_sigma"] is not None else " (held)")
    found = f", found at focal scale {o['focal_scale']:.2f}" if o["searched"] else ""
    return (
        f"optics: {psf}; focal {o['focal_px']:.1f} +- {o['focal_sigma_px']:.1f} px, {k1} "
        f"(fitted over {o['fit_stars']} stars, RMS {o['fit_rms_px']:.3f} px{found})"
    )


def _listed(rec: dict) -> str:
    """What the star list below holds when it is not every detection (a result record holds the
    :data:`protocol.result.EXT_MAX_STARS` brightest): how many it lists and how many of those matched."""
    stars = rec.get("stars")
    if stars is None or len(stars) >= rec["n_detected"]:
        return ""
    listed = sum(s["catalog_id"] is not None for s in stars)
    return (
        f"; the result lists the {len(stars)} brightest detections, {listed} of them matched "
        f"(a result record holds {result.EXT_MAX_STARS})"
    )


def format_record(rec: dict) -> str:
    """Lines for people from a :func:`solve_record`, :func:`result_record` or :func:`combination_record`
    (only the fields present are shown)."""
    lines = []
    if "status" in rec:
        lines.append(
            f"status {rec['status']}"
            + (f" ({rec['reason']})" if rec.get("reason") else "")
            + (f", method {rec['method']}" if rec.get("method") else "")
        )
    if "bits" in rec:
        lines.append(f"return code 0x{rec['return_code']:04X}: {', '.join(rec['bits']) or 'no bits set'}")
    if "sequence" in rec or "epoch" in rec:
        lines.append(
            ", ".join(
                ([f"sequence {rec['sequence']}"] if "sequence" in rec else [])
                + ([f"epoch {rec['epoch_utc'] or 'not set'} UTC"] if "epoch" in rec else [])
            )
        )
    if rec.get("bodies_in_fov"):
        lines.append(f"inside their exclusion angles: {', '.join(rec['bodies_in_fov'])}")
    if rec.get("q_icrs_to_sensor") is not None:
        q = rec["q_icrs_to_sensor"]
        lines.append(f"q_icrs_to_sensor [w x y z] = [{q[0]:+.9f} {q[1]:+.9f} {q[2]:+.9f} {q[3]:+.9f}]")
        sigma = rec.get("sigma_arcsec")
        lines.append(
            f"boresight RA {rec['ra_deg']:.5f} deg, Dec {rec['dec_deg']:+.5f} deg, roll {rec['roll_deg']:.4f} deg"
            + (f"; 1-sigma x/y/z {', '.join(f'{s:.2f}' for s in sigma)} arcsec" if sigma else "")
        )
    elif "quaternion_wire" in rec:
        q = rec["quaternion_wire"]
        lines.append(
            f"quaternion as sent = [{q[0]:+.9f} {q[1]:+.9f} {q[2]:+.9f} {q[3]:+.9f}], "
            "order unknown: request the hardware section (0x0020) too"
        )
    elif "q_icrs_to_sensor" in rec:
        lines.append("no attitude")
    if "hardware" in rec:
        h = rec["hardware"]
        lines.append(
            f"hardware: detector {h['detector_temp_c']:.1f} degC, processor {h['processor_temp_c']:.1f} degC, "
            f"status {h['status']}, standard quaternions {h['quaternion_order']}"
        )
    if "omega_rad_s" in rec:
        sigma = rec.get("omega_sigma_rad_s") or [0.0]
        spread = " +- [" + " ".join(f"{s:.1e}" for s in sigma) + "]" if any(sigma) else ""
        lines.append("omega [x y z] = [" + " ".join(f"{w:+.3e}" for w in rec["omega_rad_s"]) + f"]{spread} rad/s")
    if "n_detected" in rec:
        lines.append(f"detected {rec['n_detected']}, matched {rec['n_matched']}" + _listed(rec))
    if "matching" in rec:
        m = rec["matching"]
        lines.append(
            f"matching: consensus of {m['consensus_size']}, confidence {m['confidence']}, "
            f"catalog ids {m['matched_stars']}"
        )
    if rec.get("optics") and rec["optics"]["psf_sigma_px"] != 0:  # 0: a zeroed record, nothing measured
        lines.append(_optics_line(rec["optics"]))
    search = rec.get("search")
    if search and (search["budget_reached"] or search["deadline_missed"]):
        stopped = "the flight-timing deadline" if search["deadline_missed"] else "its counted budget"
        lines.append(
            f"search: stopped by {stopped} after {search['seeds']} seeds and {search['verifications']} "
            "verifications (the parameter file's max_seeds, max_frame_verifications and max_verifications "
            "raise the budgets)"
        )
    for s in rec.get("stars", []):
        if s.get("body"):
            lines.append(
                f"  on {s['body']}: x {s['x']:8.2f}  y {s['y']:8.2f} "
                "(predicted at the frame's epoch; not used as a star)"
            )
    for s in rec.get("stars", []):
        if s["catalog_id"] is not None:
            colour = f" rg {s['rg']:.3f} bg {s['bg']:.3f}" if s["rg"] is not None else ""
            lines.append(
                f"  id {s['catalog_id']:>7}  x {s['x']:8.2f}  y {s['y']:8.2f}{colour}  "
                f'residual {s["residual_arcsec"]:.2f}"'
            )
    if "timings_s" in rec:
        lines.append("time per stage (ms): " + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in rec["timings_s"].items()))
    for address, hex_ in rec.get("raw", {}).items():
        lines.append(f"section at {address} ({len(hex_) // 2} bytes, not decoded): {hex_}")
    if "attitude_error_deg" in rec:
        lines.append(f"attitude error vs truth: {rec['attitude_error_deg'] * 3600:.2f} arcsec ({rec['outcome']})")
    return "\n".join(lines)


def matched_stars(record: dict) -> list[dict]:
    return [s for s in record["stars"] if s["catalog_id"] is not None]
