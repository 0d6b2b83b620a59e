"""The types of one frame's solve: its configuration (:class:`PipelineParams`, the optics search's
:class:`OpticsSearch`), its answer (:class:`PipelineOutput`, with the optics fitted to it,
:class:`OpticsFit`, and the seconds and counted work of its stages, :class:`StageTimings`), what
one identification works on (:class:`SolveInput`), and the constants they default to.

Units: px, seconds, radians unless a name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from firmware_model.camera import CameraModel
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.ident.budget import Stop
from firmware_model.ident.solver import SolveParams, SolveResult
from firmware_model.ident.strategy import IdentifyTimings
from firmware_model.pipeline.exclusion import ExclusionLimits
from firmware_model.pipeline.extract import ExtractParams, StarList
from protocol.result import Status

if TYPE_CHECKING:  # the index's module compiles kernels: the types alone here
    from firmware_model.pipeline.pattern_index import PatternIndex

#: Floor on the per-axis centroid noise fed to the solver (px): covers camera-model and
#: optical residuals that the photon-noise covariance of the fit does not know about.
CENTROID_SIGMA_FLOOR_PX = 0.1

#: Centroid noise assumed when the fit gave no covariance (centre-of-gravity fallback), px.
UNKNOWN_CENTROID_SIGMA_PX = 1.0
#: Floor for stars whose fit is flagged untrusted (saturated, blended, poor fit, edge), px. Such
#: stars keep their place in the geometry with this weight; saturated or blended stars lose
#: their colour (the identification then uses their geometry alone).
UNTRUSTED_CENTROID_FLOOR_PX = 0.5

#: Detections whose fitted centroid is less certain than this (px, 1-sigma) are not used.
MAX_CENTROID_SIGMA_PX = 3.0

#: Stage names reported in the result extension, in order (fields of :class:`StageTimings`).
STAGES = ("detect", "fit", "vectors", "identify", "attitude", "total")
#: Set-up stages a solve may pay for before its frame's own work, reported beside :data:`STAGES`
#: off the device (``timings_s``): ``index`` the catalog's pattern index for the field, ``catalog``
#: building or loading the catalog, ``compile`` loading or compiling the kernels. The device does
#: all three before it says ``listening`` or at a catalog COMMIT, so a GO reports none of them.
SETUP_STAGES = ("index", "catalog", "compile")

#: Pattern seeds one frame's optics search may refine (``OpticsSearch.max_seeds``).
MAX_SEEDS = 48
#: Verifications after which a frame starts no further seed (``OpticsSearch.max_verifications``).
MAX_FRAME_VERIFICATIONS = 2000


@dataclass
class StageTimings(IdentifyTimings):
    """Seconds per pipeline stage (:data:`STAGES`): detection, centroid fit, camera vectors (from
    the extraction), identification and attitude (every solve of the frame, the optics search's
    included), and the whole frame; then the set-up stages (:data:`SETUP_STAGES`), which ``total``
    includes: the whole time the caller waited."""

    detect: float = 0.0
    fit: float = 0.0
    vectors: float = 0.0
    total: float = 0.0
    index: float = 0.0
    catalog: float = 0.0
    compile: float = 0.0

    def to_dict(self) -> dict[str, float]:
        """``{stage: seconds}``: :data:`STAGES`, then the set-up stages that took any time."""
        out = {name: getattr(self, name) for name in STAGES}
        out.update({name: getattr(self, name) for name in SETUP_STAGES if getattr(self, name) > 0})
        return out


@dataclass(frozen=True)
class OpticsSearch:
    """The settings of the optics search (``firmware_model.pipeline.optics_search``: lost in space
    with a datasheet camera, as plate solvers do it) and of the per-solve fit of focal length and
    k1.

    Patterns: the brightest ``n_bright`` clean detections matched as scale-free 4-star patterns,
    the ``first_tier_hypotheses`` first matches among the brightest ``first_tier`` first, rank by
    rank; edge ratios within ``pattern_tolerance``, focal length within ``focal_range`` (fraction)
    of the nominal. Fit: k1 fitted with at least ``k1_min_stars`` matched stars, no fit under
    ``min_stars``; fitted optics replace the camera when they move a corner by more than
    ``refit_px`` (px, and 3 sigma of the fit) or fit the stars ``optics_search.REFIT_RMS_RATIO``
    times better. Budget (counted, never the clock): at most ``max_seeds`` pattern seeds refined,
    no seed started once the frame has made ``max_verifications`` verifications.
    ``focal_search 0`` on the device (``PipelineParams.optics=None``) takes the camera as
    calibrated: no search and no refit; on the geometric route the first tier of ``OpticsSearch()``
    still seeds a verification with it before the matchers run."""

    focal_range: float = 0.05
    n_bright: int = 20
    pattern_tolerance: float = 0.01
    k1_min_stars: int = 6
    min_stars: int = 4
    refit_px: float = 1.0
    max_seeds: int = MAX_SEEDS
    max_verifications: int = MAX_FRAME_VERIFICATIONS
    first_tier: int = 8
    first_tier_hypotheses: int = 4


@dataclass
class OpticsFit:
    """Optics fitted to the matched stars of one solve: the camera (principal point held at the
    nominal one: on a narrow field it is degenerate with the attitude), 1-sigma of each fitted
    parameter (``f`` px, ``k1``), RMS residual (px), stars used, and ``focal_scale`` the focal
    length of the pattern match that found the answer over the nominal one (NaN: no search)."""

    camera: CameraModel
    sigmas: dict
    residual_rms_px: float
    n_stars: int
    focal_scale: float = float("nan")
    #: the attitude covariance (rad^2, sensor axes) the fitted parameters' uncertainty adds
    #: (``CalibrationResult.camera_attitude_covariance``)
    attitude_covariance: np.ndarray | None = None
    #: the fitted stars: detection rows (of the answer's star list) and catalog indices
    rows: np.ndarray | None = None
    cat: np.ndarray | None = None


@dataclass(frozen=True)
class PipelineParams:
    """Pipeline configuration. ``colour_beta`` is the eq. 24 correction (6 numbers) or None;
    ``solve`` is the solver configuration (its colour sigmas are raised to the catalog's design
    values, its field of view defaults to the camera's); the per-detection direction noise is
    derived from the fit covariance (with the floor ``centroid_floor_px``) unless ``fixed_sigma_px``
    is set.

    ``photometric_gate`` (mag, or None to disable): a low-confidence consensus may be caused by
    detections fainter than the catalog holds, which the eta test of Enright & McVittie counts
    against the match. The pipeline then estimates every detection's magnitude from the zero point
    of the matched stars, drops those fainter than the catalog limit plus this margin, and solves
    again; the second answer is taken only if it is high-confidence and agrees with the first.

    ``geometric_density_factor``: the geometric (4-star) method sees only the brightest
    detections, this factor times the catalog stars expected in the field
    (``strategy.geometric_detection_cap``), in one solve. ``geometric_fallback``: when that 4-star
    match finds nothing, the consensus matcher of Enright & McVittie runs on geometry alone
    (colours unknown), which tolerates missing and extra stars far better; its answers are labelled
    ``geometric-consensus``. ``colour_fallback``: in ``auto`` mode a colour frame that the colour
    matcher cannot solve with high confidence (colours biased beyond the catalog's noise model,
    e.g. through the atmosphere before calibration, or gamma-encoded sRGB images) is solved on
    geometry alone, as a mono frame would be; that answer is taken when the colour matcher found
    none or when it is high-confidence.

    ``optics``: the uncalibrated-optics search and the per-solve focal-length/distortion fit
    (:class:`OpticsSearch`; None takes the camera as calibrated: neither runs).

    ``flight_deadline_s``: flight timing only (``st16-device --timing realistic``): seconds after
    the frame's extraction began past which every search stops (``budget.SearchBudget``) and the
    answer says the deadline was missed; None, the default: counted budgets alone, the same
    answer on any machine.

    ``exclusion``: the bright-body exclusion angles (``exclusion.ExclusionLimits``; None: no
    check, no BLINDED status)."""

    extract: ExtractParams = ExtractParams()
    solve: SolveParams = SolveParams()
    colour_beta: tuple | None = None
    fixed_sigma_px: float | None = None
    photometric_gate: float | None = 0.1
    geometric_density_factor: float = 1.5
    geometric_fallback: bool = True
    colour_fallback: bool = True
    optics: OpticsSearch | None = OpticsSearch()
    centroid_floor_px: float = CENTROID_SIGMA_FLOOR_PX
    flight_deadline_s: float | None = None
    exclusion: ExclusionLimits | None = ExclusionLimits()


def with_psf_sigma(params: PipelineParams, sigma_px: float | None) -> PipelineParams:
    """``params`` with the PSF Gaussian sigma fixed to ``sigma_px`` (an override of the per-frame
    measurement; None measures again)."""
    return replace(params, extract=replace(params.extract, psf_sigma_px=sigma_px))


@dataclass
class PipelineOutput:
    """One frame's answer: its status and reason, the extracted stars, the rows of them given to
    the solver, the solution, what the frame cost (``timings``) and what else it found."""

    status: Status
    reason: str = ""
    stars: StarList | None = None
    used: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))  #: star rows given to the solver
    solution: SolveResult | None = None
    timings: StageTimings = field(default_factory=StageTimings)  #: seconds per stage (STAGES)
    colour_beta: tuple | None = None  #: the eq. 24 correction the matcher's colours went through
    camera: CameraModel | None = None  #: the camera model the answer was identified with
    optics: OpticsFit | None = None  #: focal length and distortion fitted to the matched stars
    planets: list = field(default_factory=list)  #: ``planets.PlanetLabel`` of detections on a planet / the moon
    fallback_due: bool = False  #: the mono consensus fallback was deferred (``StrategyParams.defer_fallback``)
    omega: np.ndarray | None = None  #: body rate (rad/s, sensor axes) of a tracked answer (``tracking_run``)
    omega_covariance: np.ndarray | None = None  #: its 3x3 covariance ((rad/s)^2)
    in_fov: tuple = ()  #: bodies inside their exclusion angles (``exclusion.check_exclusion``)

    @property
    def ok(self) -> bool:
        return self.status is Status.OK

    @property
    def stopped(self) -> Stop:
        """What stopped a search of this frame early (``budget.Stop``), if anything."""
        return self.timings.stopped


@dataclass(frozen=True)
class SolveInput:
    """What one identification of a frame works on: its extracted ``stars`` (``stars.vectors``
    through ``camera``), the ``camera`` model, the ``catalog`` matched against and the pattern
    index its patterns are looked up in (``patterns``; None: the catalog's own for the camera's
    field, ``scale_free.catalog_patterns``)."""

    stars: StarList
    camera: CameraModel
    catalog: OnboardCatalog
    patterns: PatternIndex | None = None

    def with_camera(self, camera: CameraModel) -> SolveInput:
        """The same stars, catalog and patterns seen through ``camera`` (their directions recomputed)."""
        return SolveInput(through_camera(self.stars, camera), camera, self.catalog, self.patterns)


def through_camera(stars: StarList, camera: CameraModel) -> StarList:
    """``stars`` with their directions (``vectors``) through ``camera``."""
    return replace(stars, vectors=camera.pixel_to_vector(stars.x, stars.y))
