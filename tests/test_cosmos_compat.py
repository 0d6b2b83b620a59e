"""The result as the public COSMOS driver reads it (docs/ICD.md section 10.2): the quaternion order
parameter end to end, return-code bits 0-7 per condition, the status mirrored where a byte-wide
reader sees it, and hardware temperatures COSMOS converts to plausible values."""

import functools
import json
import struct
import threading

import guards
import numpy as np
import pytest

from firmware_model.camera import CameraModel
from firmware_model.device.cli import build_device, build_parser
from firmware_model.device.cli import main as device_main
from firmware_model.device.cosmos_compat import finish
from firmware_model.device.device import Device
from firmware_model.device.housekeeping import Housekeeping
from firmware_model.device.link import PtyLink, serve
from firmware_model.device.sensor_input import REJECT_PARAMS_VALUE, DeviceParams
from firmware_model.ident.consensus import Outcome
from firmware_model.ident.solver import SolveResult
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.result_fields import result_fields, return_bits
from firmware_model.pipeline.run import run_pipeline
from firmware_model.pipeline.solve_types import PipelineOutput, PipelineParams
from firmware_model.reference_frames import attitude_from_radec_roll, matrix_to_quat, quat_to_matrix
from ground.cli.main import main as ground_main
from ground.link.client import Client
from ground.link.solve_report import combination_record, format_record, hardware_record, standard_quaternion
from protocol import nsp, result, slip
from protocol.commands import APP_START_ADDRESS, Code, Go, Init, SlotRejected, XferBegin, XferData
from protocol.crc import crc32
from protocol.result import QuaternionOrder, ReturnBits, Status

ORDERS = list(QuaternionOrder)
Q = matrix_to_quat(attitude_from_radec_roll(*np.radians([83.8, -5.4, 10.0])))  # scalar first
HW = result.SECTIONS[0x0020][0]  # 0x048
RC_BYTE = 0x004  # the return code's low byte: what a reader keeping it in a char sees
STATUS_BYTE = HW + 0x10  # low byte of hardware.status
CAMERA = CameraModel.reference_design()


def _device_bytes(fields: dict, order: QuaternionOrder) -> bytes:
    return result.build(finish(fields, order), sequence=1)


# ------------------------------------------------------------------ quaternion order


@pytest.mark.parametrize("order", ORDERS)
def test_both_orders_round_trip_through_build_and_decode(order):
    fields = {
        "return_code": result.make_return_code(Status.OK, ReturnBits.CONSISTENT_SOLUTION),
        "quaternion": Q,
        "matching.0.quaternion": Q,
        "ext.quaternion": Q,
    }
    rec = result.parse(_device_bytes(fields, order))
    wire = [*Q[1:], Q[0]] if order is QuaternionOrder.SCALAR_LAST else list(Q)
    assert list(rec["quaternion"]) == wire and list(rec["matching"][0]["quaternion"]) == wire
    assert list(rec["ext"]["quaternion"]) == list(Q)  # the extension stays scalar first
    assert np.array_equal(standard_quaternion(rec), Q)
    assert hardware_record(rec)["quaternion_order"] == order.value
    assert np.array_equal(order.from_wire(order.to_wire(Q)), Q)


@pytest.mark.parametrize("order", ORDERS)
def test_combination_decodes_the_attitude_only_when_the_order_is_known(order):
    data = _device_bytes({"return_code": result.make_return_code(Status.OK), "quaternion": Q}, order)
    parts = {a: data[a : a + n] for mask, (a, n) in result.SECTIONS.items() if mask in (0x0004, 0x0020)}
    out = combination_record(parts)
    assert out["q_icrs_to_sensor"] == pytest.approx(list(Q), abs=1e-15)
    assert out["ra_deg"] == pytest.approx(83.8) and out["roll_deg"] == pytest.approx(10.0)
    del parts[HW]
    out = combination_record(parts)  # no hardware section: the order is not assumed
    assert out["q_icrs_to_sensor"] is None and out["quaternion_wire"] == list(result.parse(data)["quaternion"])
    assert "order unknown" in format_record(out)


def test_an_unknown_order_is_refused_in_one_line_before_work_starts(tmp_path, capsys):
    with pytest.raises(SlotRejected) as exc:
        DeviceParams.from_json(b'{"quaternion_order": "wxyz"}')
    assert exc.value.code == REJECT_PARAMS_VALUE and "scalar_first" in exc.value.message
    bad = tmp_path / "bad.json"
    bad.write_text('{"quaternion_order": "xyzw"}')
    assert device_main(["--pty", "--params", str(bad)]) == 2  # before a link is opened
    err = capsys.readouterr()
    assert "listening" not in err.out and err.err.count("\n") == 1 and "quaternion_order" in err.err
    assert ground_main(["--port", "/nonexistent", "params", "upload", str(bad)]) == 2  # refused locally
    assert capsys.readouterr().err.count("\n") == 1
    assert (
        DeviceParams.from_json(b'{"quaternion_order": "scalar_last"}').quaternion_order is QuaternionOrder.SCALAR_LAST
    )


# ------------------------------------------------------------------ return-code bits per condition


@functools.cache
def _blank() -> PipelineOutput:
    """The pipeline's output for a dark frame (no catalog needed: it stops before identification)."""
    dark = Frame(np.zeros((CAMERA.height, CAMERA.width), np.uint16))
    return run_pipeline(dark, CAMERA, None, PipelineParams(optics=None))  # no optics search: no catalog use


def _output(status: Status, stars: bool = True, q: bool = False) -> PipelineOutput:
    sol = SolveResult(Outcome.HIGH_CONFIDENCE, q_icrs_to_sensor=Q) if q else None
    return PipelineOutput(status, stars=_blank().stars if stars else None, solution=sol, camera=CAMERA)


BIT_CASES = {
    "bad frame: nothing": (Status.BAD_FRAME, False, False, 0),
    "too few stars: read, no quality": (Status.TOO_FEW_STARS, True, False, ReturnBits.IMAGE1_SUCCESS),
    "no match: read, quality, full": (Status.NO_MATCH, True, False, 0x15),
    "low confidence: not consistent": (Status.LOW_CONFIDENCE, True, True, 0x15),
    "ok: consistent": (Status.OK, True, True, 0x55),
}


@pytest.mark.parametrize("case", BIT_CASES)
def test_return_bits_follow_what_happened_to_the_frame(case):
    status, stars, q, bits = BIT_CASES[case]
    out = _output(status, stars, q)
    assert return_bits(out) == bits
    rc = result_fields(out)["return_code"]
    assert rc & 0x7F == bits and result.status_of(rc) is status
    assert bool(rc & ReturnBits.STATUS_NOT_OK) == (status is not Status.OK)
    assert not rc & (ReturnBits.IMAGE2_QUALITY | ReturnBits.IMAGE2_SUCCESS | ReturnBits.DETECTOR_IMAGE)


def test_pipeline_outputs_of_real_frames_give_their_bits():
    small = Frame(np.zeros((10, 10), np.uint16))
    assert return_bits(run_pipeline(small, CAMERA, None)) == 0  # wrong size: BAD_FRAME
    assert _blank().status is Status.TOO_FEW_STARS and return_bits(_blank()) == ReturnBits.IMAGE1_SUCCESS


def _command(dev: Device, code: Code, data: bytes = b"") -> None:
    """One acknowledged command to an in-process device."""
    (frame,) = dev.receive(nsp.command(nsp.DEVICE_ADDRESS, 0x11, code, data).frame())
    (event,) = slip.Decoder(nsp.MAX_MESSAGE).feed(frame)
    assert nsp.decode(event.data).ack


def _upload(dev: Device, slot: int, data: bytes) -> None:
    _command(dev, Code.XFER_BEGIN, XferBegin(slot, len(data), crc32(data)).pack())
    _command(dev, Code.XFER_DATA, XferData(slot, 0, data).pack())
    _command(dev, Code.XFER_COMMIT, bytes([slot]))


def _ok_solver(ctx) -> dict:
    return {"return_code": result.make_return_code(Status.OK, 0x55)}


@pytest.mark.parametrize("captured", [True, False])
def test_detector_image_only_for_a_frame_the_detector_captured(captured):
    dev = Device(solver=_ok_solver, frame_source=(lambda ctx: b"exposure") if captured else None)
    _command(dev, Code.INIT, Init(APP_START_ADDRESS).pack())
    _upload(dev, 0, b"catalog")
    if not captured:
        _upload(dev, 1, b"uploaded frame")
    _command(dev, Code.GO, Go(0x0B).pack())
    assert dev.wait_idle(5)
    rc = int(result.parse(dev.runner.result)["return_code"])
    assert rc & 0xFF == 0x55 | (ReturnBits.DETECTOR_IMAGE if captured else 0)


# ------------------------------------------------------------------ status mirror, hardware


def test_the_status_is_seen_by_a_byte_wide_reader():
    for status in Status:
        data = _device_bytes({"return_code": result.make_return_code(status, 0x15)}, QuaternionOrder.SCALAR_FIRST)
        low = np.int8(data[RC_BYTE] - 256 if data[RC_BYTE] > 127 else data[RC_BYTE])  # COSMOS: char ReturnCode
        assert (low < 0) == (status is not Status.OK)  # bit 7: not OK
        assert data[STATUS_BYTE] == status  # the reason code itself
        assert hardware_record(result.parse(data))["status"] == status.name


def test_hardware_temperatures_are_plausible_as_cosmos_converts_them():
    data = Device().runner.result  # the initial NO_RESULT content too
    det, proc = struct.unpack_from("<hH", data, HW + 0x0C)
    assert (det >> 4) / 16 == 20.0 and 25 + (proc - 0x32) * 1.5 == 25.0  # COSMOS's conversions
    assert data[STATUS_BYTE] == Status.NO_RESULT and data[RC_BYTE] & ReturnBits.STATUS_NOT_OK


# ------------------------------------------------------------------ a device run, both orders


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """Catalog image, a directory with one rendered frame and its attitude (scalar first)."""
    from firmware_model.catalog.image_io import catalog_to_image
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign
    from ground.sim.device_process import pick_attitudes
    from ground.sim.frame_writer import write_rendered
    from ground.sim.sensor_sim import DetectorModel, render_frame
    from ground.sim.sky_model import sky_stars

    root = tmp_path_factory.mktemp("field")
    catalog = build_catalog(CatalogDesign())
    (a,) = pick_attitudes(catalog, CAMERA, 1, np.random.default_rng(42))
    (root / "frames").mkdir()
    write_rendered(render_frame(sky_stars(), a, CAMERA, DetectorModel(pattern="RGGB"), seed=100), root / "frames/f.dng")
    return {"image": catalog_to_image(catalog), "root": root, "q": matrix_to_quat(a)}


def _angle(q1, q2) -> float:
    r = quat_to_matrix(q1) @ quat_to_matrix(q2).T
    return float(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))


def test_a_device_run_in_both_orders(field):
    params = field["root"] / "params.json"
    params.write_text(json.dumps({"quaternion_order": "scalar_last"}))  # the device's default set
    args = build_parser().parse_args(
        ["--pty", "--frames", str(field["root"] / "frames"), "--loop", "--params", str(params)]
    )
    dev, link, stop = build_device(args), PtyLink(), threading.Event()
    # the thermal model on a clock that stands still: the temperatures do not depend on how long
    # the solves take on this machine (the heating itself: test_housekeeping.py, on a manual clock)
    dev.housekeeping = Housekeeping(clock=lambda: 0.0)
    thread = threading.Thread(target=serve, args=(dev, link, stop), daemon=True)
    thread.start()
    try:
        with Client(link.path, timeout=guards.REPLY_S) as c:
            c.init()
            c.upload(0, field["image"], progress=False)
            recs = {QuaternionOrder.SCALAR_LAST: c.go_and_wait(timeout=60)}
            c.upload(2, json.dumps({"quaternion_order": "scalar_first"}).encode(), progress=False)  # an upload wins
            recs[QuaternionOrder.SCALAR_FIRST] = c.go_and_wait(timeout=60)
    finally:
        stop.set()
        thread.join(5)
        link.close()
    for order, rec in recs.items():
        rc = int(rec["return_code"])
        assert result.status_of(rc) is Status.OK and rc & 0xFF == 0x75  # quality, success, full, detector, consistent
        hw = hardware_record(rec)
        assert hw == {
            "detector_temp_c": 20.0,
            "processor_temp_c": 25.0,
            "status": "OK",
            "quaternion_order": order.value,
        }
        q = standard_quaternion(rec)
        assert np.allclose(q, rec["ext"]["quaternion"], atol=1e-15) and _angle(q, field["q"]) < 1e-4
        assert np.allclose(order.to_wire(rec["ext"]["quaternion"]), rec["quaternion"], atol=1e-15)
        assert np.allclose(order.from_wire(rec["matching"][0]["quaternion"]), q, atol=1e-15)
        assert rec["statistics"]["good_rows"][0] == CAMERA.height


# ------------------------------------------------------------------ the documented one-line upload


def test_the_documented_quaternion_order_upload_sets_scalar_last(tmp_path, capsys):
    """docs/ICD.md (top and section 10.2) and docs/ground_systems.md give COSMOS driver users one
    line that sets the order; that line, run against a device, makes its results scalar last."""
    import re
    import shlex
    from pathlib import Path

    docs = Path(__file__).resolve().parents[1] / "docs"
    lines = set()
    for name in ("ICD.md", "ground_systems.md"):
        found = re.findall(
            r"echo '(\{[^']*\})' > ([\w.]+) && st16-ground --port URL params upload ([\w.]+)", (docs / name).read_text()
        )
        assert found, name
        lines.update(found)
    ((document, written, uploaded),) = lines  # the same line everywhere
    assert written == uploaded
    (tmp_path / written).write_text(document + "\n")  # what `echo` writes
    from ground.testing.device_proc import DeviceProcess

    with DeviceProcess("--pty", "--state", str(tmp_path / "state")) as device:
        with Client(device.path, timeout=guards.REPLY_S) as c:
            c.init()
            before = hardware_record(c.go_and_wait(timeout=30))["quaternion_order"]
        argv = shlex.split(f"--port {device.path} params upload {tmp_path / written}")
        assert ground_main(argv) == 0
        capsys.readouterr()
        with Client(device.path, timeout=guards.REPLY_S) as c:
            rec = c.go_and_wait(timeout=30)
    assert before == QuaternionOrder.SCALAR_FIRST.value  # the default
    assert hardware_record(rec)["quaternion_order"] == QuaternionOrder.SCALAR_LAST.value
    assert int(rec["hardware"]["status"]) >> 8 & 1 == 1  # bit 8, as the docs say
