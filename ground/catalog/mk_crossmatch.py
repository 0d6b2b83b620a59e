"""One-to-one positional and magnitude cross-match of untyped stars (Hipparcos) with BSC5 MK types.

Every BSC5 star within ``MK_MATCH_RADIUS`` of a star and within ``MK_MATCH_DMAG`` in V is a
candidate (KD-tree ball query). Pairs are accepted smallest combined distance
``hypot(sep / MK_MATCH_RADIUS, dV / MK_MATCH_DMAG)`` first, each star and each BSC5 entry at most
once. The :class:`MkCrossMatch` report partitions the stars into matched, lost to a closer star,
near misses (a BSC5 star within the radius but not the magnitude window: mostly doubles whose
components one catalog lists separately and the other combined) and no counterpart.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from firmware_model.catalog.onboard import angle_between, chord_of_angle
from ground.catalog.colour import parse_mk
from ground.catalog.sources import StarTable

MK_MATCH_RADIUS = np.radians(10.0 / 3600.0)  # rad
MK_MATCH_DMAG = 0.5  # mag, |V_star - V_BSC5| below this
BSC5_COMPLETE_V = 6.5  # V to which BSC5 is nearly complete: the match-rate denominator's limit


@dataclass(frozen=True)
class MkAmbiguity:
    """A star with two or more BSC5 candidates, or sharing a candidate with another star."""

    star_id: int
    candidates: tuple[int, ...]  # HR numbers within radius and magnitude window, best first
    rivals: tuple[int, ...]  # other stars claiming one of those HR numbers
    chosen: int | None  # HR number matched; None when all candidates went to closer stars

    def describe(self, label: str) -> str:
        """One line, e.g. ``HIP 13914: HR 887/888 -> HR 887``."""
        text = f"{label} {self.star_id}: HR {'/'.join(map(str, self.candidates))}"
        if self.rivals:
            text += f" (also near {label} {'/'.join(map(str, self.rivals))})"
        return text + (f" -> HR {self.chosen}" if self.chosen is not None else " -> none")


@dataclass(frozen=True)
class MkNearMiss:
    """An unmatched star with a BSC5 star within the radius but ``|dV| >= MK_MATCH_DMAG``."""

    star_id: int
    hr: int  # the positionally nearest BSC5 star
    dmag: float  # V_BSC5 - V_star, mag


@dataclass(frozen=True)
class MkCrossMatch:
    """Report of :func:`cross_match_mk` (counts of stars; the lists name the cases)."""

    source: str  # the stars' catalog, e.g. "hipparcos"
    bsc5_stars: int  # BSC5 stars considered (all with position and V)
    stars: int  # stars cross-matched (those without an MK type)
    stars_bright: int  # of which V <= BSC5_COMPLETE_V
    matched: int  # one-to-one matches
    matched_bright: int  # of which V <= BSC5_COMPLETE_V
    borrowed: int  # matches whose BSC5 type is parseable (used for a Pickles template)
    lost: int  # unmatched: every candidate went to a closer star
    no_counterpart: int  # unmatched: no BSC5 star within the radius
    ambiguous: tuple[MkAmbiguity, ...]
    near_misses: tuple[MkNearMiss, ...]
    untyped: tuple[tuple[int, int, str], ...]  # (star, HR, BSC5 type) matched with a blank/unparseable type

    @property
    def match_rate(self) -> float:
        """Matched fraction of the stars at V <= BSC5_COMPLETE_V (NaN if there are none)."""
        return self.matched_bright / self.stars_bright if self.stars_bright else float("nan")

    @property
    def label(self) -> str:
        """Identifier prefix of the stars (HIP for Hipparcos)."""
        return {"hipparcos": "HIP", "bsc5": "HR"}.get(self.source, self.source)

    def summary(self) -> dict:
        """Plain-JSON counts, the match rate and the ambiguous cases (one line each)."""
        return {
            "bsc5_stars": self.bsc5_stars,
            "stars": self.stars,
            "matched": self.matched,
            "borrowed": self.borrowed,
            "untyped": len(self.untyped),
            "ambiguous": len(self.ambiguous),
            "lost": self.lost,
            "near_misses": len(self.near_misses),
            "no_counterpart": self.no_counterpart,
            "match_rate": round(self.match_rate, 4),
            "match_rate_stars": self.stars_bright,
            "match_rate_v_limit": BSC5_COMPLETE_V,
            "ambiguous_cases": [a.describe(self.label) for a in self.ambiguous],
        }


def candidate_pairs(stars: StarTable, bsc: StarTable) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(star index, BSC5 index, separation in rad, V_BSC5 - V_star) of every pair within the radius."""
    near = cKDTree(bsc.vec).query_ball_point(stars.vec, chord_of_angle(MK_MATCH_RADIUS))
    i = np.repeat(np.arange(len(stars)), [len(n) for n in near])
    j = np.fromiter(itertools.chain.from_iterable(near), dtype=np.intp, count=len(i))
    return i, j, angle_between(stars.vec[i], bsc.vec[j]), bsc.vmag[j] - stars.vmag[i]


def one_to_one(i: np.ndarray, j: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """Mask of the pairs kept when each ``i`` and each ``j`` is used once, smallest cost first."""
    keep = np.zeros(len(i), dtype=bool)
    used_i: set[int] = set()
    used_j: set[int] = set()
    for k in np.lexsort((j, i, cost)):  # ties: lower indices first
        if i[k] not in used_i and j[k] not in used_j:
            keep[k] = True
            used_i.add(int(i[k]))
            used_j.add(int(j[k]))
    return keep


def ambiguities(stars: StarTable, bsc: StarTable, i, j, cost, keep) -> tuple[MkAmbiguity, ...]:
    """The stars with several candidates or a candidate shared with another star (by star order)."""
    per_star = np.bincount(i, minlength=len(stars))
    per_bsc = np.bincount(j, minlength=len(bsc))
    out = []
    for s in np.unique(i[(per_star[i] > 1) | (per_bsc[j] > 1)]):
        mine = np.flatnonzero(i == s)
        mine = mine[np.argsort(cost[mine], kind="stable")]
        rivals = np.unique(i[np.isin(j, j[mine]) & (i != s)])
        chosen = mine[keep[mine]]
        out.append(
            MkAmbiguity(
                star_id=int(stars.star_id[s]),
                candidates=tuple(int(h) for h in bsc.star_id[j[mine]]),
                rivals=tuple(int(r) for r in stars.star_id[rivals]),
                chosen=int(bsc.star_id[j[chosen[0]]]) if len(chosen) else None,
            )
        )
    return tuple(out)


def near_misses(stars: StarTable, bsc: StarTable, i, j, sep, dmag, has_candidate) -> tuple[MkNearMiss, ...]:
    """Stars without a candidate whose positionally nearest BSC5 star within the radius is off in V."""
    out = []
    for s in np.unique(i[~has_candidate[i]]):
        mine = np.flatnonzero(i == s)
        k = mine[np.argmin(sep[mine])]
        out.append(MkNearMiss(int(stars.star_id[s]), int(bsc.star_id[j[k]]), round(float(dmag[k]), 3)))
    return tuple(out)


def cross_match_mk(stars: StarTable, bsc: StarTable) -> tuple[np.ndarray, MkCrossMatch]:
    """Match ``stars`` (all taken as untyped) one-to-one with ``bsc`` (same epoch).

    Returns the BSC5 row of each star (-1 where unmatched) and the report.
    """
    pairs = candidate_pairs(stars, bsc)
    _, _, sep, dmag = pairs
    window = np.abs(dmag) < MK_MATCH_DMAG
    i, j = pairs[0][window], pairs[1][window]
    cost = np.hypot(sep[window] / MK_MATCH_RADIUS, dmag[window] / MK_MATCH_DMAG)
    keep = one_to_one(i, j, cost)
    row = np.full(len(stars), -1, dtype=np.intp)
    row[i[keep]] = j[keep]
    matched = row >= 0
    has_candidate = np.zeros(len(stars), dtype=bool)
    has_candidate[i] = True
    misses = near_misses(stars, bsc, *pairs, has_candidate)
    bright = stars.vmag <= BSC5_COMPLETE_V
    types = bsc.sptype[row[matched]]
    parsed = np.array([parse_mk(t) is not None for t in types], dtype=bool)
    report = MkCrossMatch(
        source=stars.source,
        bsc5_stars=len(bsc),
        stars=len(stars),
        stars_bright=int(bright.sum()),
        matched=int(matched.sum()),
        matched_bright=int((matched & bright).sum()),
        borrowed=int(parsed.sum()),
        lost=int((has_candidate & ~matched).sum()),
        no_counterpart=len(stars) - int(has_candidate.sum()) - len(misses),
        ambiguous=ambiguities(stars, bsc, i, j, cost, keep),
        near_misses=misses,
        untyped=tuple(
            (int(s), int(h), str(t))
            for s, h, t in zip(stars.star_id[matched][~parsed], bsc.star_id[row[matched]][~parsed], types[~parsed])
        ),
    )
    return row, report
