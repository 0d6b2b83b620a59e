"""What a solve takes and gives: solver modes and methods, parameters, the result, input cleaning.

The order of methods and fallbacks and the confidence decision are in
:mod:`firmware_model.ident.strategy` (``strategy.solve`` on star vectors, ``strategy.identify`` on a
frame's detections); this module holds the types they share.

``Mode`` (``SolveParams.mode``, the parameter file's ``mode``): ``auto`` uses colour consensus
when the frame and the catalog both carry colour, geometric matching otherwise; ``colour`` /
``geometric`` force one. ``Method`` names how an answer was found; its wire code is
``protocol.result.MethodCode``.

Input cleaning (:func:`clean`): rows that are not finite or have zero norm are dropped; vectors
are normalised; detections closer than the catalog's ``phi_min`` (unresolvable duplicates, or a
false detection on a star) are both dropped: which of the two is the star cannot be told; beyond
``max_detections`` the faintest are dropped. Every drop is counted in ``SolveResult.notes``.
Indices in the result refer to the caller's input rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from firmware_model.catalog.onboard import OnboardCatalog, angle_between
from firmware_model.ident.budget import Stop
from firmware_model.ident.consensus import ConsensusParams, Outcome
from firmware_model.ident.four_star import FourStarParams
from firmware_model.ident.pair_match import sigma_phi_from_centroid
from firmware_model.ident.triangle import TriangleParams
from firmware_model.ident.verify import FieldOfView, VerifiedMatch, VerifyParams
from protocol.result import MethodCode

#: Default bound on the 1-sigma roll of a high-confidence answer (rad): 0.1 deg, the roll error a
#: user stops calling high confidence (docs/identification.md, "Confidence and the attitude's own
#: uncertainty").
MAX_ROLL_SIGMA = float(np.radians(0.1))

#: Default verifications per solve (``SolveParams.max_verifications``): docs/identification.md,
#: "The solve plan", says how it was chosen.
MAX_VERIFICATIONS = 200

#: Per-axis direction noise of the Enright & McVittie reference design: 0.2 px at f = 7383 px (rad).
REFERENCE_SIGMA_VEC = 0.2 / 7383.1


class Mode(StrEnum):
    """Solver mode (``SolveParams.mode``, the parameter file's ``mode``)."""

    AUTO = "auto"
    COLOUR = "colour"
    GEOMETRIC = "geometric"

    @classmethod
    def parse(cls, text: object) -> Mode:
        """The mode ``text`` names; ValueError with a one-line reason for anything else."""
        if isinstance(text, str) and text in cls._value2member_map_:
            return cls(text)
        names = [m.value for m in cls]
        raise ValueError(f"mode must be {', '.join(names[:-1])} or {names[-1]}, got {text!r}")


class Method(StrEnum):
    """How an answer was identified (``SolveResult.method``); :attr:`code` is its wire value."""

    COLOUR = "colour"  #: colour consensus (Enright & McVittie)
    GEOMETRIC = "geometric"  #: 4-star voting (Dong et al.) with the triangle fallback
    GEOMETRIC_CONSENSUS = "geometric-consensus"  #: the consensus matcher on geometry alone
    PATTERN = "pattern"  #: scale-free pattern search (uncalibrated optics, in the pipeline)
    TRACKING = "tracking"  #: predicted from the last attitude and rate (``ident.tracking``)

    @property
    def code(self) -> MethodCode:
        return MethodCode[self.name]


def method_code(method: Method | None) -> int:
    """The result structure's ``ext.method`` for ``method`` (0: none)."""
    return int(method.code if method is not None else MethodCode.NONE)


@dataclass(frozen=True)
class SolveParams:
    """Solver configuration.

    mode: a :class:`Mode` ("auto": colour when available, else geometric; "colour"; "geometric").
        Text is accepted; an unknown mode gives a NO_MATCH answer saying so.
    sigma_vec: per-axis direction noise of a detection (rad), scalar or one per detection;
        it weights the q-method and sets the verification gates.
    sigma_phi: pair arc-length noise (rad); None means Enright & McVittie eq. 18, ``2 sigma_vec``.
    sigma_rg, sigma_bg: colour-ratio noise.
    fov: the sensor's field of view for the coverage test; None means a cone through the
        outermost detection.
    max_verifications: hypotheses one solve may verify (``budget.SearchBudget``, counted; a
        solve that runs out answers with what it verified, NO_MATCH naming the count when none).
    deadline: flight timing only: a ``time.perf_counter`` value past which the search stops
        (``budget.SearchBudget``); None, the default: counts alone decide.
    max_detections: detections considered (brightest first); the matchers use fewer.
    max_roll_sigma: the largest 1-sigma roll (rotation about the boresight, rad) a high-confidence
        answer may have (:data:`MAX_ROLL_SIGMA`; ``strategy.bound_roll``); inf: no bound.
    noise_probe_px: per-axis centroid noise (px) beyond the announced one that the answer's
        stars are looked for with before the frame's own noise is estimated
        (``strategy.adapt_noise``); 0: trust the announced noise.
    """

    mode: Mode | str = Mode.AUTO
    sigma_vec: float | np.ndarray = REFERENCE_SIGMA_VEC
    sigma_phi: float | None = None
    sigma_rg: float = 0.05
    sigma_bg: float = 0.05
    consensus: ConsensusParams = ConsensusParams()
    four_star: FourStarParams = FourStarParams(stop_after=3, max_groups=6)
    triangle: TriangleParams = TriangleParams()
    verify: VerifyParams = VerifyParams()
    fov: FieldOfView | None = None
    max_verifications: int = MAX_VERIFICATIONS
    deadline: float | None = None
    max_detections: int = 200
    max_roll_sigma: float = MAX_ROLL_SIGMA
    noise_probe_px: float = 1.0

    @property
    def pair_sigma_phi(self) -> float:
        if self.sigma_phi is not None:
            return float(self.sigma_phi)
        return sigma_phi_from_centroid(float(np.median(np.atleast_1d(self.sigma_vec))), 1.0)


@dataclass
class SolveTimings:
    """Seconds spent in one solve: input cleaning, matching (verification excluded), verification
    of the matcher's hypotheses, and the whole solve (0 for a stage that did not run)."""

    validate: float = 0.0
    match: float = 0.0
    verify: float = 0.0
    total: float = 0.0


@dataclass
class SolveResult:
    """Solution of one frame.

    status: HIGH_CONFIDENCE, LOW_CONFIDENCE or NO_MATCH (Enright & McVittie's three classes);
    reason: why it is not high confidence (empty otherwise);
    q_icrs_to_sensor: scalar-first unit quaternion, ``v_sensor = A(q) @ v_icrs`` (None if no match);
    covariance: 3x3 attitude-error covariance about the sensor axes (rad^2);
    matched_det / matched_cat / matched_star_id: input row, catalog index and catalog star id
    of each matched star; matched_rg / matched_bg: the catalog colours;
    residuals: per matched star, angle (rad) between measured and predicted direction;
    consensus_size: stars in the matcher's consensus set (before refinement);
    consensus_rms: RMS residual (rad) of the final matched set;
    confidence: coverage of predicted stars times matched fraction of used detections, in [0, 1];
    method: the :class:`Method` (None before one was chosen); timings: :class:`SolveTimings`;
    notes: input cleaning; roll_limited: high confidence but for the roll bound
    (``SolveParams.max_roll_sigma``): the matcher's decision was high, the attitude too loose.
    """

    status: Outcome
    reason: str = ""
    q_icrs_to_sensor: np.ndarray | None = None
    covariance: np.ndarray | None = None
    matched_det: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    matched_cat: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    matched_star_id: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    matched_rg: np.ndarray = field(default_factory=lambda: np.empty(0))
    matched_bg: np.ndarray = field(default_factory=lambda: np.empty(0))
    residuals: np.ndarray = field(default_factory=lambda: np.empty(0))
    consensus_size: int = 0
    consensus_rms: float = float("nan")
    confidence: float = 0.0
    coverage: float = float("nan")  #: matched / predicted catalog stars of the verified match
    chance: float = 1.0  #: chance that its stars beyond two line up by accident (``verify.chance_alignment``)
    method: Method | None = None
    n_used: int = 0
    attempts: int = 0
    timings: SolveTimings = field(default_factory=SolveTimings)
    notes: list[str] = field(default_factory=list)
    roll_limited: bool = False
    verifications: int = 0  #: hypotheses the solve verified (its counted work)
    stopped: Stop = Stop.NONE  #: what stopped the search early, if anything (``budget.Stop``)
    noise_extra: float = 0.0  #: per-axis noise (rad) the residuals showed beyond the announced (strategy.adapt_noise)
    hypotheses: int = 0  #: wrong hypotheses the solve met as well supported as its seed (the chance test's count)

    @property
    def roll_sigma(self) -> float:
        """1-sigma roll (rad): the attitude covariance about the boresight (sensor z); NaN without one."""
        if self.covariance is None:
            return float("nan")
        return float(np.sqrt(max(float(np.asarray(self.covariance)[2, 2]), 0.0)))

    @property
    def matched(self) -> list[tuple[int, int, int]]:
        """(detection index, catalog index, star id) per matched star."""
        return list(zip(self.matched_det.tolist(), self.matched_cat.tolist(), self.matched_star_id.tolist()))

    @property
    def ok(self) -> bool:
        return self.status is not Outcome.NO_MATCH


@dataclass
class CleanScene:
    """Detections that passed :func:`clean`: unit vectors, colours, per-axis noise, the caller's
    row of each (``index_map``) and what was dropped (``notes``)."""

    v: np.ndarray
    rg: np.ndarray
    bg: np.ndarray
    sigma: np.ndarray
    index_map: np.ndarray
    notes: list[str]


def clean(vectors, rg, bg, catalog: OnboardCatalog, params: SolveParams) -> CleanScene | str:
    """Validated arrays (module docstring), or the reason they cannot be used."""
    sigma = params.sigma_vec
    try:
        v = np.asarray(vectors, dtype=float)
    except (TypeError, ValueError):
        return "detection vectors are not numeric"
    if v.ndim != 2 or v.shape[1] != 3:
        return f"detection vectors must have shape (N, 3), got {v.shape}"
    n = len(v)
    cols = []
    for name, c in (("rg", rg), ("bg", bg)):
        if c is None:
            cols.append(np.full(n, np.nan))
            continue
        try:
            c = np.asarray(c, dtype=float).ravel()
        except (TypeError, ValueError):
            return f"{name} is not numeric"
        if len(c) != n:
            return f"{name} has {len(c)} values for {n} detections"
        cols.append(c)
    try:
        s = np.broadcast_to(np.asarray(sigma, dtype=float), (n,)).copy()
    except ValueError:
        return f"sigma_vec must be a scalar or have one value per detection ({n})"
    notes = []
    norm = np.linalg.norm(v, axis=1) if n else np.empty(0)
    good = np.all(np.isfinite(v), axis=1) & (norm > 1e-12) & np.isfinite(s) & (s > 0)
    if (~good).any():
        notes.append(f"dropped {int((~good).sum())} non-finite or zero vector(s)")
    idx = np.nonzero(good)[0]
    v = v[idx] / norm[idx, None]
    if len(v) > 1:
        ang = angle_between(v[:, None, :], v[None, :, :])
        close = np.triu(ang < max(catalog.phi_min, 1e-9), k=1)
        dup = close.any(axis=0) | close.any(axis=1)  # both: which of the two is the star cannot be told
        if dup.any():
            notes.append(f"dropped {int(dup.sum())} detection(s) of pairs closer than phi_min")
            idx, v = idx[~dup], v[~dup]
    if len(idx) > params.max_detections:
        notes.append(f"used the {params.max_detections} brightest of {len(idx)} detections")
        idx, v = idx[: params.max_detections], v[: params.max_detections]
    return CleanScene(v, cols[0][idx], cols[1][idx], s[idx], idx, notes)


def solution_from_match(
    match: VerifiedMatch,
    status: Outcome,
    reason: str,
    index_map: np.ndarray,
    catalog: OnboardCatalog,
    method: Method | None,
    n_used: int,
) -> SolveResult:
    """The solution a verified match stands for (``index_map``: input row of each detection)."""
    att = match.attitude
    return SolveResult(
        status=status,
        reason=reason,
        q_icrs_to_sensor=att.q.copy(),
        covariance=att.covariance,
        matched_det=index_map[match.det],
        matched_cat=match.cat,
        matched_star_id=catalog.star_id[match.cat],
        matched_rg=catalog.rg[match.cat].astype(float),
        matched_bg=catalog.bg[match.cat].astype(float),
        residuals=att.residuals,
        consensus_size=match.n_consensus,
        consensus_rms=att.rms,
        confidence=float(match.coverage if np.isfinite(match.coverage) else 1.0) * min(1.0, match.n / max(n_used, 1)),
        method=method,
        n_used=n_used,
        coverage=float(match.coverage),
        chance=float(match.chance),
    )
