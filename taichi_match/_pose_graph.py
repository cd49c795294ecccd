"""The mapping loop's pose graph optimised in gtsam (``slam``; ``_slam_outputs`` writes the graph).

``slam`` builds the graph (its factors and noise models) and asks this module for the rest: the
import, the solver after each submap, Levenberg-Marquardt over the whole graph, Values in and
poses out, and the covariance of an edge as gtsam reads it.

Nodes are ``gtsam.Pose2`` keyed by integers (a scan's index, a submap frame's ``FRAME_KEY`` + its
index); estimates travel as (N, 3) float64 arrays of (x, y, theta) in the world frame, metres and
radians. Edges are ``BetweenFactorPose2`` whose covariance gtsam reads in the tangent space of the
relative pose (``tangent_covariance``).
"""

import math

import numpy as np

__all__ = ["SOLVERS", "Solver", "import_gtsam", "optimise", "poses", "tangent_covariance", "values"]

SOLVERS = ("batch", "isam2")
# iSAM2 (``solver``): a node's linearisation point is renewed when its estimate moves by more than
# this (gtsam's default 0.1 is for metres and radians alike: loop closures here move nodes by
# centimetres), and each update is this many Gauss-Newton steps (not tuned)
ISAM_RELINEARIZE = 0.01
ISAM_STEPS = 2


def import_gtsam():
    """``gtsam``, or an ImportError that says how to install it."""
    try:
        import gtsam
    except ImportError as exc:                   # pragma: no cover - depends on the installation
        raise ImportError("the mapping loop needs gtsam: pip install 'taichi-match[slam]' "
                          "(gtsam has wheels for Python 3.11-3.13; on 3.10 build it from source)") from exc
    return gtsam


def tangent_covariance(pose, covariance) -> np.ndarray:
    """A covariance of (x, y, theta) of a relative pose in the first frame as gtsam's Pose2 wants
    it: in the tangent space at ``pose`` (translation in the pose's own axes)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    j = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    cov = j @ np.asarray(covariance, dtype=np.float64) @ j.T
    return 0.5 * (cov + cov.T)


def values(gtsam, est, keys):
    """``gtsam.Values`` holding ``est[k]`` as the Pose2 of each key ``k`` of ``keys``."""
    out = gtsam.Values()
    for k, (x, y, theta) in zip(keys, est[keys].tolist()):      # one fetch of every row: a third of the time
        out.insert(k, gtsam.Pose2(x, y, theta))
    return out


def poses(gtsam, result, keys) -> np.ndarray:
    """(len(keys), 3) the poses of ``keys`` in ``result`` (every value a Pose2): gtsam's
    ``extractPose2`` gives them all at once, in the Values' sorted key order (the same floats as
    three calls per key, a tenth of the time: 0.16 against 1.7 ms for 600 nodes)."""
    order = np.searchsorted(np.asarray(result.keys()), keys)
    return gtsam.utilities.extractPose2(result)[order]


def optimise(gtsam, graph, start, keys) -> np.ndarray:
    """The graph optimised by Levenberg-Marquardt from the Values ``start``: (len(keys), 3) poses."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    return poses(gtsam, gtsam.LevenbergMarquardtOptimizer(graph, start, params).optimize(), keys)


class Solver:
    """The pose graph's optimisation after each submap (``SlamOptions.solver``): "batch",
    Levenberg-Marquardt over the whole graph from ``start``, or "isam2", iSAM2 given the factors and
    nodes added since its last update (from their current estimates) and relinearising where the
    estimates moved."""

    def __init__(self, gtsam, kind: str):
        self._gtsam = gtsam
        self._isam = None
        if kind == "isam2":
            params = gtsam.ISAM2Params()
            params.setRelinearizeThreshold(ISAM_RELINEARIZE)
            params.relinearizeSkip = 1
            self._isam = gtsam.ISAM2(params)
        self._factors = self._nodes = 0                  # how many the solver has been given

    def optimise(self, graph, start, est, keys) -> np.ndarray:
        """(len(keys), 3) the poses of ``keys`` after this update."""
        gtsam = self._gtsam
        if self._isam is None:
            return optimise(gtsam, graph, start, keys)
        new = gtsam.NonlinearFactorGraph()
        for i in range(self._factors, graph.size()):
            new.add(graph.at(i))
        self._isam.update(new, values(gtsam, est, keys[self._nodes:]))
        for _ in range(ISAM_STEPS - 1):
            self._isam.update()
        self._factors, self._nodes = graph.size(), len(keys)
        return poses(gtsam, self._isam.calculateEstimate(), keys)
