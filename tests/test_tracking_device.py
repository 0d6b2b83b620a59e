"""Tracking mode on the device (docs/tracking.md, docs/ICD.md section 7): GO after GO along a
rendered slow slew, the parameter ``tracking`` on; a jump and a GO without ON fall back to lost in space."""

import struct

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from firmware_model.camera import CameraModel
from firmware_model.device.cli import build_device, build_parser
from firmware_model.device.device import Device
from firmware_model.device.sensor_input import REJECT_PARAMS_VALUE, DeviceParams, PipelineSolver
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.pipeline.result_fields import omega_fields
from firmware_model.pipeline.solve_types import PipelineParams
from firmware_model.pipeline.tracking_run import frame_time
from ground.catalog.build import build_catalog
from ground.catalog.design import CatalogDesign
from ground.link.solve_report import METHODS, format_record, result_record
from ground.sim.device_process import pick_attitudes
from ground.sim.exposure import ExposureRenderer
from ground.sim.sensor_sim import DetectorModel
from ground.sim.smear import SmearPSF
from protocol import nsp, result, slip
from protocol.commands import Code, Slot, SlotRejected

CAM = CameraModel.reference_design()
DET = DetectorModel()
OMEGA = np.radians(0.5) * np.array([0.6, 0.64, 0.48])  # rad/s, sensor axes: 6.4 px of smear in 0.1 s
HZ = 5.0
T0 = 1.8e9  # POSIX s of the first GO
JUMP = Rotation.from_rotvec([np.radians(60 / 3600), 0.0, 0.0]).as_matrix()  # inside the windows, beyond the gate


class Slew:
    """Capture source: the exposure at each GO (``ctx.started``, a fake device clock) along a
    constant-rate slew, smeared; ``jump`` adds an attitude step from then on."""

    def __init__(self, a0):
        self.a0, self.jump, self.now = a0, np.eye(3), T0
        self.renderer = ExposureRenderer(CAM)
        self.psf = SmearPSF(CAM, DET, OMEGA, DET.exposure_s)

    def __call__(self, ctx) -> Frame:
        t = ctx.started + DET.exposure_s / 2 - T0
        a = self.jump @ Rotation.from_rotvec(-OMEGA * t).as_matrix() @ self.a0
        return self.renderer.render(a, DET, seed=int(round(t * HZ)), psf=self.psf)


def _send(dev, code, data=b""):
    (frame,) = dev.receive(nsp.command(nsp.DEVICE_ADDRESS, 0x11, code, data).frame())
    rep = nsp.decode(slip.Decoder(nsp.MAX_MESSAGE).feed(frame)[0].data)
    assert rep.ack
    return rep


@pytest.fixture(scope="module")
def device():
    catalog = build_catalog(CatalogDesign())
    (a0,) = pick_attitudes(catalog, CAM, 1, np.random.default_rng(15))
    slew = Slew(a0)
    dev = Device(solver=PipelineSolver(CAM, PipelineParams(optics=None)), frame_source=slew, clock=lambda: slew.now)
    dev.transfers.objects[Slot.CATALOG] = catalog
    dev.transfers.objects[Slot.PARAMS] = DeviceParams(tracking=True)
    _send(dev, Code.INIT, struct.pack("<I", 0x2000))
    return dev, slew


def _go(dev, slew, code=0x0B):
    """One sequence at the next frame time; its parsed result."""
    _send(dev, Code.GO, bytes([code]))
    assert dev.wait_idle(30)
    slew.now += 1 / HZ
    return result.parse(dev.runner.result)


def _method(rec) -> str:
    return METHODS[int(rec["ext"]["method"])]


def _reason(rec) -> str:
    return bytes(rec["ext"]["reason"]).rstrip(b"\0").decode()


def test_tracking_follows_a_slew_then_falls_back_to_lost_in_space(device):
    dev, slew = device
    recs = [_go(dev, slew) for _ in range(8)]
    assert all(result.status_of(int(r["return_code"])) is result.Status.OK for r in recs)
    assert _method(recs[0]) != "tracking" and not recs[0]["omega"].any()  # the first fix: lost in space
    assert [_method(r) for r in recs[1:]] == ["tracking"] * 7
    for r in recs[3:]:  # the rate within 4 sigma per axis (its covariance in the extension)
        cov = r["ext"]["omega_covariance"]
        att = r["matching"][0]["attitude_covariance"]  # the ICD's matching +0x80: the attitude's
        diagonal = att[[0, 3, 5]]  # the upper triangle row by row: xx, xy, xz, yy, yz, zz
        assert diagonal.all() and np.allclose(np.sqrt(diagonal), r["ext"]["sigma"])
        assert np.all(np.abs(r["omega"] - OMEGA) < 4 * np.sqrt(cov[:3])), (r["omega"], OMEGA, np.sqrt(cov[:3]))
    assert np.degrees(np.sqrt(recs[-1]["ext"]["omega_covariance"][:3])).max() < 0.02  # deg/s
    text = format_record(result_record(recs[-1]))
    assert "method tracking" in text and "] +- [" in text  # omega with its sigma

    slew.jump = JUMP  # a disturbance the constant-rate model does not know
    jumped = _go(dev, slew)
    assert result.status_of(int(jumped["return_code"])) is result.Status.OK and _method(jumped) != "tracking"
    assert _reason(jumped).startswith("tracking lost, lost in space: disagrees with the prediction beyond its gate")
    assert not jumped["omega"].any()
    assert _method(_go(dev, slew)) == "tracking"  # a new track from that fix

    dropped = _go(dev, slew, 0x0A)  # without ON: the track is dropped
    # an uploaded frame has no time: the bright-body check says it did not run, nothing else
    assert (
        _method(dropped) != "tracking" and _reason(dropped) == "bright bodies not checked: the frame has no timestamp"
    )
    assert result.status_of(int(dropped["return_code"])) is result.Status.OK
    assert _method(_go(dev, slew)) == "tracking"  # a confident fix starts a track again

    dev.transfers.objects[Slot.PARAMS] = DeviceParams(tracking=False)  # off: lost in space every time
    assert [_method(_go(dev, slew)) != "tracking" for _ in range(2)] == [True, True]


def test_the_tracking_parameter_is_a_bool():
    assert DeviceParams.from_json(b'{"tracking": true}').tracking is True
    assert DeviceParams.from_json(b"{}").tracking is None  # not set: the device's default (--params)
    with pytest.raises(SlotRejected) as err:
        DeviceParams.from_json(b'{"tracking": 1}')
    assert err.value.code == REJECT_PARAMS_VALUE and err.value.message == "tracking must be true or false, got 1"


@pytest.mark.parametrize("text, default", [('{"tracking": true}', True), ("{}", False)])
def test_params_file_sets_the_device_default(tmp_path, text, default):
    (tmp_path / "p.json").write_text(text)
    dev = build_device(build_parser().parse_args(["--pty", "--params", str(tmp_path / "p.json")]))
    assert dev.solver.tracking is default  # an uploaded set's "tracking" wins over it


def test_omega_covariance_is_the_upper_triangle():
    cov = np.array([[1.0, 4.0, 5.0], [4.0, 2.0, 6.0], [5.0, 6.0, 3.0]])
    fields = omega_fields([0.1, 0.2, 0.3], cov)
    assert fields["ext.omega_covariance"].tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    assert not any(key.startswith(("matching.", "ers.")) for key in fields)  # the ICD's matching +0x80: attitude


def test_frame_time_is_mid_exposure_from_the_timestamp_or_the_go():
    pixels = np.zeros((4, 4), np.uint16)
    assert frame_time(Frame(pixels, exposure_s=0.1), 100.0) == pytest.approx(100.05)
    stamped = Frame(pixels, exposure_s=0.2, timestamp="2026-11-24T17:00:00Z")
    assert frame_time(stamped, 100.0) == pytest.approx(1795539600.1)
    assert frame_time(Frame(pixels, timestamp="not a time"), 100.0) == 100.0
