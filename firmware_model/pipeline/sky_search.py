"""Lost in space with the field of view unknown, or known only roughly: the focal length is
searched with the attitude, against the whole-sky pattern table (``sky_patterns``).

The field-of-view range (:class:`FieldRange`, horizontal, deg) is cut into focal-length brackets
of ratio :data:`BRACKET_RATIO`; in each, the frame's brightest detections are turned into
directions through the bracket's focal length and matched as scale-free 4-star patterns within
its focal range (``scale_free.pattern_matches``: inside one bracket a key bends by well under its
tolerance, even on a 60 deg field). Every bracket's matches are then taken in the plate solvers'
order, brightness rank first (the patterns of the 4 brightest, then those adding the 5th, ...),
best key next, and each is checked (:func:`check`, as tetra3 and cedar-solve verify): the
catalog's brightest stars the hypothesis puts on the array against the frame's brightest
detections, the chance that as many fall within the match radius by coincidence (binomial), and
that chance times the hypotheses tried so far: the false-alarm probability over the whole
search. The first hypothesis under :data:`FALSE_ALARM` gives the focal length; the caller
identifies the frame with it (``run.identify_stars``: the field's catalog, the optics fit). The
search is counted: at most ``max_checks`` hypotheses checked, the same answer on any machine.

Units: px, radians; the field of view in deg (horizontal, across the width).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import betainc

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import chord_of_angle
from firmware_model.pipeline import scale_free
from firmware_model.pipeline.field_of_view_limits import FOV_LIMITS_DEG
from firmware_model.pipeline.pattern_index import PatternIndex
from firmware_model.pipeline.sky_patterns import magnitude_limit

#: Fields of view a blind search spans (deg): the whole-sky table's (a range or hint may name any of
#: ``field_of_view_limits.FOV_LIMITS_DEG``).
BLIND_FOV_DEG = (5.0, 60.0)
#: A field-of-view hint's tolerance: ``F`` searches ``F / (1 + t)`` to ``F * (1 + t)`` (a hint
#: 25 % too wide or too narrow is well inside).
HINT_TOLERANCE = 0.4
#: Ratio of a focal-length bracket's ends.
BRACKET_RATIO = 1.15
#: Brightest clean detections whose patterns the search matches (clutter such as hot pixels,
#: planets or false stars can hold several of the brightest).
PATTERN_STARS = 20
#: Brightest clean detections a check compares.
CHECK_STARS = 40
#: False-alarm probability over the whole search under which a hypothesis is taken.
FALSE_ALARM = 1e-6
#: Hypotheses a frame's search checks before its candidates are first identified, and in all.
FIRST_CHECKS, MAX_CHECKS = 200, 1000
#: Key tolerance (``OpticsSearch.pattern_tolerance``).
TOLERANCE = 0.01


@dataclass(frozen=True)
class FieldRange:
    """Horizontal fields of view (deg) a search spans, ``lo_deg <= hi_deg``; ValueError (one line)
    outside :data:`FOV_LIMITS_DEG`."""

    lo_deg: float
    hi_deg: float

    def __post_init__(self):
        lo, hi = FOV_LIMITS_DEG
        for name, v in (("low end", self.lo_deg), ("high end", self.hi_deg)):
            if not lo <= v <= hi:
                raise ValueError(f"field-of-view range {name} {v:g} deg is outside {lo:g}-{hi:g} deg")
        if self.lo_deg > self.hi_deg:
            raise ValueError(f"field-of-view range {self.lo_deg:g}-{self.hi_deg:g} deg runs backwards")

    @classmethod
    def hint(cls, fov_deg: float) -> FieldRange:
        """The range a field-of-view hint stands for (:data:`HINT_TOLERANCE` either way)."""
        lo, hi = FOV_LIMITS_DEG
        if not lo <= fov_deg <= hi:
            raise ValueError(f"field-of-view hint {fov_deg:g} deg is outside {lo:g}-{hi:g} deg")
        return cls(max(lo, fov_deg / (1 + HINT_TOLERANCE)), min(hi, fov_deg * (1 + HINT_TOLERANCE)))

    @classmethod
    def blind(cls) -> FieldRange:
        return cls(*BLIND_FOV_DEG)

    @classmethod
    def of(cls, fov_deg: float | None = None, fov_range: tuple[float, float] | None = None) -> FieldRange:
        """A hint's range, a range, or blind with neither; ValueError (one line) for both."""
        if fov_deg is not None and fov_range is not None:
            raise ValueError("give a field-of-view hint or a range, not both")
        if fov_deg is not None:
            return cls.hint(float(fov_deg))
        if fov_range is not None:
            lo, hi = (float(v) for v in fov_range)
            return cls(lo, hi)
        return cls.blind()

    def focal_brackets(self, width: int) -> list[tuple[float, float]]:
        """(nominal focal length px, relative half-range) of each bracket, the longest focal
        length (narrowest field) first."""
        f_lo = width / 2.0 / math.tan(math.radians(self.hi_deg) / 2.0)
        f_hi = width / 2.0 / math.tan(math.radians(self.lo_deg) / 2.0)
        n = max(1, math.ceil(math.log(f_hi / f_lo) / math.log(BRACKET_RATIO)))
        ratio = (f_hi / f_lo) ** (1.0 / n)
        half = math.sqrt(ratio) - 1.0
        return [(f_lo * ratio ** (k + 0.5), half * 1.0001) for k in reversed(range(n))]


@dataclass(frozen=True)
class SkyFit:
    """A hypothesis the search took, or its best one: focal length (px), attitude ``a``
    (v_sensor = a @ v_icrs), detections matched of those compared, catalog stars predicted on the
    array, the false-alarm probability
    over the search (the single hypothesis' chance times those checked) and the hypotheses
    checked."""

    f: float
    a: np.ndarray
    matched: int
    compared: int
    in_view: int
    false_alarm: float
    checks: int

    def fov_deg(self, width: int) -> float:
        """Horizontal field of view (deg) of the focal length."""
        return math.degrees(2.0 * math.atan(width / 2.0 / self.f))


@dataclass(frozen=True)
class SkyResult:
    """What a search found over ``fov``: the hypothesis it took (None: none was certain enough),
    the candidates for the field's own identification (the taken one, else the best checked
    ones of distinct focal lengths, least false alarm first), the hypotheses checked, and
    whether ``max_checks`` stopped it."""

    fov: FieldRange
    taken: SkyFit | None
    candidates: list[SkyFit]
    checks: int
    stopped: bool = False


#: Candidates a search without a certain hypothesis hands on, and how far apart their focal
#: lengths must be (relative).
CANDIDATES, DISTINCT_F = 2, 0.03


def _distinct(fits: list[SkyFit]) -> list[SkyFit]:
    """The :data:`CANDIDATES` least-false-alarm fits of distinct focal lengths."""
    out: list[SkyFit] = []
    for fit in sorted(fits, key=lambda f: (f.false_alarm, -f.matched, f.checks)):
        if fit.matched >= 5 and all(abs(fit.f / o.f - 1.0) > DISTINCT_F for o in out):
            out.append(fit)
        if len(out) == CANDIDATES:
            break
    return out


class SkyRun:
    """One frame's search, advanced to a count of hypotheses checked and on again from there."""

    def __init__(self, fov: FieldRange, checked):
        self.fov, self._checked = fov, checked
        self.fits: list[SkyFit] = []
        self.exhausted = False

    @property
    def checks(self) -> int:
        return len(self.fits)

    def advance(self, max_checks: int) -> SkyResult:
        """Check hypotheses until one is taken (false alarm under :data:`FALSE_ALARM`), the
        search runs out, or ``max_checks`` in all have been checked."""
        while self.checks < max_checks:
            fit = next(self._checked, None)
            if fit is None:
                self.exhausted = True
                break
            self.fits.append(fit)
            if fit.false_alarm <= FALSE_ALARM:
                return SkyResult(self.fov, fit, [fit], self.checks)
        return SkyResult(self.fov, None, _distinct(self.fits), self.checks, stopped=not self.exhausted)


class SkySearch:
    """The search over one whole-sky :class:`PatternIndex` (its stars brightest first)."""

    def __init__(self, index: PatternIndex, mag: np.ndarray):
        self.index, self.mag = index, np.asarray(mag, float)[: len(index.vec)]

    @cached_property
    def _tree(self) -> cKDTree:
        return cKDTree(self.index.vec)

    def search(
        self, x: np.ndarray, y: np.ndarray, width: int, height: int, fov: FieldRange, max_checks: int = MAX_CHECKS
    ) -> SkyResult:
        """The search over detections ``x, y`` (px, brightest first, clean ones only), at most
        ``max_checks`` hypotheses."""
        return self.start(x, y, width, height, fov).advance(max_checks)

    def start(self, x: np.ndarray, y: np.ndarray, width: int, height: int, fov: FieldRange) -> SkyRun:
        """A search that goes on where it stopped (:meth:`SkyRun.advance`)."""
        return SkyRun(fov, self._checked(x, y, width, height, fov))

    def _checked(self, x, y, width: int, height: int, fov: FieldRange):
        """Every hypothesis checked, in the search's order (a generator: the work as asked for)."""
        brackets = fov.focal_brackets(width)
        cameras = [(CameraModel.pinhole(width, height, f), h) for f, h in brackets]
        checks, tried = 0, set()
        # rank by rank (the patterns whose faintest member is the 4th brightest detection, then
        # the 5th, ...): a rank's keys are looked up only when the checks before it are done
        for rank in range(3, min(PATTERN_STARS, len(x))):
            matches = scale_free.pattern_matches_many(x, y, cameras, self.index, rank + 1, TOLERANCE, rank)
            for b, m in _plate_order(matches):
                key = (tuple(matches[b].groups[m]), matches[b].catalog_vec[m].tobytes())
                if key in tried:  # the same match from a neighbouring bracket
                    continue
                tried.add(key)
                hyp = matches[b].hypothesis(m)
                if hyp is not None:
                    checks += 1
                    yield self.check(x[:CHECK_STARS], y[:CHECK_STARS], width, height, hyp, checks)

    def check(self, x, y, width: int, height: int, hyp: scale_free.Hypothesis, checks: int) -> SkyFit:
        """The hypothesis refined and checked against the detections (module docstring);
        ``checks`` the hypotheses checked so far, this one included."""
        cam = CameraModel.pinhole(width, height, hyp.f)
        stars = _SkyStars(self, _stars_for(cam))
        refined = scale_free.refine(x, y, cam, hyp, stars, radii_px=REFINE_RADII_PX)
        n = len(x)
        if refined is None:
            return SkyFit(hyp.f, hyp.a, 0, n, 0, 1.0, checks)
        fitted, det, _, res = refined
        a = res.attitudes[0]
        in_view = max(stars.in_view(fitted, a), len(det))
        r = REFINE_RADII_PX[-1]
        p = min(1.0, in_view * math.pi * r * r / (width * height))  # one detection's chance
        extra = len(det) - 4  # beyond the pattern's own four
        trials = max(n - 4, extra)
        single = float(betainc(extra, trials - extra + 1, p)) if extra > 0 else 1.0  # P(at least extra)
        return SkyFit(fitted.f, a, len(det), n, in_view, min(1.0, single * checks), checks)


#: Match radii of a check's refinement (``scale_free.refine``), px; the last one counts.
REFINE_RADII_PX = (30.0, 10.0, 4.0, 2.5)


def _stars_for(cam: CameraModel) -> float:
    """The faintest sky star (V) a check of this camera uses: ``sky_patterns.magnitude_limit`` of
    its minor half-field, one magnitude deeper (``CatalogDesign.for_field``'s verification
    stars)."""
    return magnitude_limit(math.degrees(cam.fov_half_angle_minor)) + 1.0


class _SkyStars:
    """The sky table's stars to a magnitude, as ``scale_free.refine`` asks a catalog for them."""

    def __init__(self, search: SkySearch, faintest: float):
        self.vec = search.index.vec
        self._tree = search._tree
        self._n = int(np.searchsorted(search.mag, faintest, "right"))

    def stars_within(self, direction: np.ndarray, radius: float, deep: bool = False) -> np.ndarray:
        idx = np.asarray(self._tree.query_ball_point(direction, chord_of_angle(radius)), np.int64)
        return np.sort(idx[idx < self._n])

    def in_view(self, cam: CameraModel, a: np.ndarray) -> int:
        """Stars of this depth the camera at attitude ``a`` puts on its array."""
        near = self.stars_within(a[2], cam.fov_half_angle_diagonal * 1.2)
        return int(np.count_nonzero(cam.in_frame(*cam.vector_to_pixel(self.vec[near] @ a.T))))


def _plate_order(matches: list[scale_free.PatternMatches]) -> list[tuple[int, int]]:
    """(bracket, match) of every bracket's matches, brightness rank first (a pattern's faintest
    member), key distance next."""
    rows = []
    for b, m in enumerate(matches):
        rank = m.groups[:, 3] if len(m.groups) else np.zeros(0, np.int64)
        rows += [(int(rank[k]), float(m.distance[k]), b, k) for k in range(len(m.distance))]
    rows.sort()
    return [(b, k) for _, _, b, k in rows]
