"""taichi_match: the relative pose between two overlapping occupancy grid maps.

Implements "Computation of the Optimal Relative Pose between Overlapping Grid Maps through
Discrepancy Minimization": blur both maps once, minimise h = e + K ||r - r0|| from the stencils
of eq. (10)-(12) evaluated by batched Taichi kernels (by default a trust-region Newton iteration
on the stencil's Hessian over a map pyramid; the paper's BFGS with ``optimizer="bfgs"``), and
take the covariance from the numeric Hessian of e. Conventions are stated once in ``taichi_match._grid`` (maps) and
``taichi_match._se2`` (poses).
"""

import logging


from ._status import Status
from ._errors import (EngineError, InvalidMapError, InvalidOptionError, InvalidPoseError, LogFileError,
                      LogFormatError, MapFileError, MapFormatError, TaichiMatchError)
from ._grid import GridMap
from ._covariance import CALIBRATED_COVARIANCE_SCALE
from ._matcher import Matcher, match
from ._options import MatchOptions
from ._result import MatchResult
from ._prepared import PreparedMap, make_engine
from ._search import Hypothesis
from ._se2 import as_poses, compose, inverse, transform_points, wrap_angle
from .many import iter_matches, match_many

__all__ = [
    "GridMap", "discrepancy", "match", "match_many", "iter_matches", "Matcher", "MatchOptions", "MatchResult", "Hypothesis", "Status",
    "CALIBRATED_COVARIANCE_SCALE",
    "TaichiMatchError", "InvalidMapError", "InvalidPoseError", "InvalidOptionError", "EngineError",
    "MapFileError", "MapFormatError", "LogFileError", "LogFormatError",
    "compose", "inverse", "transform_points", "wrap_angle",
]

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())


def discrepancy(a: GridMap, b: GridMap, poses, *, engine="taichi", return_overlap=False):
    """Eq. (6) on the maps exactly as given (no blur) for each pose r_A2B in ``poses`` (N, 3).

    Each known cell of B, taken at its centre, is mapped into A and looked up with floor; it adds
    |p_A - p_B| when it lands on a known cell of A. Returns the N values (float64), and the
    number of cells compared per pose as well when ``return_overlap`` is true.
    """
    for name, grid in (("a", a), ("b", b)):
        if not isinstance(grid, GridMap):
            raise InvalidMapError(f"{name} must be a GridMap; got {type(grid).__name__}")
    poses = as_poses(poses)
    values, overlap = make_engine(engine, PreparedMap(a, 0.0), PreparedMap(b, 0.0))(poses)
    return (values, overlap) if return_overlap else values
