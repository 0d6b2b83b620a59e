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
from functools import cached_property

import numpy as np
from numba import njit

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
    the ascending cell numbers (:func:`cell_codes`). Stored compactly (16-bit star rows where
    they fit, 32-bit floats and cell numbers: 36 bytes a pattern), so that the whole-sky table's
    file is read quickly even when it is not in the page cache."""

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
            np.ascontiguousarray(groups[order], np.uint16 if len(vec) <= 1 << 16 else np.int32),
            np.ascontiguousarray(keys[order], np.float32),
            np.ascontiguousarray(top[order], np.float32),
            codes[order].astype(np.int32),  # at most (1 / CELL + 1) ** 5 = 51 ** 5 < 2 ** 31
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
        (L-infinity) of a query key (rows of ``keys``), query rows ascending, pattern rows
        ascending within each."""
        keys = np.ascontiguousarray(np.asarray(keys, float).reshape(-1, 5))
        if len(keys) == 0 or len(self) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return _within_kernel(self.codes, self._prefix_starts, self.keys, keys, float(tolerance), CELL, _BINS)

    @cached_property
    def _prefix_starts(self) -> np.ndarray:
        """The first pattern row of each cell prefix (the first three axes' bins): a lookup then
        searches only its prefix's few rows, which stay in the processor's cache (built once)."""
        return np.searchsorted(self.codes, np.arange(_BINS**3 + 1, dtype=np.int64) * _BINS**2).astype(np.int64)


@njit(cache=True, nogil=True)
def _within_kernel(codes, prefix_starts, table, keys, tolerance, cell, bins):  # pragma: no cover - compiled
    """:meth:`PatternIndex.within`'s numbers: for each query, every cell its tolerance box
    touches (at most 2 an axis while the tolerance is under half a cell), the cells' patterns
    found by binary search among their prefix's rows of the sorted ``codes`` (the cells that
    differ only on the last axis hold one run of rows: one search for its start, one for its
    end), those within the tolerance kept."""
    n_q = len(keys)
    lo = np.empty(5, np.int64)
    hi = np.empty(5, np.int64)
    cur = np.empty(5, np.int64)
    out_q = np.empty(64, np.int64)
    out_p = np.empty(64, np.int64)
    n = 0
    for q in range(n_q):
        for a in range(5):
            lo[a] = min(max(int(np.floor((keys[q, a] - tolerance) / cell)), 0), bins - 1)
            hi[a] = min(max(int(np.floor((keys[q, a] + tolerance) / cell)), 0), bins - 1)
            cur[a] = lo[a]
        first = n
        while True:
            prefix = (cur[0] * bins + cur[1]) * bins + cur[2]
            code = (prefix * bins + cur[3]) * bins
            a0, b0 = prefix_starts[prefix], prefix_starts[prefix + 1]
            start = a0 + np.searchsorted(codes[a0:b0], code + lo[4], "left")
            stop = a0 + np.searchsorted(codes[a0:b0], code + hi[4], "right")
            for p in range(start, stop):
                close = True
                for a in range(5):
                    if abs(table[p, a] - keys[q, a]) > tolerance:
                        close = False
                        break
                if close:
                    if n == len(out_q):
                        out_q = np.concatenate((out_q, np.empty(n, np.int64)))
                        out_p = np.concatenate((out_p, np.empty(n, np.int64)))
                    out_q[n] = q
                    out_p[n] = p
                    n += 1
            a = 3  # the next run of cells of the box (the last axis is within the run)
            while a >= 0 and cur[a] == hi[a]:
                cur[a] = lo[a]
                a -= 1
            if a < 0:
                break
            cur[a] += 1
        out_p[first:n] = np.sort(out_p[first:n])
    return out_q[:n], out_p[:n]


def warm_up() -> None:
    """Compile (or load from numba's disk cache) the lookup kernel."""
    index = PatternIndex.from_patterns(np.eye(3), np.zeros((2, 4), np.int64), np.full((2, 5), 0.5), np.ones(2))
    index.within(np.full((1, 5), 0.5), 0.01)
