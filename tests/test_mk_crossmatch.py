"""One-to-one Hipparcos x BSC5 cross-match lending MK types: synthetic cases and real data."""

import json

import numpy as np
import pytest
from conftest import require_shared

from ground.catalog.build import borrow_mk_types
from ground.catalog.design import DesignError
from ground.catalog.mk_crossmatch import MkAmbiguity, MkNearMiss
from ground.catalog.sources import StarTable
from ground.cli.main import main as cli_main

ARCSEC = np.radians(1.0 / 3600.0)

# BSC5 entries: (HR, RA hour, Dec deg, Dec arcsec, V, SpType); all at RA hh 00 00.0, Dec +dd 00 ss
BSC5_ROWS = [
    (101, 1, 10, 0, 3.00, "A0V"),  # HIP 1: a plain match
    (201, 2, 20, 2, 4.00, "B3V"),  # HIP 2: a double listed twice, the nearer wins
    (202, 2, 20, 5, 4.00, "B5V"),
    (301, 3, 30, 0, 4.50, "F5V"),  # claimed by HIP 3 (1") and HIP 4 (6")
    (401, 4, 40, 3, 5.40, "K0III"),  # HIP 5: combined V 4.5 in Hipparcos: a near miss
    (501, 5, 50, 0, 5.00, ""),  # HIP 6: matched, blank type
    (601, 6, 60, 0, 5.00, "C5II"),  # HIP 7: matched, carbon type (not parseable)
    (701, 7, 70, 30, 5.00, "G0V"),  # 30" from HIP 8: no counterpart
    (801, 8, 10, 0, 7.10, "K0III"),  # HIP 9: matched, fainter than the BSC5 completeness
    (901, 9, 20, 0, 4.00, "K0III"),  # HIP 10 already has a type: not matched
]
# Hipparcos-like stars: (HIP, RA hour, Dec deg, Dec arcsec, V, own type)
STARS = [
    (1, 1, 10, 0.4, 3.10, ""),
    (2, 2, 20, 0.0, 4.00, ""),
    (3, 3, 30, 1.0, 4.55, ""),
    (4, 3, 30, -6.0, 4.70, ""),
    (5, 4, 40, 0.0, 4.50, ""),
    (6, 5, 50, 0.0, 5.00, ""),
    (7, 6, 60, 0.0, 5.00, ""),
    (8, 7, 70, 0.0, 5.00, ""),
    (9, 8, 10, 0.0, 7.00, ""),
    (10, 9, 20, 0.0, 4.00, "G2V"),
]


def _bsc5_line(hr: int, ra_h: int, dec_d: int, dec_s: int, vmag: float, sptype: str) -> str:
    """A catalog.dat line with the fields read_bsc5 needs (V/50 byte layout, 1-based)."""
    line = [" "] * 160

    def put(start: int, text: str) -> None:
        line[start - 1 : start - 1 + len(text)] = text

    put(1, f"{hr:4d}")
    put(76, f"{ra_h:02d}0000.0+{dec_d:02d}00{dec_s:02d}")
    put(103, f"{vmag:5.2f}")
    put(128, f"{sptype:<20}")
    return "".join(line)


def _stars() -> StarTable:
    hip, ra_h, dec_d, dec_s, vmag, sp = zip(*STARS)
    n = len(STARS)
    return StarTable(
        source="hipparcos",
        star_id=np.array(hip, dtype=np.int64),
        ra=np.radians(15.0 * np.array(ra_h, dtype=float)),
        dec=np.radians(np.array(dec_d, dtype=float)) + np.array(dec_s) * ARCSEC,
        vmag=np.array(vmag),
        bv=np.full(n, np.nan),
        vi=np.full(n, np.nan),
        sptype=np.array(sp, dtype=object),
        variable=np.zeros(n, dtype=bool),
        pm_ra=np.zeros(n),
        pm_dec=np.zeros(n),
        epoch=2000.0,
    )


@pytest.fixture
def synthetic(tmp_path):
    path = tmp_path / "catalog.dat"
    path.write_text("\n".join(_bsc5_line(*row) for row in BSC5_ROWS) + "\n")
    return borrow_mk_types(_stars(), path, 2000.0)


def test_one_to_one_match_counts_add_up(synthetic):
    _, r = synthetic
    assert (r.bsc5_stars, r.stars, r.stars_bright) == (10, 9, 8)
    assert (r.matched, r.matched_bright, r.borrowed) == (6, 5, 4)
    assert (r.lost, len(r.near_misses), r.no_counterpart) == (1, 1, 1)
    assert r.matched + r.lost + len(r.near_misses) + r.no_counterpart == r.stars
    assert r.match_rate == 5 / 8


def test_types_borrowed_only_where_none_and_parseable(synthetic):
    table, _ = synthetic
    got = dict(zip(table.star_id.tolist(), table.sptype.tolist()))
    assert got == {1: "A0V", 2: "B3V", 3: "F5V", 4: "", 5: "", 6: "", 7: "", 8: "", 9: "K0III", 10: "G2V"}


def test_ambiguous_double_and_shared_candidate_listed(synthetic):
    _, r = synthetic
    assert r.ambiguous == (
        MkAmbiguity(star_id=2, candidates=(201, 202), rivals=(), chosen=201),
        MkAmbiguity(star_id=3, candidates=(301,), rivals=(4,), chosen=301),
        MkAmbiguity(star_id=4, candidates=(301,), rivals=(3,), chosen=None),
    )
    assert r.summary()["ambiguous_cases"] == [
        "HIP 2: HR 201/202 -> HR 201",
        "HIP 3: HR 301 (also near HIP 4) -> HR 301",
        "HIP 4: HR 301 (also near HIP 3) -> none",
    ]


def test_near_miss_and_untyped_matches(synthetic):
    _, r = synthetic
    assert r.near_misses == (MkNearMiss(star_id=5, hr=401, dmag=0.9),)
    assert r.untyped == ((6, 501, ""), (7, 601, "C5II"))
    s = r.summary()
    assert (s["untyped"], s["near_misses"], s["ambiguous"]) == (2, 1, 3)
    json.dumps(s)  # plain JSON for the catalog summary


def test_missing_bsc5_file_is_a_one_line_design_error(tmp_path):
    with pytest.raises(DesignError, match=r"nope\.dat'?: BSC5 catalog\.dat not found"):
        borrow_mk_types(_stars(), tmp_path / "nope.dat", 2000.0)


def test_real_hipparcos_match_rate_and_cli_summary(shared_data, tmp_path, capsys):
    bsc5 = require_shared(shared_data / "bsc5" / "catalog.dat")
    args = ["--json", "catalog", "build", "--m-thresh", "5.0", "--mk-types", str(bsc5), "-o", str(tmp_path / "c")]
    assert cli_main(args) == 0
    out = json.loads(capsys.readouterr().out)
    x, counts = out["mk_crossmatch"], out["colour_source_counts"]
    assert x["stars"] == out["n_stars"] == x["match_rate_stars"]  # all of V <= 5.0 is within BSC5's completeness
    assert x["matched"] + x["lost"] + x["near_misses"] + x["no_counterpart"] == x["stars"]
    assert x["borrowed"] + x["untyped"] == x["matched"] == out["selection"]["mk_types_borrowed"] + x["untyped"]
    assert x["match_rate"] >= 0.975  # measured 0.9828 (1597 of 1625)
    assert len(x["ambiguous_cases"]) == x["ambiguous"] >= 1
    assert sum(counts.values()) == out["n_stars"] and counts["PICKLES_MK"] > 0.9 * out["n_stars"]
    split = out["colour_source_split"]
    assert {k: split["pattern"][k] + split["verification_only"][k] for k in counts} == counts
