"""taichi_match: the relative pose between two overlapping occupancy grid maps.

Implements "Computation of the Optimal Relative Pose between Overlapping Grid Maps through
Discrepancy Minimization": blur both maps once, minimise h = e + K ||r - r0|| from the stencils
of eq. (10)-(12) evaluated by batched Taichi kernels (by default a trust-region Newton iteration
on the stencil's Hessian over a map pyramid; the paper's BFGS with ``optimizer="bfgs"``), and
take the covariance from the numeric Hessian of e. Conventions are stated once in ``taichi_match._grid`` (maps) and
``taichi_match._se2`` (poses).
"""

import logging

from ._covariance import CALIBRATED_COVARIANCE_SCALE
from ._engines import make_engine
from ._errors import (
    EngineError,
    InvalidMapError,
    InvalidOptionError,
    InvalidPoseError,
    LogFileError,
    LogFormatError,
    MapFileError,
    MapFormatError,
    SlamRunError,
    TaichiMatchError,
)
from ._grid import GridMap
from ._matcher import Matcher, match
from ._options import MatchOptions
from ._prepared import PreparedMap
from ._result import MatchResult
from ._se2 import as_poses, compose, inverse, transform_points, wrap_angle
from ._search import Hypothesis
from ._status import Status
from .many import iter_matches, match_many

__all__ = [
    "GridMap", "discrepancy", "match", "match_many", "iter_matches", "Matcher", "MatchOptions", "MatchResult",
    "Hypothesis", "Status",
    "CALIBRATED_COVARIANCE_SCALE",
    "TaichiMatchError", "InvalidMapError", "InvalidPoseError", "InvalidOptionError", "EngineError",
    "MapFileError", "MapFormatError", "LogFileError", "LogFormatError", "SlamRunError",
    "compose", "inverse", "transform_points", "wrap_angle",
]

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())


def discrepancy(a: GridMap, b: GridMap, poses, *, engine="taichi", return_overlap=False):
    """Eq. (6) on the maps exactly as given (no blur) for each pose r_A2B in ``poses`` (N, 3).

    Each known cell of B, taken at its centre, is mapped into A and looked up with floor; it adds
    |p_A - p_B| when it lands on a known cell of A. Returns the N values (float64), and the
    number of cells compared per pose as well when ``return_overlap`` is true.

    Parameters
    ----------
    a, b : GridMap
        The two maps, each in its own frame.
    poses : array_like, shape (N, 3) or (3,)
        Poses r_A2B = (x, y, theta) of B's frame in A's, metres and radians.
    engine : {"taichi", "numpy"}
        The Taichi kernels, or the plain NumPy oracle (``taichi_match._reference``); the same
        values.
    return_overlap : bool
        Also return the number of cells compared at each pose.

    Returns
    -------
    values : numpy.ndarray, shape (N,)
        e(A, B, r) per pose, float64 (0 where the maps do not overlap).
    overlap : numpy.ndarray, shape (N,)
        The known cells of B that land on known cells of A per pose (int); only with
        ``return_overlap``.

    Raises
    ------
    InvalidMapError
        If ``a`` or ``b`` is not a ``GridMap``.
    InvalidPoseError
        If ``poses`` is not of shape (N, 3) or (3,), or holds a non-finite value.
    InvalidOptionError
        For an unknown ``engine``.

    Examples
    --------
    A map whose right half is a wall, against itself: 0 at the identity; moved 0.1 m (a cell)
    along x, the 20 free cells next to the wall land on it and a column leaves A; along y
    nothing changes but the row that leaves A:

    >>> import numpy as np
    >>> from taichi_match import GridMap, discrepancy
    >>> prob = np.zeros((20, 20))
    >>> prob[:, 10:] = 1.0
    >>> a = GridMap(prob, 0.1)
    >>> values, overlap = discrepancy(a, a, [(0.0, 0.0, 0.0), (0.1, 0.0, 0.0), (0.0, 0.1, 0.0)],
    ...                               engine="numpy", return_overlap=True)
    >>> values.tolist(), overlap.tolist()
    ([0.0, 20.0, 0.0], [400, 380, 380])
    """
    for name, grid in (("a", a), ("b", b)):
        if not isinstance(grid, GridMap):
            raise InvalidMapError(f"{name} must be a GridMap; got {type(grid).__name__}")
    poses = as_poses(poses)
    values, overlap = make_engine(engine, PreparedMap(a, 0.0), PreparedMap(b, 0.0))(poses)
    return (values, overlap) if return_overlap else values
