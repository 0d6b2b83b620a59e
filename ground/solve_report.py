"""Decode a solve result (READ RESULT record) into what users read and log.

``solve_record(rec)`` returns the ``--json`` form of ``st16-ground solve``: status, the
quaternion ``q_icrs_to_sensor`` [w, x, y, z], boresight RA/Dec/roll in degrees
(docs/CONVENTIONS.md), detected and matched counts, the matched stars (catalog id, pixel
position, colour ratios, residual), attitude 1-sigma per sensor axis (arcsec), and the time per
pipeline stage. The same function serves offline runs through :func:`record_from_output`.
"""

from __future__ import annotations

import numpy as np

from firmware_model.frames import quat_to_matrix, radec_roll_from_attitude
from firmware_model.pipeline import METHOD_CODES, STAGES, PipelineOutput, result_fields
from protocol import result

ARCSEC = 180.0 / np.pi * 3600.0
METHODS = {0: "", **{code: name for name, code in METHOD_CODES.items()}}


def _num(v) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None


def _body(flags: int) -> str | None:
    """The planet or moon a star's flags name (protocol.result.EXT_STAR), or None."""
    code = (flags >> 8) & 0xF
    return result.BODIES[code - 1] if flags & 4 and 1 <= code <= len(result.BODIES) else None


def _optics(ext) -> dict:
    """PSF and optics block of the extension (``None`` for values the device did not set)."""
    flags = int(ext["optics_flags"])
    fitted = bool(flags & result.OPTICS_FITTED)
    return {
        "psf_sigma_px": _num(ext["psf_sigma"]), "psf_measured": bool(flags & result.PSF_MEASURED),
        "focal_px": _num(ext["focal_px"]), "focal_sigma_px": _num(ext["focal_sigma"]) if fitted else None,
        "k1": _num(ext["k1"]), "k1_sigma": _num(ext["k1_sigma"]) if fitted else None,
        "fit_rms_px": _num(ext["optics_rms"]) if fitted else None,
        "fit_stars": int(ext["optics_stars"]) if fitted else 0, "fitted": fitted,
        "searched": bool(flags & result.OPTICS_SEARCHED),
        "focal_scale": _num(ext["focal_scale"]) if flags & result.OPTICS_SEARCHED else None,
    }


def solve_record(rec: np.ndarray) -> dict:
    """JSON-ready dict of a parsed result record (protocol.result.RESULT)."""
    rc = int(rec["return_code"])
    st = result.status_of(rc)
    ext = rec["ext"]
    out = {
        "sequence": int(rec["sequence"]),
        "status": st.name if isinstance(st, result.Status) else f"UNKNOWN_{st}",
        "return_code": rc,
        "reason": bytes(ext["reason"]).rstrip(b"\0").decode("utf-8", "replace"),
        "method": METHODS.get(int(ext["method"]), ""),
        "n_detected": int(ext["n_detected"]),
        "n_matched": int(ext["n_matched"]),
        "q_icrs_to_sensor": None, "ra_deg": None, "dec_deg": None, "roll_deg": None,
        "sigma_arcsec": None, "residual_rms_arcsec": None,
        "timings_s": {name: float(t) for name, t in zip(STAGES, ext["stage_times"])},
        "optics": _optics(ext),
        "n_planets": int(ext["n_planets"]),
        "stars": [],
    }
    q = np.asarray(ext["quaternion"], dtype=float)
    if rc & result.ReturnBits.IMAGE1_SUCCESS and np.isfinite(q).all() and abs(np.linalg.norm(q) - 1) < 1e-6:
        ra, dec, roll = radec_roll_from_attitude(quat_to_matrix(q))
        out.update(q_icrs_to_sensor=[float(v) for v in q], ra_deg=float(np.degrees(ra)),
                   dec_deg=float(np.degrees(dec)), roll_deg=float(np.degrees(roll)),
                   sigma_arcsec=[float(s * ARCSEC) for s in ext["sigma"]],
                   residual_rms_arcsec=_num(ext["residual_rms"] * ARCSEC))
    for s in ext["stars"][: int(ext["n_reported"])]:
        out["stars"].append({
            "x": _num(s["x"]), "y": _num(s["y"]), "flux": _num(s["flux"]), "rg": _num(s["rg"]), "bg": _num(s["bg"]),
            "catalog_id": int(s["catalog_id"]) if int(s["catalog_id"]) >= 0 else None,
            "residual_arcsec": _num(s["residual"] * ARCSEC) if int(s["flags"]) & 1 else None,
            "saturated": bool(int(s["flags"]) & 2),
            "body": _body(int(s["flags"])),
        })
    return out


def record_from_output(out: PipelineOutput, sequence: int = 0) -> dict:
    """The same dict for an in-process pipeline run (offline replay)."""
    fields = result_fields(out)
    fields["ext.reason"] = out.reason.encode()[: result.EXT_REASON_BYTES]
    return solve_record(result.parse(result.build(fields, sequence)))


def matched_stars(record: dict) -> list[dict]:
    return [s for s in record["stars"] if s["catalog_id"] is not None]
