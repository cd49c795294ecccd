"""The settings of a match (``MatchOptions``), checked when made.

Units: metres and radians; K (``prior_weight``) in discrepancy units per metre.
"""

import dataclasses
from dataclasses import dataclass
from typing import Literal, Optional

import numpy as np

from ._blur import BLUR_KINDS
from ._engines import ENGINES
from ._errors import InvalidOptionError, shown

__all__ = ["MatchOptions"]

XTOL_DEFAULT = {"newton": 0.25, "bfgs": 0.05}
MAX_OPTION = 1e9                 # metres (blur, steps), metres per radian, K: far beyond any use, short of overflow
OPTIMIZERS = tuple(XTOL_DEFAULT)
INTERPOLATIONS = ("nearest", "bilinear")
EVIDENCE = ("trinary", "probability")
GRID_EDGES = ("free", "unknown")
MAX_LEVELS = 8
# MatchOptions.paper(): the fields that differ from the defaults
PAPER_OPTIONS = dict(blur_kind="gaussian", blur=0.5, blur_growth=1.0, unknown_cost=0.0, evidence="probability")


@dataclass(frozen=True)
class MatchOptions:
    """Settings of a match. Units: metres, radians; K in discrepancy units per metre.

    Frozen: make a variant with ``replace`` (or pass fields as keyword arguments to ``match``).

    Attributes
    ----------
    blur : width of the blur (sec. 3.2) on the given maps, metres: the envelope's or the Gaussian's
        standard deviation, or the ramp's length for ``blur_kind="ramp"``.
    blur_kind : "envelope" (the default: the envelope discrepancy of ``_envelope``, walls of each
        map against the other's free space) or the paper's |p_A - p_B| (eq. 6) on a "gaussian"
        (normalised convolution over known cells) or "ramp" blur (see ``_blur``).
    blur_growth : the blur of each coarser pyramid level is this many times wider.
    unknown_cost : what a wall landing on an unknown cell inside the other map's grid pays in the
        envelope discrepancy (0: not compared, as the paper treats unknown cells).
    grid_edge : what a wall landing off the other map's grid pays in the envelope discrepancy:
        "free" (nothing: a grid's edge is often where a map was cropped, and charging for it would
        make the crop structure) or "unknown" (``unknown_cost``, as on an unknown cell no wall
        reaches: for maps whose grid is only the box around what a laser saw, whose edge would
        otherwise be structure; measured on the mapping loop's loop closures in docs/slam.md).
    evidence : how grey probabilities enter: "trinary" (as ROS map_saver writes them: p > 0.65
        occupied, p < 0.196 free, else unknown; ``_grid.trinary``) or "probability" (as given).
    prior_weight : K of eq. (8), discrepancy units per metre of ||r - r0||; None (the default)
        scales it with B: K = prior_weight_per_cell * (known cells of B).
    prior_weight_per_cell : K per known cell of B when ``prior_weight`` is None. The discrepancy
        grows with the maps, so a fixed K would weigh the prior ten times more on a map ten times
        smaller; 8.6e-4 gives K = 100 on the paper's corridor.
    rotation_scale : L of eq. (7), metres per radian.
    step : finite-difference step eps for x and y (eq. 10-12), metres; None = A's resolution.
    rotation_step : eps for theta, radians, a rotation about B's centroid; None = step / S, where S
        is the rms distance of B's known cells from their centroid (a typical cell moves by eps).
    max_step : longest step (BFGS) or largest trust region (Newton) in scaled units (metres),
        None = max(blur / 2, 4 * step).
    xtol : the optimiser stops when a step (BFGS: taken; Newton: proposed by its model) is shorter
        than xtol * step; None = 0.25 for Newton, 0.05 for BFGS.
    gtol : ... or when the gradient norm of h is below gtol * K.
    max_iterations : budget on the coarsest level: BFGS iterations, or Newton launches after the
        first.
    levels : pyramid levels for coarse-to-fine matching: 1 optimises on the maps as given; n > 1
        starts on a copy with cells 2**(n-1) times larger and refines on each finer level, the
        last being the given maps. The covariance is always taken on the given maps.
    refine_iterations : budget on each finer level (levels > 1): Newton launches after the first
        (from a trust region of 4 cells, 1 on the given maps); for BFGS, iterations on the given
        maps (of at most two cells), the levels between getting only the compass search.
    refine_xtol : on the finer levels, Newton stops when its model's step is shorter than
        refine_xtol * step (``xtol`` holds on the coarsest level, which only has to find the
        basin). Stopping at a quarter of a cell there left laser submaps 1 degree off and the
        pose 2-4 times farther from the truth than settling does (bench/TUNING.md).
    optimizer : None (default): "bfgs" for the paper's e with bilinear interpolation, else "newton".
        "newton": trust-region Newton on the stencil's own Hessian, one launch
        of the 25 poses of eq. (10)-(12) per iteration, whose last launch also gives the
        covariance; "bfgs": the paper's BFGS with the 13-pose gradient stencil (eq. 9-10),
        finished by a compass search, then one launch for the Hessian.
    interpolation : "nearest" (the paper's eq. 6: B's cell centre looks up A's cell) or
        "bilinear" (beyond the paper). For the paper's e: A interpolated between its cell centres,
        a cell of B counting where the four around it are known; bilinear e is continuous away
        from unknown cells, its gradient analytic (one pose per evaluation) and its Hessian, also
        for the covariance, the central difference of gradients one step either side (7 poses).
        For the "envelope" discrepancy: each wall's cost (``_envelope``) interpolated between the
        four cell centres around where it lands, so that e no longer steps as walls cross cell
        boundaries; four lookups a wall, derivatives from the stencils as with "nearest".
    covariance_scale : the proportionality factor of eq. (11), cov = scale * H(e)^-1.
    engine : "taichi" (batched kernels) or "numpy" (the plain reference, for baselines).
    count_overlap : count the overlap at the answer (``MatchResult.overlap``). With the envelope
        discrepancy that count is a launch over B's known cells of its own (0.3-0.7 ms of a
        mapping loop's 2-3 ms scan match, 2026-12-06); False leaves ``overlap`` None there and only
        checks that the maps still overlap (``Status.SEPARATED``) with the walls the envelope's
        launch counts anyway (the paper's e counts it in its own launches and reports it either
        way). The pose, covariance and verdict are the same either way.

    Examples
    --------
    >>> from taichi_match import MatchOptions
    >>> MatchOptions().method, MatchOptions(interpolation="nearest", optimizer="bfgs").method
    ('newton', 'bfgs')
    >>> MatchOptions.paper().blur_kind
    'gaussian'
    >>> MatchOptions(levels=0)
    Traceback (most recent call last):
    ...
    taichi_match._errors.InvalidOptionError: levels must be an integer in 1..8; got 0
    """

    blur: float = 0.1
    blur_kind: Literal["gaussian", "ramp", "envelope"] = "envelope"
    blur_growth: float = 2.0
    unknown_cost: float = 0.3
    grid_edge: Literal["free", "unknown"] = "free"
    evidence: Literal["trinary", "probability"] = "trinary"
    prior_weight: Optional[float] = None
    prior_weight_per_cell: float = 8.6e-4
    rotation_scale: float = 2.0
    step: Optional[float] = None
    rotation_step: Optional[float] = None
    max_step: Optional[float] = None
    xtol: Optional[float] = None
    gtol: float = 1e-3
    max_iterations: int = 100
    levels: int = 3
    refine_iterations: int = 8
    refine_xtol: float = 0.05
    optimizer: Optional[Literal["newton", "bfgs"]] = None
    interpolation: Literal["nearest", "bilinear"] = "nearest"
    covariance_scale: float = 1.0
    engine: Literal["taichi", "numpy"] = "taichi"
    count_overlap: bool = True

    def __post_init__(self):
        _check_number("blur_growth", self.blur_growth, minimum=1.0)
        _check_number("unknown_cost", self.unknown_cost, minimum=0.0)
        if self.unknown_cost > 1.0:
            raise InvalidOptionError(f"unknown_cost must be in [0, 1]; got {shown(self.unknown_cost)}")
        if self.blur_growth > 16.0:
            raise InvalidOptionError(f"blur_growth must be at most 16; got {shown(self.blur_growth)}")
        for name in ("blur", "prior_weight_per_cell", "gtol", "refine_xtol"):
            _check_number(name, getattr(self, name), minimum=0.0)
        _check_number("covariance_scale", self.covariance_scale, minimum=0.0, strict=True)
        for name in ("blur", "rotation_scale", "prior_weight", "prior_weight_per_cell", "step", "max_step"):
            value = getattr(self, name)
            if value is not None and isinstance(value, (int, float, np.integer, np.floating)) and value > MAX_OPTION:
                raise InvalidOptionError(f"{name} must be at most {MAX_OPTION:g}; got {shown(value)}")
        if self.xtol is not None:
            _check_number("xtol", self.xtol, minimum=0.0)
        if self.prior_weight is not None:
            _check_number("prior_weight", self.prior_weight, minimum=0.0)
        _check_number("rotation_scale", self.rotation_scale, minimum=0.0, strict=True)
        for name in ("step", "rotation_step", "max_step"):
            if getattr(self, name) is not None:
                _check_number(name, getattr(self, name), minimum=0.0, strict=True)
        _check_integer("max_iterations", self.max_iterations, minimum=0)
        _check_integer("levels", self.levels, minimum=1, maximum=MAX_LEVELS)
        _check_integer("refine_iterations", self.refine_iterations, minimum=0)
        if not (isinstance(self.grid_edge, str) and self.grid_edge in GRID_EDGES):
            raise InvalidOptionError(f"grid_edge must be one of {GRID_EDGES}; got {shown(self.grid_edge)}")
        if self.evidence not in EVIDENCE:
            raise InvalidOptionError(f"evidence must be one of {EVIDENCE}; got {self.evidence!r}")
        if self.blur_kind not in BLUR_KINDS:
            raise InvalidOptionError(f"blur_kind must be one of {BLUR_KINDS}; got {self.blur_kind!r}")
        if self.interpolation not in INTERPOLATIONS:
            raise InvalidOptionError(f"interpolation must be one of {INTERPOLATIONS}; got {self.interpolation!r}")
        if self.optimizer is not None and self.optimizer not in OPTIMIZERS:
            raise InvalidOptionError(f"optimizer must be one of {OPTIMIZERS} or None; got {self.optimizer!r}")
        if self.engine not in ENGINES:
            raise InvalidOptionError(f"engine must be one of {ENGINES}; got {self.engine!r}")
        if not isinstance(self.count_overlap, (bool, np.bool_)):
            raise InvalidOptionError(f"count_overlap must be True or False; got {shown(self.count_overlap)}")

    @classmethod
    def paper(cls, **overrides) -> "MatchOptions":
        """The paper's discrepancy, |p_A - p_B| over B's known cells (eq. 6), on maps blurred by a
        0.5 m normalised Gaussian, grey probabilities as given, unknown cells not compared: the
        default before laser-built maps showed its limits (bench/TUNING.md). ``overrides`` are
        further fields."""
        return cls(**{**PAPER_OPTIONS, **overrides})

    def replace(self, **changes) -> "MatchOptions":
        """These options with ``changes`` (field names) applied; an unknown name raises
        ``InvalidOptionError``.

        Examples
        --------
        >>> from taichi_match import MatchOptions
        >>> MatchOptions().replace(blur=0.2, levels=2).levels
        2
        >>> MatchOptions().replace(blurr=0.2)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        taichi_match._errors.InvalidOptionError: unknown option(s) ['blurr']; the options are ...
        """
        if not changes:
            return self
        names = [f.name for f in dataclasses.fields(self)]
        unknown = sorted(set(changes) - set(names))
        if unknown:
            raise InvalidOptionError(f"unknown option(s) {unknown}; "
                                     f"the options are the fields of MatchOptions: {names}")
        return dataclasses.replace(self, **changes)

    @property
    def step_tolerance(self):
        """xtol, or its default for the optimizer."""
        return self.xtol if self.xtol is not None else XTOL_DEFAULT[self.method]

    @property
    def method(self):
        """The optimizer in use: ``optimizer``, or by default "bfgs" for the paper's e with bilinear
        interpolation (whose analytic gradient leaves out the jumps where B's cells cross onto
        unknown cells of A, which a Newton model then misses; measured in bench/ABLATION.md), and
        "newton" otherwise (the envelope discrepancy's derivatives come from the stencils)."""
        if self.optimizer is not None:
            return self.optimizer
        return "bfgs" if self.analytic_gradient else "newton"

    @property
    def analytic_gradient(self) -> bool:
        """Whether e's gradient is analytic: the paper's e looked up bilinearly (the envelope's
        derivatives always come from the stencils)."""
        return self.interpolation == "bilinear" and self.blur_kind != "envelope"

    def weight(self, known_cells_b):
        """K of eq. (8) for a map B with ``known_cells_b`` known cells."""
        if self.prior_weight is not None:
            return float(self.prior_weight)
        return self.prior_weight_per_cell * known_cells_b

    def steps(self, resolution_a, radius_b):
        """(eps_x, eps_y, eps_theta) for a map A of the given resolution and a map B whose known
        cells lie at rms distance ``radius_b`` from its frame's origin."""
        eps = self.step if self.step is not None else resolution_a
        eps_theta = self.rotation_step if self.rotation_step is not None else eps / radius_b
        return np.array([eps, eps, eps_theta])


def _check_number(name, value, *, minimum, strict=False):
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidOptionError(f"{name} must be a number; got {shown(value)}")
    if not np.isfinite(value) or value < minimum or (strict and value == minimum):
        raise InvalidOptionError(f"{name} must be finite and {'>' if strict else '>='} {minimum}; got {shown(value)}")


def _check_integer(name, value, *, minimum, maximum=None):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum \
            or (maximum is not None and value > maximum):
        bounds = f">= {minimum}" if maximum is None else f"in {minimum}..{maximum}"
        raise InvalidOptionError(f"{name} must be an integer {bounds}; got {shown(value)}")
