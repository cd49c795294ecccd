"""Taichi kernels (CPU backend) evaluating eq. (6) for a batch of poses in one parallel launch.

Two kernels: ``discrepancy_rows`` for any batch of poses, and ``bilinear_rows``, the option
beyond the paper that interpolates A between its cell centres and also sums what the analytic
gradient needs. ``TaichiDense`` is the "taichi" backend's dense evaluator (``_engines``) on them.
(A third kernel served the 25 poses of the Hessian stencil with 5 index computations; it ran only
for the paper's dense blur on maps of 50,000+ known cells, measured 1.00x end to end at the
default options, and was removed.)

The kernels know nothing but arrays:

- ``a``: map A padded with a ring of ``PAD`` unknown cells, float32, unknown = -1. Lookups are
  clamped into the padded grid, so the inner loops need no bounds branch.
- ``b``: map B, float32, unknown = -1; ``rows``: (R, 3) int32, for each row of B holding known
  cells its index i and the column range [lo, hi) that holds them.
- ``affine``: (N, 6) float64, per pose the map from B's cell indices to A's padded cell
  coordinates: ``u = c0*j + c1*i + c2`` (column) and ``v = c3*j + c4*i + c5`` (row); A's cell is
  (floor(v), floor(u)). ``_cost.AffineMap`` builds it from eq. (2)-(5).

Output is one partial sum (and optionally a count, or bilinear's gradient sums) per (pose, row),
written without atomics so the result is bit-identical run after run; the caller adds the rows
in float64. Each row is summed in float32 (at most a few thousand terms of size <= 1).
They are launched through ``_launch``; Taichi itself is started by ``_taichi``.
"""

import typing

import numpy as np

from ._cost import AffineMap
from ._launch import Launcher
from ._taichi import kernels

__all__ = ["TaichiDense", "TaichiEngine", "Kernels", "dense_kernels", "PAD", "COUNT_MODES"]

# Width of the ring of unknown cells around A: lookups are clamped two cells inside the padded
# grid and then shifted by up to two cells, so any lookup that leaves A must land on the ring.
PAD = 5

COUNT_MODES = {"none": 0, "first": 1, "any": 1, "all": 2}   # which poses of a batch get an overlap count


def _build_kernel(ti):
    f32_2d = ti.types.ndarray(dtype=ti.f32, ndim=2)

    @ti.func
    def row_start(affine: ti.template(), k, i):
        """Per-cell steps (du, dv) along a row of B and A's coordinates (u0, v0) of the row's j = 0."""
        return (ti.f32(affine[k, 0]), ti.f32(affine[k, 3]), ti.f32(affine[k, 1] * i + affine[k, 2]),
                ti.f32(affine[k, 4] * i + affine[k, 5]))

    @ti.func
    def row_sum(a: ti.template(), b: ti.template(), i, lo, hi, u0, v0, du, dv, u_max, v_max, count: ti.template()):
        acc = ti.f32(0.0)
        cnt = 0
        for j in range(lo, hi):
            # float -> int truncates; anything below 0 or past the end is clamped onto the ring of
            # unknown cells, so truncation toward zero is as good as floor here
            iu = ti.min(ti.max(ti.cast(u0 + du * j, ti.i32), 0), u_max)
            iv = ti.min(ti.max(ti.cast(v0 + dv * j, ti.i32), 0), v_max)
            pa = a[iv, iu]
            pb = b[i, j]
            ok = (pa >= 0.0) & (pb >= 0.0)
            acc += ti.select(ok, ti.abs(pa - pb), 0.0)
            if ti.static(count):
                cnt += ti.select(ok, 1, 0)
        return acc, cnt

    @ti.kernel
    def discrepancy_rows(a: f32_2d, b: f32_2d, rows: ti.types.ndarray(dtype=ti.i32, ndim=2),
                         affine: ti.types.ndarray(dtype=ti.f64, ndim=2),
                         out: ti.types.ndarray(dtype=ti.f32, ndim=3), count_mode: ti.template()):
        u_max = a.shape[1] - 1
        v_max = a.shape[0] - 1
        for k, r in ti.ndrange(affine.shape[0], rows.shape[0]):
            i = rows[r, 0]
            du, dv, u0, v0 = row_start(affine, k, i)
            acc = ti.f32(0.0)
            cnt = 0
            if ti.static(count_mode == 2):
                acc, cnt = row_sum(a, b, i, rows[r, 1], rows[r, 2], u0, v0, du, dv, u_max, v_max, True)
            elif ti.static(count_mode == 1):
                # the branch is per (pose, row), outside the inner loop: both loops stay branch-free
                if k == 0:
                    acc, cnt = row_sum(a, b, i, rows[r, 1], rows[r, 2], u0, v0, du, dv, u_max, v_max, True)
                else:
                    acc, cnt = row_sum(a, b, i, rows[r, 1], rows[r, 2], u0, v0, du, dv, u_max, v_max, False)
            else:
                acc, cnt = row_sum(a, b, i, rows[r, 1], rows[r, 2], u0, v0, du, dv, u_max, v_max, False)
            out[0, k, r] = acc
            if ti.static(count_mode != 0):
                out[1, k, r] = ti.f32(cnt)          # exact: a row has far fewer than 2**24 cells

    @ti.kernel
    def bilinear_rows(a: f32_2d, b: f32_2d, rows: ti.types.ndarray(dtype=ti.i32, ndim=2),
                      affine: ti.types.ndarray(dtype=ti.f64, ndim=2),
                      out: ti.types.ndarray(dtype=ti.f32, ndim=3)):
        # A interpolated bilinearly between its cell centres; per (pose, row): e, the overlap, and
        # sums of sign(p_A - p_B) times dp_A/du, (dp_A/du) j, dp_A/dv, (dp_A/dv) j, from which the
        # caller forms the gradient with the affine map's derivatives (the chain rule per row)
        u_max = a.shape[1] - 2
        v_max = a.shape[0] - 2
        for k, r in ti.ndrange(affine.shape[0], rows.shape[0]):
            i = rows[r, 0]
            du, dv, u0, v0 = row_start(affine, k, i)
            u0 -= 0.5                                                  # from cell centres
            v0 -= 0.5
            acc = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dt=ti.f32)
            for j in range(rows[r, 1], rows[r, 2]):
                fu = ti.min(ti.max(u0 + du * j, 0.0), ti.f32(u_max))
                fv = ti.min(ti.max(v0 + dv * j, 0.0), ti.f32(v_max))
                iu = ti.cast(fu, ti.i32)
                iv = ti.cast(fv, ti.i32)
                tu = fu - iu
                tv = fv - iv
                a00 = a[iv, iu]
                a01 = a[iv, iu + 1]
                a10 = a[iv + 1, iu]
                a11 = a[iv + 1, iu + 1]
                pb = b[i, j]
                ok = (a00 >= 0.0) & (a01 >= 0.0) & (a10 >= 0.0) & (a11 >= 0.0) & (pb >= 0.0)
                value = (a00 * (1.0 - tu) + a01 * tu) * (1.0 - tv) + (a10 * (1.0 - tu) + a11 * tu) * tv
                d = value - pb
                s = ti.select(ok, ti.select(d > 0.0, 1.0, ti.select(d < 0.0, -1.0, 0.0)), 0.0)
                g_u = s * ((1.0 - tv) * (a01 - a00) + tv * (a11 - a10))
                g_v = s * ((1.0 - tu) * (a10 - a00) + tu * (a11 - a01))
                acc += ti.Vector([ti.select(ok, ti.abs(d), 0.0), ti.select(ok, 1.0, 0.0),
                                  g_u, g_u * j, g_v, g_v * j], dt=ti.f32)
            for m in ti.static(range(6)):
                out[m, k, r] = acc[m]

    return Kernels(discrepancy_rows, bilinear_rows)


class Kernels(typing.NamedTuple):
    poses: object          # discrepancy_rows: any batch of poses
    bilinear: object       # bilinear_rows: e, overlap and gradient sums with A interpolated


def dense_kernels() -> "Kernels":
    """The kernels of this module, built once (Taichi started first)."""
    return kernels(_build_kernel)


class TaichiEngine:
    """Evaluate eq. (6) for batches of poses on prepared arrays with the Taichi kernel."""

    name = "taichi"

    def __init__(self, a_padded, b, rows):
        self._a = a_padded
        self._b = b
        self._rows = rows
        self._launchers = {}

    def __call__(self, affine, count="all"):
        """affine: (N, 6) float64; count: which poses get an overlap count, "all", "first" or "none".

        Returns (discrepancy float64 (N,), overlap int64 (N,) or None); with "first" only the
        first overlap is meaningful (the others are 0)."""
        mode = COUNT_MODES[count]
        n = affine.shape[0]
        if self._rows.shape[0] == 0:
            return np.zeros(n), (np.zeros(n, dtype=np.int64) if mode else None)
        return self._totals(self._run("poses", affine, (2 if mode else 1, n), mode), mode)

    def bilinear(self, affine):
        """A interpolated bilinearly: (e (N,), overlap (N,) int64, row sums (4, N, R) float64 of
        sign * dp_A/du, sign * dp_A/du * j, sign * dp_A/dv, sign * dp_A/dv * j)."""
        n = affine.shape[0]
        if self._rows.shape[0] == 0:
            return np.zeros(n), np.zeros(n, dtype=np.int64), np.zeros((4, n, 0))
        out = self._run("bilinear", affine, (6, n), None)
        counts = out[1].sum(axis=1, dtype=np.float64).astype(np.int64)
        return out[0].sum(axis=1, dtype=np.float64), counts, out[2:].astype(np.float64)

    def _run(self, name, affine, planes, mode):
        """One launch of the kernel ``name`` of ``Kernels``; returns its output, of shape
        ``planes + (rows of B,)``, float32, one partial sum per row."""
        affine = self._clear_poses_outside(np.ascontiguousarray(affine, dtype=np.float64))
        launcher = self._launchers.get(name)
        if launcher is None:
            launcher = self._launchers[name] = Launcher(lambda: getattr(dense_kernels(), name),
                                                        (self._a, self._b, self._rows, None))
        return launcher.run((affine,), planes + (self._rows.shape[0],), mode)

    @staticmethod
    def _totals(out, mode):
        """Rows added in float64: (e (N,), overlap (N,) int64 or None)."""
        counts = None
        if mode == 2:
            counts = out[1].sum(axis=1, dtype=np.float64).astype(np.int64)
        elif mode == 1:
            counts = np.zeros(out.shape[1], dtype=np.int64)
            counts[0] = int(out[1, 0].sum(dtype=np.float64))
        return out[0].sum(axis=1, dtype=np.float64), counts

    def _clear_poses_outside(self, affine):
        """Send poses that put all of B outside A to A's unknown ring (u = v = 0).

        Their discrepancy is 0 either way; this keeps every coordinate the kernel converts to
        int32 within range, however far away a pose is. Poses within 10**7 cells need no check.
        """
        if np.abs(affine[:, 2::3]).max(initial=0.0) < 1e7:
            return affine
        rows, cols = self._b.shape
        j = np.array([0.0, cols, 0.0, cols])
        i = np.array([0.0, 0.0, rows, rows])
        u = affine[:, 0:1] * j + affine[:, 1:2] * i + affine[:, 2:3]
        v = affine[:, 3:4] * j + affine[:, 4:5] * i + affine[:, 5:6]
        outside = ((u.max(axis=1) < 0) | (u.min(axis=1) > self._a.shape[1])
                   | (v.max(axis=1) < 0) | (v.min(axis=1) > self._a.shape[0]))
        affine[outside] = 0.0
        return affine


class TaichiDense:
    """The "taichi" backend's ``_engines.DenseEvaluator``: eq. (6) for batches of poses of B in A,
    one launch per batch (the overlap counted in it).

    With ``count_only`` the kernel reads the maps' conflict grids (laid out as ``a.padded``, known
    exactly where >= 0) instead of their values: all an overlap count needs, with no copy of
    either map as values (the envelope discrepancy counts its overlap so).
    """

    counts_free = True           # the kernel counts the overlap as it sums

    def __init__(self, a, b, count_only: bool = False):
        if count_only:
            # B's conflict grid is read at its cells PAD rows and columns in
            self._kernel = TaichiEngine(a.conflict, b.conflict, b.rows + np.int32(PAD))
        else:
            self._kernel = TaichiEngine(a.padded, b.values, b.rows)
        self._affine = AffineMap(a.frame, b.frame, PAD, b_pad=PAD if count_only else 0)
        self._rows_i = b.rows[:, 0].astype(np.float64)

    def __call__(self, poses, count="all"):
        return self._kernel(self._affine(poses), count)

    def overlap(self, poses):
        """The overlap (N,) at each pose, one launch."""
        return self(poses, "all")[1]

    def bilinear(self, poses):
        """A interpolated bilinearly between its cell centres (an option beyond the paper):
        (e (N,), overlap (N,), gradient of e in (x, y, theta) (N, 3)), one launch."""
        poses = np.asarray(poses, dtype=np.float64)
        e, counts, sums = self._kernel.bilinear(self._affine(poses))
        # u = c0 j + c1 i + c2, v = c3 j + c4 i + c5: d/dq sum = dc0 S(g_u j) + dc1 S(g_u i) + ...
        su, suj, sv, svj = sums
        totals = np.stack([suj.sum(axis=1), su @ self._rows_i, su.sum(axis=1),
                           svj.sum(axis=1), sv @ self._rows_i, sv.sum(axis=1)], axis=1)      # (N, 6)
        return e, counts, np.einsum("kqc,kc->kq", self._affine_derivatives(poses), totals)

    def _affine_derivatives(self, poses, h=1e-6):
        """(N, 3, 6): d affine coefficients / d (x, y, theta), by central differences (the map is
        linear in x and y and smooth in theta: the error is ~h^2)."""
        out = np.empty((len(poses), 3, 6))
        for q in range(3):
            step = np.zeros(3)
            step[q] = h
            out[:, q] = (self._affine(poses + step) - self._affine(poses - step)) / (2.0 * h)
        return out
