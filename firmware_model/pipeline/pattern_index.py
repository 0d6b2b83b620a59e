"""A table of scale-free 4-star pattern keys and its lookup, in plain arrays.

A pattern is four catalog stars (rows of ``vec``); its key is its six pairwise angles sorted and
divided by the largest (five numbers in (0, 1], ``scale_free``), ``top`` its largest angle (rad).
Keys are filed in cells of :data:`CELL` on each axis, the patterns sorted by cell, as tetra3 files
its keys in a hash table; a lookup visits the cells a tolerance box can touch and keeps the
patterns within the tolerance (L-infinity). The table is a handful of arrays (no pickled tree),
so a file of it loads by ``numpy.load`` alone and the same keys give the same answer in any
process (``firmware_model.pipeline.sky_patterns``: the whole-sky table; ``scale_free``: a
per-field one).

Units: radians; ``vec`` ICRS unit vectors (docs/CONVENTIONS.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Cell edge on each key axis: a tolerance up to half of it touches at most 2 cells an axis.
CELL = 0.02
_BINS = int(round(1.0 / CELL)) + 1  # keys in (0, 1]: bin 1 / CELL holds the keys equal to 1
#: Array names of :meth:`PatternIndex.arrays` (a file's members).
ARRAYS = ("vec", "groups", "keys", "top", "codes")


def cell_codes(keys: np.ndarray) -> np.ndarray:
    """The cell number of each key (rows of 5): its bins on the five axes, mixed radix."""
    bins = np.clip(np.floor(np.asarray(keys, float) / CELL), 0, _BINS - 1).astype(np.int64)
    code = np.zeros(len(bins), np.int64)
    for axis in range(bins.shape[1]):
        code = code * _BINS + bins[:, axis]
    return code


@dataclass(frozen=True)
class PatternIndex:
    """Catalog patterns sorted by key cell: star directions ``vec`` (N, 3), 4-star ``groups``
    (P, 4) rows of ``vec``, ``keys`` (P, 5), ``top`` (P,) the largest angle (rad), ``codes`` (P,)
    the ascending cell numbers (:func:`cell_codes`)."""

    vec: np.ndarray
    groups: np.ndarray
    keys: np.ndarray
    top: np.ndarray
    codes: np.ndarray

    @classmethod
    def from_patterns(cls, vec: np.ndarray, groups: np.ndarray, keys: np.ndarray, top: np.ndarray) -> PatternIndex:
        """The index of patterns given in any order (stable: equal cells keep their order)."""
        codes = cell_codes(keys)
        order = np.argsort(codes, kind="stable")
        return cls(
            np.ascontiguousarray(vec, float),
            np.ascontiguousarray(groups[order], np.int32),
            np.ascontiguousarray(keys[order], np.float32),
            np.ascontiguousarray(top[order], float),
            codes[order],
        )

    def __len__(self) -> int:
        return len(self.codes)

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays a file keeps (:data:`ARRAYS`)."""
        return {name: getattr(self, name) for name in ARRAYS}

    @classmethod
    def from_arrays(cls, arrays) -> PatternIndex:
        """The index of :meth:`arrays` read back (a mapping such as an ``np.load`` file); ValueError
        when they do not make one."""
        try:
            vec, groups, keys, top, codes = (np.asarray(arrays[name]) for name in ARRAYS)
        except KeyError as exc:
            raise ValueError(f"no pattern array {exc}") from None
        n = len(codes)
        shapes_ok = vec.ndim == 2 and vec.shape[1:] == (3,) and groups.shape == (n, 4) and keys.shape == (n, 5)
        if not shapes_ok or top.shape != (n,):
            raise ValueError("pattern arrays of mismatched shapes")
        if n and (groups.min() < 0 or groups.max() >= len(vec) or np.any(np.diff(codes) < 0)):
            raise ValueError("pattern arrays out of range or unsorted")
        return cls(vec, groups, keys, top, codes)

    def within(self, keys: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        """(query row, pattern row) of every pattern whose key is within ``tolerance``
        (L-infinity) of a query key (rows of ``keys``), query rows ascending."""
        keys = np.asarray(keys, float).reshape(-1, 5)
        if len(keys) == 0 or len(self) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        lo = np.clip(np.floor((keys - tolerance) / CELL), 0, _BINS - 1).astype(np.int64)
        span = int(np.ceil(2.0 * tolerance / CELL)) + 1  # cells an axis a box can touch
        offsets = np.stack(np.meshgrid(*[np.arange(span)] * 5, indexing="ij"), -1).reshape(-1, 5)
        bins = lo[:, None, :] + offsets[None]  # (Q, span^5, 5)
        hi = np.clip(np.floor((keys + tolerance) / CELL), 0, _BINS - 1).astype(np.int64)
        useful = np.all(bins <= hi[:, None, :], axis=2)  # cells past the box's far edge: none
        q, cell = np.nonzero(useful)
        code = np.zeros(len(q), np.int64)
        for axis in range(5):
            code = code * _BINS + bins[q, cell, axis]
        # each distinct cell looked up once, in ascending order (the table's cache lines in turn)
        cells, back = np.unique(code, return_inverse=True)
        start = np.searchsorted(self.codes, cells, "left")[back]
        stop = np.searchsorted(self.codes, cells, "right")[back]
        counts = stop - start
        qi = np.repeat(q, counts)
        pi = np.repeat(start - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
        close = np.max(np.abs(self.keys[pi] - keys[qi]), axis=1) <= tolerance
        qi, pi = qi[close], pi[close]
        order = np.argsort(qi, kind="stable")
        return qi[order], pi[order]
