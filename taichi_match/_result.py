"""The outcome of a match (``MatchResult``)."""

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ._covariance import calibrate
from ._options import MatchOptions
from ._status import Status
from ._verdict import Evidence

__all__ = ["MatchResult"]


@dataclass(frozen=True)
class MatchResult:
    """The outcome of a match, in the style of ``scipy.optimize.OptimizeResult``.

    Attributes
    ----------
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
    overlap : number of known cells of B that land on known cells of A at ``pose``; None where it
        was not counted (``MatchOptions.count_overlap`` False).
    initial_pose, iterations, evaluations (poses evaluated), launches (batched evaluations),
    converged, status, message, seconds (wall clock of the whole match).
    accepted : the verdict: True when the pose can be trusted (``converged`` only says the
        optimiser stopped at a minimum). ``evidence`` holds what it rests on: walls compared, the
        share of walls meeting the other map's walls, the share landing on its free space, and
        the largest standard deviation outside degenerate directions (``taichi_match._verdict``).
        After a search, also False when a distinct runner-up scores at least ``AMBIGUITY`` (0.75)
        times the best (the maps fit two ways: a corridor, a symmetric room) or when the search hit
        its budget of nodes before proving the best (``search_complete`` False: the best found,
        not proven best).
    hypotheses : after a search (no initial pose, or ``search_window``), its distinct lattice
        poses with their scores (``_search.Hypothesis``), best first; the best was refined into
        ``pose``. Empty without a search. ``search_complete``: None without a search, else whether
        the best is proven: the search ran to the end, or to its budget of nodes
        (``_search.SearchOptions.max_nodes``) with nothing left that could score 0.9 of the best.
        ``search_proven``: None without a search, else the fraction of the best's score down to
        which the runner-ups are proven (0.75; up to 0.9 where the budget ran out; 1.0 when the
        search is not complete).

    Examples
    --------
    A room matched to itself from a guess a few cells off (see ``match``):

    >>> import numpy as np
    >>> from taichi_match import match
    >>> from taichi_match.scenes import room
    >>> grid = room()
    >>> result = match(grid, grid, initial_pose=(0.1, -0.05, 0.03))
    >>> result.status.name, result.accepted, result.converged
    ('STEP', True, True)
    >>> sd = np.sqrt(np.diag(result.calibrated_covariance))    # metres, metres, radians
    >>> bool(np.all(sd < 0.05)), bool(np.all(np.abs(result.pose) < 0.025))
    (True, True)
    """

    pose: np.ndarray
    covariance: np.ndarray
    information: np.ndarray
    degenerate: np.ndarray
    cost: float
    discrepancy: float
    overlap: Optional[int]
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
    search_proven: Optional[float] = None

    @property
    def calibrated_covariance(self):
        """The covariance to put in a pose graph: ``H(e)^-1`` scaled with the residual, plus the
        plateau's ``covariance_floor`` (``_covariance.calibrate``, where its fit is described;
        fitted for the envelope looked up either way)."""
        return calibrate(self.covariance / self.options.covariance_scale, self.residual, self.covariance_floor,
                         self.options.interpolation)

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
