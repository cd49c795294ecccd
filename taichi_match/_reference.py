"""Eq. (6) in plain NumPy: the oracle for the tests and the baseline engine for the benchmarks.

Written straight from the paper, independently of the Taichi kernels: every known cell of B is
taken at its centre (eq. 2), mapped into A by the pose (eq. 4) and looked up with floor (eq. 3);
it adds |p_A - p_B| when it lands on a known cell of A. Arithmetic is float64 throughout.
Given an upper map ``a_upper`` (the "envelope" blur), A's cell is the interval [p_A, upper_A]
and a cell of B adds its distance to it, ``max(p_B - upper_A, 0) + max(p_A - p_B, 0)``.

``NumpyBilinear`` is the same sum with A interpolated bilinearly between the centres of its cells
(an option beyond the paper): a cell of B counts when the four cells of A around it are known;
it returns the analytic gradient with respect to the pose too (the tests check it against
SciPy's finite differences of the value).
"""

import numpy as np

from ._grid import GridMap
from ._se2 import as_poses, transform_points

__all__ = ["NumpyDiscrepancy", "NumpyBilinear"]


class NumpyDiscrepancy:
    """Evaluate e(A, B, r) and the overlap count for a batch of poses r_A2B, in NumPy."""

    def __init__(self, a: GridMap, b: GridMap, a_upper: GridMap = None):
        rows, cols = np.nonzero(b.known)
        self._centres_b = b.cell_centres(rows, cols)
        self._prob_b = b.prob[rows, cols]
        self._a = a
        self._upper = a.prob if a_upper is None else a_upper.prob

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
            cells = r[inside].astype(np.intp), c[inside].astype(np.intp)
            p_b = self._prob_b[inside]
            diff = np.maximum(p_b - self._upper[cells], 0.0) + np.maximum(a.prob[cells] - p_b, 0.0)
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
            prob_b = self._prob_b[inside]

            def interpolate(grid):
                """value, d value / d col, d value / d row of ``grid`` bilinear at the points"""
                a00, a01 = grid[i0, j0], grid[i0, j0 + 1]
                a10, a11 = grid[i0 + 1, j0], grid[i0 + 1, j0 + 1]
                value = a00 * (1 - tu) * (1 - tv) + a01 * tu * (1 - tv) + a10 * (1 - tu) * tv + a11 * tu * tv
                return value, (1 - tv) * (a01 - a00) + tv * (a11 - a10), (1 - tu) * (a10 - a00) + tu * (a11 - a01)

            lo, lo_u, lo_v = interpolate(a.prob)
            hi, hi_u, hi_v = interpolate(self._upper)
            diff = np.maximum(prob_b - hi, 0.0) + np.maximum(lo - prob_b, 0.0)
            ok = ~np.isnan(diff)
            values[k] = diff[ok].sum()
            counts[k] = ok.sum()
            # d value / d (col, row), then the chain rule through the point's motion in A's grid
            above, below = (prob_b > hi)[ok], (lo > prob_b)[ok]
            d_u = np.where(above, -hi_u[ok], 0.0) + np.where(below, lo_u[ok], 0.0)
            d_v = np.where(above, -hi_v[ok], 0.0) + np.where(below, lo_v[ok], 0.0)
            p_b = self._centres_b[inside][ok]
            # d point / d theta in A's frame: R'(theta) p_b
            dpx = -np.sin(theta) * p_b[:, 0] - np.cos(theta) * p_b[:, 1]
            dpy = np.cos(theta) * p_b[:, 0] - np.sin(theta) * p_b[:, 1]
            res = a.resolution
            du = np.array([c_yaw, s_yaw]) / res                # d col / d (x, y) of the point
            dv = np.array([-s_yaw, c_yaw]) / res               # d row / d (x, y)
            gx = np.sum((d_u * du[0] + d_v * dv[0]))
            gy = np.sum((d_u * du[1] + d_v * dv[1]))
            gt = np.sum((d_u * (du[0] * dpx + du[1] * dpy) + d_v * (dv[0] * dpx + dv[1] * dpy)))
            grads[k] = gx, gy, gt
        return values, counts, grads
