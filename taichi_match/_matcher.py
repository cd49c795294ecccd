"""The public face: options, the result, and the matcher that ties the steps together.

Data flows one way: maps -> prepared (blurred) maps -> batched evaluation of eq. (6) ->
cost h (eq. 8) with its stencil gradient (eq. 10) -> BFGS (eq. 9), finished by a compass-search
polish -> Hessian (eq. 12) -> covariance (eq. 11).
"""

import dataclasses
import functools
import math
import numbers
import threading
import time
import weakref
from dataclasses import dataclass, field
from typing import Literal, Optional

import numpy as np

from ._blur import BLUR_KINDS
from ._bfgs import MESSAGES, Status, minimize_bfgs, polish
from ._cost import (gradient_from_stencil, gradient_stencil, hessian_from_stencil, prior, prior_terms,
                    prior_values)
from ._covariance import (CALIBRATED_COVARIANCE_SCALE, calibrate, centroid_metric, covariance_floor,
                          covariance_from_hessian, plateau_sd)
from ._errors import InvalidMapError, InvalidOptionError
from ._grid import GridMap
from ._kernels import check_not_forked
from ._newton import minimize_newton
from ._prepared import ENGINES, PreparedMap, make_engine
from ._search import RUNNER_UP_FRACTION, SearchOptions, search
from ._se2 import as_pose, wrap_angle
from ._verdict import Evidence, compare_walls, evidence, placed_walls

__all__ = ["MatchOptions", "MatchResult", "Matcher", "match", "CALIBRATED_COVARIANCE_SCALE"]


# Trust region of the Newton driver on entering a finer level, in that level's cells: the
# coarser level left the pose within a few of its own cells (measured in bench/TUNING.md).
ENTRY_RADIUS_CELLS = 4.0          # middle levels
ENTRY_RADIUS_CELLS_FINEST = 1.0   # the given maps
XTOL_DEFAULT = {"newton": 0.25, "bfgs": 0.05}
MAX_OPTION = 1e9                 # metres (blur, steps), metres per radian, K: far beyond any use, short of overflow
OPTIMIZERS = tuple(XTOL_DEFAULT)
INTERPOLATIONS = ("nearest", "bilinear")
EVIDENCE = ("trinary", "probability")
# MatchOptions.paper(): the fields that differ from the defaults
PAPER_OPTIONS = dict(blur_kind="gaussian", blur=0.5, blur_growth=1.0, unknown_cost=0.0, evidence="probability")


@dataclass(frozen=True)
class MatchOptions:
    """Settings of a match. Units: metres, radians; K in discrepancy units per metre.

    blur : width of the blur (sec. 3.2) on the given maps, metres: the envelope's or the Gaussian's
        standard deviation, or the ramp's length for ``blur_kind="ramp"``.
    blur_kind : "envelope" (the default: the envelope discrepancy of ``_envelope``, walls of each
        map against the other's free space) or the paper's |p_A - p_B| (eq. 6) on a "gaussian"
        (normalised convolution over known cells) or "ramp" blur (see ``_blur``).
    blur_growth : the blur of each coarser pyramid level is this many times wider.
    unknown_cost : what a wall landing on an unknown cell inside the other map's grid pays in the
        envelope discrepancy (0: not compared, as the paper treats unknown cells).
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
    optimizer : None (default): "newton" with nearest-cell lookup, "bfgs" with bilinear.
        "newton": trust-region Newton on the stencil's own Hessian, one launch
        of the 25 poses of eq. (10)-(12) per iteration, whose last launch also gives the
        covariance; "bfgs": the paper's BFGS with the 13-pose gradient stencil (eq. 9-10),
        finished by a compass search, then one launch for the Hessian.
    interpolation : "nearest" (the paper's eq. 6: B's cell centre looks up A's cell) or
        "bilinear" (beyond the paper: A interpolated between its cell centres, a cell of B
        counting where the four around it are known). Bilinear e is continuous away from unknown
        cells; its gradient is analytic (one pose per evaluation) and its Hessian, also for the
        covariance, the central difference of gradients one step either side (7 poses).
    covariance_scale : the proportionality factor of eq. (11), cov = scale * H(e)^-1.
    engine : "taichi" (batched kernels) or "numpy" (the plain reference, for baselines).
    """

    blur: float = 0.1
    blur_kind: Literal["gaussian", "ramp", "envelope"] = "envelope"
    blur_growth: float = 2.0
    unknown_cost: float = 0.3
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

    def __post_init__(self):
        _check_number("blur_growth", self.blur_growth, minimum=1.0)
        _check_number("unknown_cost", self.unknown_cost, minimum=0.0)
        if self.unknown_cost > 1.0:
            raise InvalidOptionError(f"unknown_cost must be in [0, 1]; got {self.unknown_cost!r}")
        if self.blur_growth > 16.0:
            raise InvalidOptionError(f"blur_growth must be at most 16; got {self.blur_growth!r}")
        for name in ("blur", "prior_weight_per_cell", "gtol", "refine_xtol"):
            _check_number(name, getattr(self, name), minimum=0.0)
        _check_number("covariance_scale", self.covariance_scale, minimum=0.0, strict=True)
        for name in ("blur", "rotation_scale", "prior_weight", "prior_weight_per_cell", "step", "max_step"):
            value = getattr(self, name)
            if value is not None and isinstance(value, (int, float, np.integer, np.floating)) and value > MAX_OPTION:
                raise InvalidOptionError(f"{name} must be at most {MAX_OPTION:g}; got {value!r}")
        if self.xtol is not None:
            _check_number("xtol", self.xtol, minimum=0.0)
        if self.prior_weight is not None:
            _check_number("prior_weight", self.prior_weight, minimum=0.0)
        _check_number("rotation_scale", self.rotation_scale, minimum=0.0, strict=True)
        for name in ("step", "rotation_step", "max_step"):
            if getattr(self, name) is not None:
                _check_number(name, getattr(self, name), minimum=0.0, strict=True)
        if isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, (int, np.integer)) \
                or self.max_iterations < 0:
            raise InvalidOptionError(f"max_iterations must be an integer >= 0; got {self.max_iterations!r}")
        if isinstance(self.levels, bool) or not isinstance(self.levels, (int, np.integer)) or not 1 <= self.levels <= 8:
            raise InvalidOptionError(f"levels must be an integer in 1..8; got {self.levels!r}")
        if isinstance(self.refine_iterations, bool) or not isinstance(self.refine_iterations, (int, np.integer)) \
                or self.refine_iterations < 0:
            raise InvalidOptionError(f"refine_iterations must be an integer >= 0; got {self.refine_iterations!r}")
        if self.evidence not in EVIDENCE:
            raise InvalidOptionError(f"evidence must be one of {EVIDENCE}; got {self.evidence!r}")
        if self.blur_kind not in BLUR_KINDS:
            raise InvalidOptionError(f"blur_kind must be one of {BLUR_KINDS}; got {self.blur_kind!r}")
        if self.interpolation not in INTERPOLATIONS:
            raise InvalidOptionError(f"interpolation must be one of {INTERPOLATIONS}; got {self.interpolation!r}")
        if self.interpolation == "bilinear" and self.blur_kind == "envelope":
            raise InvalidOptionError('interpolation="bilinear" interpolates the paper\'s |p_A - p_B|: use it with '
                                     'blur_kind="gaussian" or "ramp" (for instance MatchOptions.paper(interpolation='
                                     '"bilinear")), not the "envelope" discrepancy')
        if self.optimizer is not None and self.optimizer not in OPTIMIZERS:
            raise InvalidOptionError(f"optimizer must be one of {OPTIMIZERS} or None; got {self.optimizer!r}")
        if self.engine not in ENGINES:
            raise InvalidOptionError(f"engine must be one of {ENGINES}; got {self.engine!r}")

    @classmethod
    def paper(cls, **overrides) -> "MatchOptions":
        """The paper's discrepancy, |p_A - p_B| over B's known cells (eq. 6), on maps blurred by a
        0.5 m normalised Gaussian, grey probabilities as given, unknown cells not compared: the
        default before laser-built maps showed its limits (bench/TUNING.md). ``overrides`` are
        further fields."""
        return cls(**{**PAPER_OPTIONS, **overrides})

    @property
    def step_tolerance(self):
        """xtol, or its default for the optimizer."""
        return self.xtol if self.xtol is not None else XTOL_DEFAULT[self.method]

    @property
    def method(self):
        """The optimizer in use: ``optimizer``, or by default "newton" with nearest-cell lookup and
        "bfgs" with bilinear interpolation (whose analytic gradient leaves out the jumps where B's
        cells cross onto unknown cells of A, which a Newton model then misses; measured in
        bench/ABLATION.md)."""
        if self.optimizer is not None:
            return self.optimizer
        return "bfgs" if self.interpolation == "bilinear" else "newton"

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


# After a search, a distinct runner-up scoring at least this times the best makes the match
# ambiguous (not accepted): the fraction above which the search proves its runner-ups.
AMBIGUITY = RUNNER_UP_FRACTION


def _ambiguous(hypotheses) -> bool:
    """After a search: no best with a positive score, or a runner-up close to it."""
    if not hypotheses:
        return False
    best = hypotheses[0].score
    return best <= 0 or (len(hypotheses) > 1 and hypotheses[1].score >= AMBIGUITY * best)


def _with(options, overrides):
    """``options`` with ``overrides`` applied; unknown names raise InvalidOptionError."""
    if not overrides:
        return options
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(MatchOptions)})
    if unknown:
        raise InvalidOptionError(f"unknown option(s) {unknown}; the options are the fields of MatchOptions: "
                                 f"{[f.name for f in dataclasses.fields(MatchOptions)]}")
    return dataclasses.replace(options, **overrides)


def _check_number(name, value, *, minimum, strict=False):
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidOptionError(f"{name} must be a number; got {value!r}")
    if not np.isfinite(value) or value < minimum or (strict and value == minimum):
        raise InvalidOptionError(f"{name} must be finite and {'>' if strict else '>='} {minimum}; got {value!r}")


@dataclass(frozen=True)
class MatchResult:
    """The outcome of a match, in the style of ``scipy.optimize.OptimizeResult``.

    pose : r_A2B = (x, y, theta), maps B's frame into A's; theta in (-pi, pi].
    covariance : 3x3 in (x, y, theta) units, ``covariance_scale * H(e)^-1`` with degenerate
        directions given a very large variance (eq. 11).
    information : the 3x3 numeric Hessian of e at ``pose`` (eq. 12), unmodified.
    covariance_floor : the 3x3 covariance that ``calibrated_covariance`` adds: an error spread
        over the plateau where e stays flat while no wall changes cell (``_covariance.plateau_sd``).
    residual : e per wall compared at ``pose`` (``evidence.walls_compared``): how much the maps
        still disagree there; ``calibrated_covariance`` grows with it.
    degenerate : (k, 3) unit vectors in (x, y, theta) along which the maps give (almost) no
        information, e.g. (1, 0, 0) in a corridor along x.
    cost : h at ``pose`` (eq. 8), on the blurred maps; ``prior_weight`` is the K it used.
    discrepancy : e at ``pose``: eq. (6) on the blurred maps, or the envelope discrepancy.
    overlap : number of known cells of B that land on known cells of A at ``pose``.
    initial_pose, iterations, evaluations (poses evaluated), launches (batched evaluations),
    converged, status, message, seconds (wall clock of the whole match).
    accepted : the verdict: True when the pose can be trusted (``converged`` only says the
        optimiser stopped at a minimum). ``evidence`` holds what it rests on: walls compared, the
        share of walls meeting the other map's walls, the share landing on its free space, and
        the largest standard deviation outside degenerate directions (``taichi_match._verdict``).
        After a search, also False when a distinct runner-up scores at least ``AMBIGUITY`` times
        the best (the maps fit two ways: a corridor, a symmetric room) or when the search hit
        its budget of nodes (``search_complete`` False: the best found, not proven best).
    hypotheses : after a search (no initial pose, or ``search_window``), its distinct lattice
        poses with their scores (``_search.Hypothesis``), best first; the best was refined into
        ``pose``. Empty without a search. ``search_complete``: None without a search, else whether
        it ran to the end (``_search.SearchOptions.max_nodes``).
    """

    pose: np.ndarray
    covariance: np.ndarray
    information: np.ndarray
    degenerate: np.ndarray
    cost: float
    discrepancy: float
    overlap: int
    prior_weight: float
    initial_pose: np.ndarray
    iterations: int
    evaluations: int
    launches: int
    converged: bool
    status: Status
    message: str
    seconds: float
    accepted: bool
    evidence: Evidence
    covariance_floor: np.ndarray
    residual: float
    options: MatchOptions = field(repr=False)
    hypotheses: tuple = ()
    search_complete: Optional[bool] = None

    @property
    def calibrated_covariance(self):
        """The covariance to put in a pose graph: ``H(e)^-1`` scaled with the residual, plus the
        plateau's ``covariance_floor`` (``_covariance.calibrate``, where its fit is described;
        valid for the default options)."""
        return calibrate(self.covariance / self.options.covariance_scale, self.residual, self.covariance_floor)

    # OptimizeResult-style aliases
    @property
    def x(self):
        return self.pose

    @property
    def fun(self):
        return self.cost

    @property
    def success(self):
        return self.converged

    @property
    def nit(self):
        return self.iterations

    @property
    def nfev(self):
        return self.evaluations

    def __repr__(self):
        x, y, t = self.pose
        return (f"MatchResult(pose=({x:.4f} m, {y:.4f} m, {t:.5f} rad), status={self.status.name}, "
                f"iterations={self.iterations}, overlap={self.overlap}, seconds={self.seconds:.4f})")


class Matcher:
    """A reusable matcher: prepared maps are cached per (map, blur) and the kernels compile once.

    Use one matcher in a loop that matches many pairs; maps of any size share the compiled kernel.
    """

    def __init__(self, options: Optional[MatchOptions] = None, **overrides):
        options = options if options is not None else MatchOptions()
        self.options = _with(options, overrides)
        self._cache = weakref.WeakKeyDictionary()      # GridMap -> {(blur, kind, growth, evidence): PreparedMap}
        self._lock = threading.Lock()

    def prepare(self, grid: GridMap, blur: Optional[float] = None, blur_kind: Optional[str] = None,
                blur_growth: Optional[float] = None, evidence: Optional[str] = None,
                levels: Optional[int] = None) -> PreparedMap:
        """Prepare ``grid`` for matching once (cached for as long as the map lives): blurred, and
        everything a match through ``levels`` pyramid levels reads (the matcher's options fill in
        what is not given). A mapping loop calls this when a submap is finished, so that its
        matches cost only the matching."""
        check_not_forked()              # before the cache's lock, which a parent's thread may have held
        if not isinstance(grid, GridMap):
            raise InvalidMapError(f"expected a GridMap; got {type(grid).__name__}")
        key = (self.options.blur if blur is None else float(blur),
               self.options.blur_kind if blur_kind is None else blur_kind,
               self.options.blur_growth if blur_growth is None else float(blur_growth),
               self.options.evidence if evidence is None else evidence)
        with self._lock:
            per_map = self._cache.setdefault(grid, {})
            prepared = per_map.get(key)
        if prepared is None:
            prepared = PreparedMap(grid, *key)
            with self._lock:
                prepared = per_map.setdefault(key, prepared)
        levels = self.options.levels if levels is None else levels
        if isinstance(levels, bool) or not isinstance(levels, numbers.Integral) or levels < 1:
            raise InvalidOptionError(f"levels must be a whole number >= 1; got {levels!r}")
        prepared.ready(int(levels))
        return prepared

    def match(self, a: GridMap, b: GridMap, initial_pose=None, *, search_window=None, **overrides) -> MatchResult:
        """Find r_A2B near ``initial_pose`` minimising h (eq. 8-9), after a search without it or
        within ``search_window``; see ``match``."""
        start = time.perf_counter()
        opts = _with(self.options, overrides)
        hypotheses, complete = (), None
        if initial_pose is None or search_window is not None:
            for name, grid in (("a", a), ("b", b)):
                if not isinstance(grid, GridMap):
                    raise InvalidMapError(f"{name} must be a GridMap; got {type(grid).__name__}")
            guess = None if initial_pose is None else as_pose(initial_pose, "initial_pose")
            if search_window is not None and guess is None:
                raise InvalidOptionError("search_window needs an initial_pose to search around")
            if search_window is not None:
                try:
                    window = tuple(float(v) for v in search_window)
                except (TypeError, ValueError):
                    window = ()
                if len(window) != 2 or not all(math.isfinite(v) for v in window):
                    raise InvalidOptionError(f"search_window must be (metres, radians), two finite numbers; "
                                             f"got {search_window!r}")
                search_window = window
            found = search(a, b, guess, SearchOptions(window=search_window), engine=opts.engine)
            hypotheses, complete = tuple(found.hypotheses), found.complete
            # none: the window holds no pose that puts B on A, and the local match from the guess says so
            initial_pose = hypotheses[0].pose if hypotheses else guess
        r0 = as_pose(initial_pose, "initial_pose")
        r0[2] = wrap_angle(r0[2])
        prep_a = self.prepare(a, opts.blur, opts.blur_kind, opts.blur_growth, opts.evidence, opts.levels)
        prep_b = self.prepare(b, opts.blur, opts.blur_kind, opts.blur_growth, opts.evidence, opts.levels)
        counter = _Counter()
        full_weight = opts.weight(prep_b.n_known)
        if opts.method == "bfgs":
            r, status, nit, cost_value, e, overlap, information = self._bfgs_levels(
                prep_a, prep_b, opts, r0, full_weight, counter)
        else:
            r, status, nit, cost_value, e, overlap, information = self._newton_levels(
                prep_a, prep_b, opts, r0, full_weight, counter)
        if overlap == 0 and status.converged:
            status = Status.SEPARATED
        metric = centroid_metric(prep_b.centroid, prep_b.spread, r[2])
        covariance, degenerate = covariance_from_hessian(information, metric, scale=opts.covariance_scale)
        if len(degenerate) == 3 and status.converged:
            status = Status.NO_INFORMATION
        pose = np.array([r[0], r[1], wrap_angle(r[2])])
        walls_a, walls_b = prep_a.wall_distance, prep_b.wall_distance
        b_in_a, a_in_b = placed = placed_walls(walls_a, walls_b, pose)
        comparison = compare_walls(walls_a, walls_b, placed)
        residual = float(e) / max(comparison[0], 1)
        plateau = min(plateau_sd(*b_in_a) * prep_a.resolution, plateau_sd(*a_in_b) * prep_b.resolution)
        floor = covariance_floor(plateau, prep_b.centroid, prep_b.spread, pose[2])
        calibrated = calibrate(covariance / opts.covariance_scale, residual, floor)
        proof = evidence(comparison, pose, calibrated, degenerate, prep_b.centroid, prep_b.spread)
        return MatchResult(
            pose=pose, covariance=covariance, information=information, degenerate=degenerate,
            cost=float(cost_value), discrepancy=float(e), overlap=int(overlap), prior_weight=full_weight,
            initial_pose=r0, iterations=nit, evaluations=counter.poses, launches=counter.launches,
            converged=status.converged, status=status, message=MESSAGES[status],
            seconds=time.perf_counter() - start, accepted=proof.accepts(status.converged) and not _ambiguous(hypotheses) and complete is not False,
            evidence=proof, covariance_floor=floor, residual=residual, options=opts, hypotheses=hypotheses,
            search_complete=complete)

    @staticmethod
    def _newton_levels(prep_a, prep_b, opts, r0, full_weight, counter):
        """Trust-region Newton on each level, coarse to fine; one 25-pose launch per iteration."""
        top = opts.levels - 1
        r, status, nit = r0, Status.MAX_ITERATIONS, 0
        for level in range(top, -1, -1):                  # coarse to fine; level 0: the given maps
            cost = _LevelCost(prep_a.level(level), prep_b.level(level), prep_b, opts, r0, full_weight, counter)
            eps = cost.steps[0]
            # the overlap is needed at the start (is there any?) and at the end (the result's)
            count = "first" if level == 0 and cost.counts_free else "none"
            evaluate = functools.partial(cost.value_gradient_hessian, count=count)
            # at the top: is there any overlap? (the exact count only when the top level is also the last)
            first_count = ("any" if top > 0 else "first") if level == top else count
            first = cost.value_gradient_hessian(cost.to_z(r), count=first_count)
            if level == top and first[3][1] == 0:
                return r0, Status.NO_OVERLAP, 0, first[0], 0.0, 0, np.zeros((3, 3))
            if level == top:
                radius, budget = cost.max_step, opts.max_iterations
            else:
                radius = (ENTRY_RADIUS_CELLS_FINEST if level == 0 else ENTRY_RADIUS_CELLS) * eps
                budget = min(opts.refine_iterations, opts.max_iterations)
            xtol = opts.step_tolerance if level == top else opts.refine_xtol
            res = minimize_newton(evaluate, cost.to_z(r), radius=radius, max_radius=cost.max_step, xtol=xtol * eps,
                                  gtol=opts.gtol * cost.weight, max_launches=budget, first=first,
                                  gradient_fallback=level == top)
            r, nit = cost.to_r(res.z), nit + res.nit
            if level == top:          # the finer levels refine within a fixed budget of launches
                status = res.status
        e, overlap, information = res.extra
        if overlap is None:
            overlap = cost.overlap(r)
        return r, status, nit, res.fun, e, overlap, information

    @staticmethod
    def _bfgs_levels(prep_a, prep_b, opts, r0, full_weight, counter):
        """The paper's BFGS (eq. 9) on each level, compass polish, then one 25-pose Hessian launch."""
        top = opts.levels - 1
        r, status, nit, cost_value = r0, Status.MAX_ITERATIONS, 0, 0.0
        for level in range(top, -1, -1):                  # coarse to fine; level 0: the given maps
            cost = _LevelCost(prep_a.level(level), prep_b.level(level), prep_b, opts, r0, full_weight, counter)
            eps = cost.steps[0]
            # the overlap is needed at the start (is there any?) and at the end (the result's)
            h_start, grad_start, counts = cost.value_and_gradient(
                r, count="first" if level == top or cost.counts_free else "none")
            z, step = cost.to_z(r), 4.0 * eps
            if level == top and counts[0] == 0:
                return r0, Status.NO_OVERLAP, 0, h_start, 0.0, 0, np.zeros((3, 3))
            if level == top:                               # BFGS from the initial guess
                res = minimize_bfgs(cost.fun_grad, z, max_step=cost.max_step, xtol=opts.step_tolerance * eps,
                                    gtol=opts.gtol * cost.weight, max_iterations=opts.max_iterations,
                                    first=(h_start, cost.grad_z(grad_start)))
                z, h_start, status, nit = res.z, res.fun, res.status, nit + res.nit
            elif level == 0:                               # a few BFGS steps of at most two cells
                res = minimize_bfgs(cost.fun_grad, z, max_step=2.0 * eps, xtol=opts.step_tolerance * eps,
                                    gtol=opts.gtol * cost.weight,
                                    max_iterations=min(opts.refine_iterations, opts.max_iterations),
                                    first=(h_start, cost.grad_z(grad_start)))
                z, h_start, nit, step = res.z, res.fun, nit + res.nit, eps
            # then the compass search (alone on the levels in between)
            z, cost_value, _ = polish(cost.batch, z, h_start, step=step, xtol=opts.step_tolerance * eps,
                                      max_step=cost.max_step)
            r = cost.to_r(z)
        # eq. (11)-(12) on the given maps, one launch (two when counting the overlap takes its own)
        _, _, _, (e, overlap, information) = cost.value_gradient_hessian(cost.to_z(r), count="first")
        return r, status, nit, cost_value, e, overlap, information


class _Counter:
    """Kernel launches and poses evaluated during one match."""

    def __init__(self):
        self.launches = 0
        self.poses = 0


class _LevelCost:
    """h (eq. 8) on one level of the pyramid, as the optimisers see it.

    Poses r are (x, y, theta); the optimisers work in z = M r, all in metres (see ``__init__``),
    so that a unit step moves a typical cell of B by about a metre whichever way it goes. K follows
    the number of B's known cells at this level.
    With ``interpolation="nearest"`` (the paper's e) derivatives come from the stencils of
    eq. (10)-(12); with "bilinear" the gradient is analytic (one pose) and the Hessian is the
    central difference of gradients at +-1 step on each axis (7 poses).
    """

    def __init__(self, pa, pb, prep_b, opts, r0, full_weight, counter):
        self._engine = make_engine(opts.engine, pa, pb, opts.unknown_cost)
        self._bilinear = opts.interpolation == "bilinear"
        self._counter = counter
        self._r0 = r0
        self._rotation_scale = opts.rotation_scale
        self.steps = opts.steps(pa.resolution, prep_b.radius)
        self.weight = full_weight * pb.n_known / max(prep_b.n_known, 1)
        # z = M r: B's centroid's position in A and theta times B's rms radius about its centroid,
        # linearised at r0's theta. A unit step in z then moves a typical cell of B by about a
        # metre whichever way, also when B's frame origin lies far from its cells (ROS maps put it
        # at a corner, tens of metres away): there a rotation about the origin is mostly a
        # translation, and a trust region in (x, y, theta * radius) crawled along the valley of
        # rotations about the map's own centre (a self-match from 0.02 rad stopped 0.4 deg off).
        self._to_z = centroid_metric(prep_b.centroid, prep_b.spread, r0[2])
        self._from_z = np.linalg.inv(self._to_z)
        # the stencils' steps in z: one cell of A along x and y, and a rotation about B's centroid
        # that moves a typical cell of B by one cell (the derivatives of e then come in z directly;
        # taken about B's frame origin they hid the rotation about B's centre in the rounding of
        # far larger terms)
        self.z_steps = np.array([self.steps[0], self.steps[1],
                                 self.steps[0] if opts.rotation_step is None else opts.rotation_step * prep_b.spread])
        self.max_step = opts.max_step if opts.max_step is not None else max(opts.blur / 2.0, 4.0 * self.steps[0])

    @property
    def counts_free(self):
        """Whether the engine counts the overlap in the same launch as e."""
        return self._engine.counts_free

    def to_z(self, r):
        """The optimiser's coordinates z = M r of a pose r."""
        return self._to_z @ np.asarray(r, dtype=np.float64)

    def to_r(self, z):
        return self._from_z @ np.asarray(z, dtype=np.float64)

    def grad_z(self, grad_r):
        """A gradient in r as a gradient in z."""
        return self._from_z.T @ grad_r

    def _count(self, poses, count="none"):
        self._counter.launches += 1 if count in ("none", "any") or self.counts_free else 2
        self._counter.poses += poses

    def overlap(self, r):
        """The overlap at r (one launch)."""
        self._count(1)
        return int(self._engine.overlap(np.asarray(r, dtype=np.float64)[None, :])[0])

    def evaluate(self, poses, count="first"):
        """e and the overlap (see ``make_engine`` for ``count``) for a batch of poses: one launch."""
        self._count(len(poses), count)
        if self._bilinear:
            return self._engine.bilinear(poses)[:2]
        return self._engine(poses, count)

    def value_and_gradient(self, r, count="none"):
        """h and its gradient in r at r: the 13-pose stencil (eq. 10) in z, or one pose (bilinear)."""
        if self._bilinear:
            self._count(1)
            values, counts, grads = self._engine.bilinear(r[None, :])
            grad = grads[0]
        else:
            values, counts = self.evaluate(gradient_stencil(r, self.z_steps, self._from_z), count)
            grad = self._to_z.T @ gradient_from_stencil(values, self.z_steps)
        p_val, p_grad = prior(r, self._r0, self.weight, self._rotation_scale)
        return values[0] + p_val, grad + p_grad, counts

    def value_gradient_hessian(self, z, count="none"):
        """h, its gradient and Hessian in z (the prior's included), from one launch; extra:
        (e, overlap or None, Hessian of e in r) at z."""
        r = self.to_r(z)
        if self._bilinear:
            self._count(7)
            poses = r + np.vstack([np.zeros(3), np.diag(self.steps), -np.diag(self.steps)])
            values, counts, grads = self._engine.bilinear(poses)
            hess = (grads[1:4] - grads[4:7]).T / (2.0 * self.steps)      # column q: d grad / d r_q
            hess = 0.5 * (hess + hess.T)
            grad_z, hess_z = self.grad_z(grads[0]), self._from_z.T @ hess @ self._from_z
        else:
            self._count(25, count)
            spared = getattr(self._engine, "dense_launches", 0)        # count="any": a launch only if needed
            values, counts = self._engine.hessian_stencil(r, self.z_steps, count, basis=self._from_z)
            self._counter.launches += getattr(self._engine, "dense_launches", 0) - spared
            grad_z, hess_z = gradient_from_stencil(values, self.z_steps), hessian_from_stencil(values, self.z_steps)
            hess = self._to_z.T @ hess_z @ self._to_z                      # eq. (12) in r
        p_val, p_grad, h_prior = prior_terms(r, self._r0, self.weight, self._rotation_scale, self.steps[0])
        extra = (values[0], None if counts is None else counts[0], hess)
        return (values[0] + p_val, grad_z + self.grad_z(p_grad),
                hess_z + self._from_z.T @ h_prior @ self._from_z, extra)

    def fun_grad(self, z):
        h, grad, _ = self.value_and_gradient(self.to_r(z))
        return h, self.grad_z(grad)

    def batch(self, zs):
        """h at a batch of points z, one launch (for the compass search)."""
        rs = zs @ self._from_z.T
        e_values, _ = self.evaluate(rs, count="none")
        return e_values + prior_values(rs, self._r0, self.weight, self._rotation_scale)


_DEFAULT = {}


def match(a: GridMap, b: GridMap, initial_pose=None, *, search_window=None, **options) -> MatchResult:
    """Find the pose r_A2B of map B in map A near ``initial_pose`` (the paper's method).

    Without ``initial_pose`` a search over every relative pose where the maps overlap finds one
    first (``_search``, a branch and bound over a lattice of poses at 0.2 m); with
    ``search_window=(metres, radians)`` a search within that window around ``initial_pose``. The
    best pose found is refined; ``hypotheses`` lists it with the distinct runner-ups.
    ``options`` are fields of ``MatchOptions`` (blur, prior_weight, rotation_scale, step, ...).
    Non-convergence and a missing overlap are reported in the result (``converged``, ``status``,
    ``message``), not raised. For many matches, reuse a ``Matcher``.
    """
    matcher = _DEFAULT.get("matcher")
    if matcher is None:
        matcher = _DEFAULT.setdefault("matcher", Matcher())
    return matcher.match(a, b, initial_pose, search_window=search_window, **options)
