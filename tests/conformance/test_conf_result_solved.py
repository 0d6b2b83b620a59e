"""The matching telemetry of a solved attitude (1-35920 as paraphrased in
../shared/research/st16_icd_vs_emulator.md row 4: +0x60 the inertial quaternion, scalar first;
+0x80 six f64, the upper triangle of the attitude covariance). A result with an attitude needs a
catalog and a frame, which no command of the public pages provides: the setup builds a catalog
with the vendor-side tool (``st16-ground catalog build``, a subprocess), lays it in the device's
state directory in the documented slot file format (docs/ICD.md section 9: ``ST16IMG1``, u64
length, u32 CRC-32, data) and renders frames at known attitudes (``--sky``, a schedule of
scalar-first quaternions). Only the assertions speak for the ICD."""

import math
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest

from .conf_device import DeviceProcess
from .icd import GO, GO_COMMAND, GO_ON, MATCHING, init_application, result_bytes, wait_result_ready

pytestmark = pytest.mark.timeout(300)

#: (RA, Dec, roll) in degrees of the scheduled boresights: star-rich fields, any roll.
FIELDS = ((84.0, -1.0, 30.0), (310.0, 40.0, 75.0), (165.0, 56.0, 140.0))
CONSISTENT_SOLUTION = 0x40  # return-code bit (COSMOS name)


def quat_from_matrix(r: list[list[float]]) -> tuple[float, ...]:
    """Scalar-first unit quaternion of a rotation matrix (Shepperd's method)."""
    t = r[0][0] + r[1][1] + r[2][2]
    if t > 0:
        s = 2 * math.sqrt(1 + t)
        q: tuple[float, ...] = (s / 4, (r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s)
    else:
        i = max(range(3), key=lambda k: r[k][k])
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * math.sqrt(1 + r[i][i] - r[j][j] - r[k][k])
        v = [0.0, 0.0, 0.0]
        v[i] = s / 4
        v[j] = (r[j][i] + r[i][j]) / s
        v[k] = (r[k][i] + r[i][k]) / s
        q = ((r[k][j] - r[j][k]) / s, *v)
    return q if q[0] >= 0 else tuple(-c for c in q)


def attitude(ra_deg: float, dec_deg: float, roll_deg: float) -> tuple[float, ...]:
    """ICRS-to-sensor quaternion whose sensor z is the boresight (RA, Dec), rolled about it."""
    ra, dec, roll = map(math.radians, (ra_deg, dec_deg, roll_deg))
    z = (math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec))
    e = (-math.sin(ra), math.cos(ra), 0.0)  # east
    n = (z[1] * e[2] - z[2] * e[1], z[2] * e[0] - z[0] * e[2], z[0] * e[1] - z[1] * e[0])  # north
    x = tuple(math.cos(roll) * a + math.sin(roll) * b for a, b in zip(e, n, strict=True))
    y = tuple(-math.sin(roll) * a + math.cos(roll) * b for a, b in zip(e, n, strict=True))
    return quat_from_matrix([list(x), list(y), list(z)])


def same_rotation(a, b) -> bool:
    return abs(sum(p * q for p, q in zip(a, b, strict=True))) > 0.9999


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    """(scheduled quaternions, matching records and return codes of one GO per field)."""
    work = tmp_path_factory.mktemp("conformance-solved")
    tool = Path(sys.executable).parent / "st16-ground"
    catalog = work / "catalog.st16cat"
    subprocess.run(
        [str(tool), "catalog", "build", "-o", str(catalog), "--no-progress"],
        check=True,
        capture_output=True,
        timeout=240,
    )
    data = catalog.read_bytes()
    slot = work / "state" / "slot0"
    slot.mkdir(parents=True)
    (slot / "active.img").write_bytes(b"ST16IMG1" + struct.pack("<QI", len(data), zlib.crc32(data)) + data)
    quats = [attitude(*f) for f in FIELDS]
    schedule = work / "schedule.csv"
    schedule.write_text("qw,qx,qy,qz\n" + "".join(",".join(f"{c:.12f}" for c in q) + "\n" for q in quats))
    dev = DeviceProcess(work / "state", "--sky", str(schedule))
    try:
        link = dev.link
        assert init_application(link).ack
        out = []
        for _ in quats:
            assert link.one(GO, bytes((GO_ON | GO_COMMAND,))).ack
            wait_result_ready(link)
            code = struct.unpack("<I", result_bytes(link, 0x004, 4))[0]
            out.append((code, result_bytes(link, MATCHING, 176)))
    finally:
        dev.stop()
    return quats, out


def test_conf_matching_quaternion_is_scalar_first(solved):
    """1-35920 (via st16_icd_vs_emulator.md row 4): matching telemetry +0x60 is the inertial
    quaternion, scalar first. For every field the device solved (return-code bit 0x40), the four
    f64 at +0x60 read scalar first are the scheduled attitude (or its conjugate, whichever
    direction the rotation is read in); read scalar last they are not."""
    quats, results = solved
    checked = 0
    for q, (code, rec) in zip(quats, results, strict=True):
        if not code & CONSISTENT_SOLUTION:
            continue
        got = struct.unpack_from("<4d", rec, 0x60)
        conj = (q[0], -q[1], -q[2], -q[3])
        assert same_rotation(got, q) or same_rotation(got, conj), (got, q)
        as_last = (got[3], got[0], got[1], got[2])
        assert not (same_rotation(as_last, q) or same_rotation(as_last, conj))
        checked += 1
    assert checked >= 1, [hex(code) for code, _ in results]


def positive_definite(xx, xy, xz, yy, yz, zz) -> bool:
    """The 3 x 3 symmetric matrix is a plausible attitude covariance: positive definite, every
    variance below (1 deg)^2 in rad^2."""
    limit = math.radians(1) ** 2
    det = xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)
    return 0 < xx < limit and 0 < yy < limit and 0 < zz < limit and xx * yy - xy * xy > 0 and det > 0


def test_conf_matching_attitude_covariance_of_a_solved_attitude(solved):
    """1-35920 (via st16_icd_vs_emulator.md row 4): matching telemetry +0x80 is six f64, the upper
    triangle of the attitude covariance. A solved lost-in-space attitude has an uncertainty: the
    six numbers make a positive-definite matrix with variances below (1 deg)^2. The element order
    of "the upper triangle" is in the page's table, which this suite could not read: either row
    by row (xx, xy, xz, yy, yz, zz) or diagonal first (xx, yy, zz, xy, xz, yz) is accepted."""
    _, results = solved
    checked = 0
    for code, rec in results:
        if not code & CONSISTENT_SOLUTION:
            continue
        c = struct.unpack_from("<6d", rec, 0x80)
        row_major = positive_definite(*c)
        diagonal_first = positive_definite(c[0], c[3], c[4], c[1], c[5], c[2])
        assert row_major or diagonal_first, c
        checked += 1
    assert checked >= 1, [hex(code) for code, _ in results]
