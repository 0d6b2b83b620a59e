"""Source catalog readers (Hipparcos 2, Yale BSC5), proper motion and selection."""

import numpy as np
import pytest

from ground.catalog.sources import (
    MAS,
    CatalogFormatError,
    StarTable,
    hp_to_v,
    hp_to_v_coefficients,
    merge_close_doubles,
    read_bsc5,
    read_hipparcos,
    select_stars,
)

# Real BSC5 lines (HR 3 = 30 Psc, a variable K0 giant; HR 92 = a nova entry without position/V)
BSC5_HR3 = (
    "   3 33    PscBD-06 6357     281285721002I         Var?     000013.0-061601000520.1-054227 93.75-65.93 4.61  "
    "+1.04 +0.89 +0.54   K0IIIbCN-0.5       -0.009+0.089 +.014-006SB1O < 17  2.5   0.0     3*"
)
BSC5_SIRIUS = (
    "2491  9Alp CMaBD-16 1591  48915151881 257I   5423           064044.6-163444064508.9-164258227.22-08.88-1.46   "
    "0.00 -0.05 -0.03   A1Vm               -0.553-1.205 +.375-008SBO    13 10.3  11.2AB   4*"
)
BSC5_NOVA = "  92          BD+61 2604  2245 109       ".ljust(160)


def _write(tmp_path, name, lines):
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


def test_bsc5_reader_fields_and_nova_dropped(tmp_path):
    t = read_bsc5(_write(tmp_path, "c.dat", [BSC5_HR3, BSC5_NOVA, BSC5_SIRIUS]))
    assert list(t.star_id) == [3, 2491]
    assert t.vmag[1] == -1.46 and t.bv[1] == 0.0 and t.sptype[1] == "A1Vm"
    assert t.sptype[0] == "K0IIIbCN-0.5" and not t.variable[0]  # "Var?" is only a suspicion
    ra, dec = np.degrees(t.ra[1]), np.degrees(t.dec[1])
    assert ra == pytest.approx(15 * (6 + 45 / 60 + 8.9 / 3600), abs=1e-9)
    assert dec == pytest.approx(-(16 + 42 / 60 + 58 / 3600), abs=1e-9)
    assert t.pm_ra[1] == pytest.approx(-0.553 * 1000 * MAS)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda s: s[:102] + " 4.x1" + s[107:], r"line 1: Vmag \(bytes 103-107\) is not a number: '4.x1'"),
        (lambda s: s[:120], r"line 1: 120 characters"),
        (lambda s: s[:83] + "*" + s[84:], r"line 1: Dec sign \(byte 84\) is '\*'"),
        (lambda s: s[:75] + "25" + s[77:], r"line 1: position out of range"),
        (lambda s: "    " + s[4:], r"line 1: HR number"),
    ],
)
def test_bsc5_malformed_lines_name_file_line_and_value(tmp_path, mutate, match):
    path = _write(tmp_path, "bad.dat", [mutate(BSC5_HR3)])
    with pytest.raises(CatalogFormatError, match=match) as info:
        read_bsc5(path)
    assert str(path) in str(info.value)


def _hip_line(hip=32349, ra=1.7678, dec=-0.2917, hp=-1.0876, bv=0.009, vi=-0.02, va=0, pmra=-546.01, pmde=-1223.07):
    f = (
        [hip, 1, 0, 1, ra, dec, 379.21, pmra, pmde]
        + [0.5] * 5
        + [100, 0.1, 0, 0.0, 0, hp, 0.002, 0.01, va, bv, 0.01, vi]
        + [1.0] * 15
    )
    return " ".join(str(x) for x in f)


def test_hipparcos_reader_and_epoch(tmp_path):
    path = _write(tmp_path, "hip2.dat", [_hip_line(), _hip_line(hip=7, va=2, bv=1.5)])
    t = read_hipparcos(path, epoch=1991.25)
    assert list(t.star_id) == [32349, 7] and list(t.variable) == [False, True]
    assert t.vmag[0] == pytest.approx(hp_to_v(-1.0876, 0.009))
    assert t.sptype[0] == ""
    later = read_hipparcos(path, epoch=2091.25)  # 100 years of proper motion
    dra = (later.ra[0] - t.ra[0]) * np.cos(t.dec[0])
    ddec = later.dec[0] - t.dec[0]
    assert dra == pytest.approx(-546.01 * MAS * 100, rel=1e-3)
    assert ddec == pytest.approx(-1223.07 * MAS * 100, rel=1e-3)


@pytest.mark.parametrize(
    "line, match",
    [
        (" ".join(_hip_line().split()[:-1]), "line 2: expected 41 fields, got 40"),
        (_hip_line().replace("-1.0876", "abc"), "could not convert"),
        (_hip_line(dec=2.0), "line 2: position out of range"),
    ],
)
def test_hipparcos_malformed(tmp_path, line, match):
    path = _write(tmp_path, "hip2.dat", [_hip_line(), line])
    with pytest.raises(CatalogFormatError, match=match) as info:
        read_hipparcos(path)
    assert str(path) in str(info.value)


def test_hp_to_v_transform_is_the_fitted_one():
    c = hp_to_v_coefficients()
    assert c["rms_mag"] < 0.03 and c["n_stars"] > 3000
    # V ~ Hp near B-V = 0; red stars have Hp > V (Bessell 2000, PASP 112, 961, fig. 3)
    assert abs(hp_to_v(5.0, 0.0) - 5.0) < 0.01
    assert -0.25 < hp_to_v(5.0, 1.5) - 5.0 < -0.05


def _table(ra_deg, dec_deg, v):
    n = len(v)
    z = np.zeros(n)
    return StarTable(
        "test",
        np.arange(n),
        np.radians(ra_deg),
        np.radians(dec_deg),
        np.array(v, float),
        z,
        z,
        np.full(n, "", object),
        np.array([False] * (n - 1) + [True]),
        z,
        z,
        2000.0,
    )


def test_close_doubles_merged_keeping_the_brighter():
    t = _table([10.0, 10.001, 10.1, 50.0], [0.0, 0.0, 0.0, 0.0], [4.0, 3.0, 4.5, 2.0])
    merged, removed = merge_close_doubles(t, np.radians(0.01))  # 0.001 deg apart: one source
    assert removed == 1 and sorted(merged.vmag) == [2.0, 3.0, 4.5]
    sel, stats = select_stars(t, m_thresh=4.2, resolve_angle=np.radians(0.01), drop_variable=True)
    assert list(sel.vmag) == [3.0]  # 4.0 merged, 4.5 too faint, 2.0 variable
    assert stats == {"source_stars": 4, "merged_doubles": 1, "dropped_variable": 1, "selected": 1}


def test_real_bsc5(shared_data):
    t = read_bsc5(shared_data / "bsc5" / "catalog.dat")
    assert len(t) == 9096  # 9110 HR numbers less 14 novae / non-stellar entries
    assert np.isfinite(t.bv).sum() == 8786
    sirius = t.subset(t.star_id == 2491)
    assert sirius.vmag[0] == -1.46


def test_real_hipparcos_against_bsc5(shared_data):
    hip = read_hipparcos(epoch=2000.0)
    assert len(hip) == 117955
    vega, arcturus = hip.subset(hip.star_id == 91262), hip.subset(hip.star_id == 69673)
    assert vega.vmag[0] == pytest.approx(0.03, abs=0.07) and arcturus.vmag[0] == pytest.approx(-0.04, abs=0.07)
    bright = hip.subset(hip.vmag <= 5.0)
    bsc = read_bsc5(shared_data / "bsc5" / "catalog.dat")
    assert abs(len(bright) - (bsc.vmag <= 5.0).sum()) < 0.05 * len(bright)
