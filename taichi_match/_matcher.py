"""The matcher: prepares the maps, descends to the pose, and judges it.

Data flows one way: maps -> prepared (blurred) maps (``_prepared``) -> batched evaluation of e
(eq. 6, or the envelope discrepancy) -> h (eq. 8) and its stencils (eq. 10-12, ``_cost``) ->
the optimiser on each pyramid level (``_descent``) -> covariance (eq. 11, ``_covariance``) and
the verdict (``_verdict``) -> ``MatchResult``. Without a guess, or within a window, a search
(``_search``) finds the start first.
"""

import math
import numbers
import threading
import time
import weakref
from typing import Optional, Tuple

import numpy as np
import numpy.typing as npt

from ._cost import Counter
from ._covariance import calibrate, centroid_metric, covariance_floor, covariance_from_hessian, plateau_sd
from ._descent import descend
from ._errors import InvalidMapError, InvalidOptionError, shown
from ._grid import GridMap
from ._options import MatchOptions
from ._prepared import PreparedMap
from ._result import MatchResult
from ._se2 import as_pose, wrap_angle
from ._search import RUNNER_UP_FRACTION, SearchOptions, search
from ._status import MESSAGES, Status
from ._taichi import check_not_forked
from ._verdict import compare_walls, evidence, placed_walls

__all__ = ["Matcher", "match"]

# A map whose cells lie farther than this (metres) from its frame's origin is refused: a rotation
# about an origin that far moves its cells by more than the pose's own precision can follow (maps
# placed 1e7 m out gave an accepted pose 5 cm off with a zero covariance, 1e6 m a perfect pair not
# accepted, 1e4-1e5 m the right fit; measured 2026-12-03 on a 15 x 15 m crop of gdc_3ne).
MAX_FRAME_DISTANCE = 1e5


def _check_frame(what, grid):
    """``InvalidMapError`` when ``grid``'s farthest corner lies beyond ``MAX_FRAME_DISTANCE``."""
    x, y, yaw = grid.corner_pose
    h, w = grid.shape
    c, s = math.cos(yaw), math.sin(yaw)
    far = max(math.hypot(x + c * u - s * v, y + s * u + c * v)
              for u in (0.0, w * grid.resolution) for v in (0.0, h * grid.resolution))
    if not far <= MAX_FRAME_DISTANCE:
        raise InvalidMapError(f"{what}'s cells lie up to {far:.3g} m from its frame's origin, beyond "
                              f"{MAX_FRAME_DISTANCE:.0e} m: give the maps origins near their cells (a ROS map's "
                              f"origin field); the pose is then between the new frames")


# After a search, a distinct runner-up scoring at least this times the best makes the match
# ambiguous (not accepted): the fraction above which the search proves its runner-ups.
AMBIGUITY = RUNNER_UP_FRACTION


def _ambiguous(hypotheses) -> bool:
    """After a search: no best with a positive score, or a runner-up close to it."""
    if not hypotheses:
        return False
    best = hypotheses[0].score
    return best <= 0 or (len(hypotheses) > 1 and hypotheses[1].score >= AMBIGUITY * best)


class Matcher:
    """A reusable matcher: prepared maps are cached per (map, blur) and the kernels compile once.

    Use one matcher in a loop that matches many pairs; maps of any size share the compiled kernel.
    Thread-safe (Taichi's launches are serialised); a process forked after its first match
    cannot use it (``EngineError``: start workers with "spawn").

    Parameters
    ----------
    options : MatchOptions, optional
        The settings of every match; the defaults without it.
    **overrides
        Fields of ``MatchOptions`` replacing those of ``options``.

    Examples
    --------
    >>> from taichi_match import Matcher
    >>> from taichi_match.scenes import room
    >>> grid = room()
    >>> matcher = Matcher(levels=2)
    >>> results = [matcher.match(grid, grid, guess) for guess in [(0.1, 0.0, 0.0), (0.0, -0.1, 0.02)]]
    >>> [r.accepted for r in results]
    [True, True]
    """

    def __init__(self, options: Optional[MatchOptions] = None, **overrides):
        options = options if options is not None else MatchOptions()
        self.options = options.replace(**overrides)
        self._cache = weakref.WeakKeyDictionary()      # GridMap -> {(blur, kind, growth, evidence): PreparedMap}
        self._lock = threading.Lock()

    def prepare(self, grid: GridMap, blur: Optional[float] = None, blur_kind: Optional[str] = None,
                blur_growth: Optional[float] = None, evidence: Optional[str] = None,
                levels: Optional[int] = None, coarse_from: Optional[PreparedMap] = None) -> PreparedMap:
        """Prepare ``grid`` for matching once (cached for as long as the map lives): blurred, with
        the pyramid levels and wall distances a match through ``levels`` levels reads (the
        matcher's options fill in what is not given; ``PreparedMap.ready``). A mapping loop calls
        this when a submap is finished, so that its matches cost only the matching.
        ``coarse_from``: a prepared earlier version of the same map (a submap before its latest
        scan), whose coarser pyramid levels are taken over when ``grid`` is prepared now: only the
        given level is made (``PreparedMap.share_coarser``)."""
        check_not_forked()              # before the cache's lock, which a parent's thread may have held
        if not isinstance(grid, GridMap):
            raise InvalidMapError(f"expected a GridMap; got {type(grid).__name__}")
        _check_frame("the map", grid)
        key = (self.options.blur if blur is None else float(blur),
               self.options.blur_kind if blur_kind is None else blur_kind,
               self.options.blur_growth if blur_growth is None else float(blur_growth),
               self.options.evidence if evidence is None else evidence)
        with self._lock:
            per_map = self._cache.setdefault(grid, {})
            prepared = per_map.get(key)
        if prepared is None:
            prepared = PreparedMap(grid, *key)
            if coarse_from is not None:
                prepared.share_coarser(coarse_from)
            with self._lock:
                prepared = per_map.setdefault(key, prepared)
        levels = self.options.levels if levels is None else levels
        if isinstance(levels, bool) or not isinstance(levels, numbers.Integral) or levels < 1:
            raise InvalidOptionError(f"levels must be a whole number >= 1; got {shown(levels)}")
        prepared.ready(int(levels))
        return prepared

    def match(self, a: GridMap, b: GridMap, initial_pose: Optional[npt.ArrayLike] = None, *,
              search_window: Optional[Tuple[float, float]] = None, **overrides) -> MatchResult:
        """Find r_A2B near ``initial_pose`` minimising h (eq. 8-9), after a search without it or
        within ``search_window``; the parameters are those of ``match``, ``overrides`` changing this
        matcher's options for this call only."""
        start = time.perf_counter()
        for name, grid in (("A", a), ("B", b)):
            if isinstance(grid, GridMap):
                _check_frame(f"map {name}", grid)
        opts = self.options.replace(**overrides)
        hypotheses, complete, proven = (), None, None
        if initial_pose is None or search_window is not None:
            initial_pose, hypotheses, complete, proven = _searched_start(a, b, initial_pose, search_window, opts)
        r0 = as_pose(initial_pose, "initial_pose")
        r0[2] = wrap_angle(r0[2])
        prep_a = self.prepare(a, opts.blur, opts.blur_kind, opts.blur_growth, opts.evidence, opts.levels)
        prep_b = self.prepare(b, opts.blur, opts.blur_kind, opts.blur_growth, opts.evidence, opts.levels)
        counter = Counter()
        weight = opts.weight(prep_b.n_known)
        end = descend(prep_a, prep_b, opts, r0, weight, counter)
        status = end.status
        if not end.overlapping and status.converged:
            status = Status.SEPARATED
        # eq. (11), then what the walls say at the pose (the calibrated covariance, the verdict)
        metric = centroid_metric(prep_b.centroid, prep_b.spread, end.pose[2])
        covariance, degenerate = covariance_from_hessian(end.information, metric, scale=opts.covariance_scale)
        if len(degenerate) == 3 and status.converged:
            status = Status.NO_INFORMATION
        pose = np.array([end.pose[0], end.pose[1], wrap_angle(end.pose[2])])
        walls_a, walls_b = prep_a.wall_distance, prep_b.wall_distance
        b_in_a, a_in_b = placed = placed_walls(walls_a, walls_b, pose)
        comparison = compare_walls(walls_a, walls_b, placed)
        residual = float(end.discrepancy) / max(comparison[0], 1)
        plateau = min(plateau_sd(*b_in_a) * prep_a.resolution, plateau_sd(*a_in_b) * prep_b.resolution)
        floor = covariance_floor(plateau, prep_b.centroid, prep_b.spread, pose[2])
        calibrated = calibrate(covariance / opts.covariance_scale, residual, floor, opts.interpolation)
        proof = evidence(comparison, pose, calibrated, degenerate, prep_b.centroid, prep_b.spread)
        accepted = proof.accepts(status.converged) and not _ambiguous(hypotheses) and complete is not False
        return MatchResult(
            pose=pose, covariance=covariance, information=end.information, degenerate=degenerate,
            cost=float(end.cost), discrepancy=float(end.discrepancy),
            overlap=None if end.overlap is None else int(end.overlap), prior_weight=weight, initial_pose=r0,
            iterations=end.iterations, evaluations=counter.poses, launches=counter.launches,
            converged=status.converged, status=status, message=MESSAGES[status],
            seconds=time.perf_counter() - start, accepted=accepted, evidence=proof, covariance_floor=floor,
            residual=residual, options=opts, hypotheses=hypotheses, search_complete=complete,
            search_proven=proven)


def _searched_start(a, b, initial_pose, search_window, opts):
    """The search's best pose (or the guess when it found none), its hypotheses, whether it
    proved the best and down to which fraction of it the runner-ups; around ``initial_pose``
    within ``search_window``, or everywhere without it."""
    for name, grid in (("a", a), ("b", b)):
        if not isinstance(grid, GridMap):
            raise InvalidMapError(f"{name} must be a GridMap; got {type(grid).__name__}")
        _check_frame(f"map {name.upper()}", grid)
    guess = None if initial_pose is None else as_pose(initial_pose, "initial_pose")
    if search_window is not None:
        if guess is None:
            raise InvalidOptionError("search_window needs an initial_pose to search around")
        try:
            window = tuple(float(v) for v in search_window)
        except (TypeError, ValueError):
            window = ()
        if len(window) != 2 or not all(math.isfinite(v) for v in window):
            raise InvalidOptionError(f"search_window must be (metres, radians), two finite numbers; "
                                     f"got {shown(search_window)}")
        search_window = window
    found = search(a, b, guess, SearchOptions(window=search_window), engine=opts.engine)
    hypotheses = tuple(found.hypotheses)
    # none: the window holds no pose that puts B on A, and the local match from the guess says so
    return (hypotheses[0].pose if hypotheses else guess), hypotheses, found.complete, found.proven


_DEFAULT = {}


def match(a: GridMap, b: GridMap, initial_pose: Optional[npt.ArrayLike] = None, *,
          search_window: Optional[Tuple[float, float]] = None, **options) -> MatchResult:
    """Find the pose r_A2B of map B in map A near ``initial_pose`` (the paper's method).

    Parameters
    ----------
    a, b : GridMap
        The maps; r_A2B maps B's frame into A's (conventions in ``taichi_match._grid``).
    initial_pose : array_like of 3 floats, optional
        The guess (x, y, theta) in metres and radians, which the prior of eq. (7)-(8) keeps the
        answer near. Without it a search over every relative pose where the maps overlap finds
        one first (``_search``: a branch and bound over a lattice of poses at 0.2 m).
    search_window : (float, float), optional
        (metres, radians): search within this window around ``initial_pose`` first.
    **options
        Fields of ``MatchOptions`` (``blur``, ``prior_weight``, ``levels``, ...).

    Returns
    -------
    MatchResult
        The pose, its covariance (``calibrated_covariance`` for a pose graph) and the verdict
        ``accepted``. Non-convergence and a missing overlap are reported in it (``converged``,
        ``status``, ``message``), not raised. After a search, ``hypotheses`` lists the best pose
        found, which was refined, with its distinct runner-ups.

    Raises
    ------
    InvalidMapError, InvalidPoseError, InvalidOptionError
        For maps that are not ``GridMap``, a pose that is not three finite numbers, or an unknown
        or out-of-range option.

    See Also
    --------
    Matcher : the same, reusing prepared maps across matches (for loops).
    match_many : many pairs, optionally over worker processes.

    Examples
    --------
    >>> import numpy as np
    >>> from taichi_match import match
    >>> from taichi_match.scenes import room
    >>> a, b = room(), room(origin=(0.3, -0.2))          # the same room, B's grid 0.3 m right, 0.2 m down
    >>> result = match(a, b, initial_pose=(-0.2, 0.1, 0.02))
    >>> result.accepted, np.round(result.pose[:2], 1).tolist()
    (True, [-0.3, 0.2])
    """
    matcher = _DEFAULT.get("matcher")
    if matcher is None:
        matcher = _DEFAULT.setdefault("matcher", Matcher())
    return matcher.match(a, b, initial_pose, search_window=search_window, **options)
