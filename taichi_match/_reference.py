"""Eq. (6) in plain NumPy: the oracle for the tests and the baseline engine for the benchmarks.

Written straight from the paper, independently of the Taichi kernels: every known cell of B is
taken at its centre (eq. 2), mapped into A by the pose (eq. 4) and looked up with floor (eq. 3);
it adds |p_A - p_B| when it lands on a known cell of A. Arithmetic is float64 throughout.

``NumpyBilinear`` is the same sum with A interpolated bilinearly between the centres of its cells
(an option beyond the paper): a cell of B counts when the four cells of A around it are known;
it returns the analytic gradient with respect to the pose too (the tests check it against
SciPy's finite differences of the value).
"""

import numpy as np

from ._grid import GridMap
from ._se2 import as_poses, transform_points

__all__ = ["NumpyDiscrepancy", "NumpyBilinear", "NumpyDense"]


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


class NumpyBilinear(NumpyDiscrepancy):
    """e with A bilinearly interpolated, its overlap count and its gradient in (x, y, theta)."""

    def __call__(self, poses):
        """Return (discrepancy (N,), overlap (N,) int64, gradient (N, 3))."""
        poses = as_poses(poses)
        values = np.zeros(len(poses))
        counts = np.zeros(len(poses), dtype=np.int64)
        grads = np.zeros((len(poses), 3))
        a = self._a
        rows_a, cols_a = a.shape
        c_yaw, s_yaw = np.cos(a.corner_pose[2]), np.sin(a.corner_pose[2])
        for k, (x, y, theta) in enumerate(poses):
            points = transform_points((x, y, theta), self._centres_b)
            fv, fu = a.grid_coordinates(points)
            fv, fu = fv - 0.5, fu - 0.5                       # from cell centres
            i0, j0 = np.floor(fv), np.floor(fu)
            tv, tu = fv - i0, fu - j0
            inside = (i0 >= 0) & (i0 + 1 < rows_a) & (j0 >= 0) & (j0 + 1 < cols_a)
            i0, j0 = i0[inside].astype(np.intp), j0[inside].astype(np.intp)
            tv, tu = tv[inside], tu[inside]
            a00, a01 = a.prob[i0, j0], a.prob[i0, j0 + 1]
            a10, a11 = a.prob[i0 + 1, j0], a.prob[i0 + 1, j0 + 1]
            value = a00 * (1 - tu) * (1 - tv) + a01 * tu * (1 - tv) + a10 * (1 - tu) * tv + a11 * tu * tv
            diff = value - self._prob_b[inside]
            ok = ~np.isnan(diff)
            values[k] = np.abs(diff[ok]).sum()
            counts[k] = ok.sum()
            # d value / d (col, row), then the chain rule through the point's motion in A's grid
            sign = np.sign(diff[ok])
            d_u = ((1 - tv) * (a01 - a00) + tv * (a11 - a10))[ok]
            d_v = ((1 - tu) * (a10 - a00) + tu * (a11 - a01))[ok]
            p_b = self._centres_b[inside][ok]
            # d point / d theta in A's frame: R'(theta) p_b
            dpx = -np.sin(theta) * p_b[:, 0] - np.cos(theta) * p_b[:, 1]
            dpy = np.cos(theta) * p_b[:, 0] - np.sin(theta) * p_b[:, 1]
            res = a.resolution
            du = np.array([c_yaw, s_yaw]) / res                # d col / d (x, y) of the point
            dv = np.array([-s_yaw, c_yaw]) / res               # d row / d (x, y)
            gx = np.sum(sign * (d_u * du[0] + d_v * dv[0]))
            gy = np.sum(sign * (d_u * du[1] + d_v * dv[1]))
            gt = np.sum(sign * (d_u * (du[0] * dpx + du[1] * dpy) + d_v * (dv[0] * dpx + dv[1] * dpy)))
            grads[k] = gx, gy, gt
        return values, counts, grads


class NumpyDense:
    """The "numpy" backend's ``_engines.DenseEvaluator`` on two maps (every overlap counted)."""

    counts_free = True

    def __init__(self, a: GridMap, b: GridMap):
        self._maps = (a, b)
        self._discrepancy = NumpyDiscrepancy(a, b)
        self._bilinear = None

    def __call__(self, poses, count="all"):
        return self._discrepancy(poses)

    def overlap(self, poses):
        """The overlap (N,) at each pose."""
        return self._discrepancy(poses)[1]

    def bilinear(self, poses):
        """(e (N,), overlap (N,), gradient (N, 3)) with A interpolated bilinearly."""
        if self._bilinear is None:
            self._bilinear = NumpyBilinear(*self._maps)
        return self._bilinear(poses)
