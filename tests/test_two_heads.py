"""The two-head Sun scenario's pieces (ground/hil/two_heads.py; the run itself is
bench/bench_two_heads_sun.py): the sweep's geometry, the selection, the verdict."""

import math

import numpy as np

from firmware_model.reference_frames import quat_to_matrix
from ground.hil import two_heads


def test_the_sweep_takes_head_a_inside_the_sun_limit_and_keeps_head_b_perpendicular():
    sun, rows = two_heads.sweep()
    mounts = {a: quat_to_matrix(q) for a, q in two_heads.HEADS}
    off_a = [math.degrees(math.acos((mounts[0x0E] @ r.a_body)[2] @ sun)) for r in rows]
    off_b = [math.degrees(math.acos((mounts[0x0F] @ r.a_body)[2] @ sun)) for r in rows]
    assert min(off_a) == two_heads.CLOSEST_DEG or abs(min(off_a) - two_heads.CLOSEST_DEG) < 1e-6
    assert max(off_a) - two_heads.START_DEG < 1e-6
    np.testing.assert_allclose(off_b, 90.0, atol=1e-6)


def test_selection_keeps_an_ok_head_and_the_verdict_counts_the_blinded_rows():
    ok = {"status": "OK", "q_icrs_to_sensor": [1, 0, 0, 0]}
    sun = {"status": "SUN_IN_FOV", "q_icrs_to_sensor": None}
    assert two_heads.select({0x0E: ok, 0x0F: ok}, None) == 0x0E
    assert two_heads.select({0x0E: ok, 0x0F: ok}, 0x0F) == 0x0F
    assert two_heads.select({0x0E: sun, 0x0F: ok}, 0x0E) == 0x0F
    assert two_heads.select({0x0E: sun, 0x0F: sun}, 0x0E) is None
    rows = [
        {"row": 0, "status": {"0x0E": "OK", "0x0F": "OK"}, "selected": "0x0E", "error_arcsec": 5.0},
        {"row": 1, "status": {"0x0E": "BLINDED", "0x0F": "OK"}, "selected": "0x0F", "error_arcsec": 9.0},
    ]
    passed, text = two_heads.verdict(rows)
    assert passed and "not OK on 1 of 2" in text
    rows[1]["error_arcsec"] = 100.0
    assert not two_heads.verdict(rows)[0]
