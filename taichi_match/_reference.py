"""Eq. (6) in plain NumPy: the oracle for the tests and the baseline engine for the benchmarks.

Written straight from the paper, independently of the Taichi kernels: every known cell of B is
taken at its centre (eq. 2), mapped into A by the pose (eq. 4) and looked up with floor (eq. 3);
it adds |p_A - p_B| when it lands on a known cell of A. Arithmetic is float64 throughout.
"""

import numpy as np

from ._grid import GridMap
from ._se2 import as_poses, transform_points

__all__ = ["NumpyDiscrepancy"]


class NumpyDiscrepancy:
    """Evaluate e(A, B, r) and the overlap count for a batch of poses r_A2B, in NumPy."""

    def __init__(self, a: GridMap, b: GridMap):
        rows, cols = np.nonzero(b.known)
        self._centres_b = b.cell_centres(rows, cols)
        self._prob_b = b.prob[rows, cols]
        self._a = a

    def __call__(self, poses):
        """Return (discrepancy, overlap): float64 and int64 arrays of shape (N,)."""
        poses = as_poses(poses)
        values = np.zeros(len(poses))
        counts = np.zeros(len(poses), dtype=np.int64)
        a = self._a
        rows_a, cols_a = a.shape
        for k, pose in enumerate(poses):
            r, c = a.cell_of(transform_points(pose, self._centres_b))
            inside = (r >= 0) & (r < rows_a) & (c >= 0) & (c < cols_a)
            p_a = a.prob[r[inside].astype(np.intp), c[inside].astype(np.intp)]
            diff = np.abs(p_a - self._prob_b[inside])
            compared = ~np.isnan(diff)
            values[k] = diff[compared].sum()
            counts[k] = compared.sum()
        return values, counts
