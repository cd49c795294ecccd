"""Taichi kernel counting, per grid cell, the laser beams that end in it and the beams that pass through.

The Taichi engine of ``scans.count_traversals``; it returns exactly what the NumPy reference does.
Conventions:

- A segment is (u0, v0, u1, v1) in grid coordinates, in cells: u the column, v the row; cell
  (row, col) spans [col, col + 1) x [row, row + 1).
- Per beam: +1 to ``hits`` at the endpoint cell (floor(v1), floor(u1)) if the beam has a return,
  and +1 to ``misses`` at every other cell the segment passes through (at the endpoint cell too
  when it has no return), except the cells where a beam of its own scan ends with a return: a
  scan's hits go in before its misses, as Cartographer inserts a scan (the beam next to a grazing
  return would otherwise clear the return's cell). Each cell counts at most once per beam. Cells
  outside the grid are skipped.
- The traversal is Amanatides & Woo's (1987) grid walk in float64: per axis, the parameter t in
  [0, 1] of the next grid line the segment crosses (tMax); the walk steps along the axis that
  crosses first, along both at once when they cross at the same t (a grid corner: the diagonal
  neighbour is touched over zero length and not counted), and stops at t = 1. A segment starting
  on a grid line starts in the cell it moves into. tMax is computed afresh from the line's index,
  ``(k - u0) / (u1 - u0)``, as the reference computes its crossings, rather than accumulated by
  tDelta: then both see the same crossings, in the same order, with the same ties, to the bit.
- All beams run in one parallel launch, the hits in a first loop, then the walks, which look up
  a cell holding a hit in the sorted list of their own scan's hit cells (a binary search); the
  counts are added with integer atomics, so the result does not depend on the schedule. A beam takes at most |u1 - u0| + |v1 - v0| + 3 steps and stops
  early once it has left the grid for good.

Taichi is initialised lazily by ``_kernels.ensure_initialized`` (which also refuses a forked
child) and launches are serialised with its lock. The kernel is built on first use and kept:
Taichi keeps a kernel across ``ti.init`` and ``ti.reset`` and compiles it again for the new
program, as it does for the kernels of ``_kernels``.
"""

import numpy as np

from ._errors import InvalidOptionError
from ._kernels import _STATE, ensure_initialized, kernel_lock

__all__ = ["count_traversals_taichi"]

# Segment coordinates beyond this many cells are refused: cell indices stay well inside int32
# and the number of steps of a beam stays bounded.
MAX_COORDINATE = float(2 ** 28)

_KERNEL = {"traverse": None}


def _build_kernel(ti):
    @ti.func
    def next_crossing(line, a0, a1, step):
        """The parameter t at which the segment reaches grid line ``line`` of its axis (2 if it
        does not move along the axis, past the segment's end)."""
        t = ti.f64(2.0)
        if step != 0:
            t = (ti.cast(line, ti.f64) - a0) / (a1 - a0)
        return t

    @ti.func
    def own_hit(own: ti.template(), lo, hi, cell):
        """Whether ``cell`` is in the sorted ``own[lo:hi]``."""
        a, b = lo, hi
        while a < b:
            mid = (a + b) // 2
            if own[mid] < cell:
                a = mid + 1
            else:
                b = mid
        return a < hi and own[a] == cell

    @ti.kernel
    def traverse(segments: ti.types.ndarray(dtype=ti.f64, ndim=2), hit: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 own: ti.types.ndarray(dtype=ti.i32, ndim=1), own_lo: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 own_hi: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 hits: ti.types.ndarray(dtype=ti.i32, ndim=2), misses: ti.types.ndarray(dtype=ti.i32, ndim=2)):
        rows = hits.shape[0]
        cols = hits.shape[1]
        for k in range(segments.shape[0]):
            end_col = ti.cast(ti.floor(segments[k, 2]), ti.i32)
            end_row = ti.cast(ti.floor(segments[k, 3]), ti.i32)
            if hit[k] != 0 and 0 <= end_row < rows and 0 <= end_col < cols:
                ti.atomic_add(hits[end_row, end_col], 1)
        for k in range(segments.shape[0]):
            u0 = segments[k, 0]
            v0 = segments[k, 1]
            u1 = segments[k, 2]
            v1 = segments[k, 3]
            end_col = ti.cast(ti.floor(u1), ti.i32)
            end_row = ti.cast(ti.floor(v1), ti.i32)
            has_hit = hit[k] != 0
            lo = own_lo[k]
            hi = own_hi[k]
            # direction per axis from the endpoints themselves (no subtraction to round to 0)
            su = ti.select(u1 > u0, 1, ti.select(u1 < u0, -1, 0))
            sv = ti.select(v1 > v0, 1, ti.select(v1 < v0, -1, 0))
            # the first cell: on a grid line, the one the segment moves into
            col = ti.cast(ti.select(su < 0, ti.ceil(u0) - 1.0, ti.floor(u0)), ti.i32)
            row = ti.cast(ti.select(sv < 0, ti.ceil(v0) - 1.0, ti.floor(v0)), ti.i32)
            # the next grid line along each axis: the far edge of the current cell
            line_u = col + ti.select(su > 0, 1, 0)
            line_v = row + ti.select(sv > 0, 1, 0)
            t_u = next_crossing(line_u, u0, u1, su)
            t_v = next_crossing(line_v, v0, v1, sv)
            steps = ti.cast(ti.abs(u1 - u0) + ti.abs(v1 - v0), ti.i32) + 3
            for _ in range(steps):
                inside = 0 <= row < rows and 0 <= col < cols
                if inside and not (has_hit and row == end_row and col == end_col):
                    counted = True
                    if lo < hi:
                        if hits[row, col] > 0:                  # a hit there: its own scan's?
                            counted = not own_hit(own, lo, hi, row * cols + col)
                    if counted:
                        ti.atomic_add(misses[row, col], 1)
                t = ti.min(t_u, t_v)
                if t >= 1.0:
                    break
                if t_u == t:
                    col += su
                    line_u += su
                    t_u = next_crossing(line_u, u0, u1, su)
                if t_v == t:
                    row += sv
                    line_v += sv
                    t_v = next_crossing(line_v, v0, v1, sv)
                if (col < 0 and su <= 0) or (col >= cols and su >= 0) or (row < 0 and sv <= 0) or \
                        (row >= rows and sv >= 0):
                    break                               # outside and moving away: never back in

    return traverse


def own_hit_cells(segments, hit, scan, shape):
    """(own, lo, hi): the linear indices (row * cols + col) of the cells where each scan's beams
    end with a return, sorted within each scan, and per beam the range ``own[lo:hi]`` of its own
    scan's (empty when ``scan`` is None: each beam its own scan)."""
    rows, cols = shape
    n = segments.shape[0]
    if scan is None:
        return np.zeros(1, dtype=np.int32), np.zeros(n, dtype=np.int32), np.zeros(n, dtype=np.int32)
    scan = np.ascontiguousarray(scan, dtype=np.int64)
    if scan.shape != (n,) or (n > 1 and np.any(np.diff(scan) < 0)):
        raise InvalidOptionError(f"scan must be (R,) and non-decreasing (beams grouped by scan); got {scan.shape}")
    end_col, end_row = np.floor(segments[:, 2]), np.floor(segments[:, 3])
    keep = (hit != 0) & (end_row >= 0) & (end_row < rows) & (end_col >= 0) & (end_col < cols)
    cells = (end_row[keep] * cols + end_col[keep]).astype(np.int64)
    order = np.lexsort((cells, scan[keep]))
    own = cells[order].astype(np.int32)
    owner = scan[keep][order]
    lo = np.searchsorted(owner, scan, side="left").astype(np.int32)
    hi = np.searchsorted(owner, scan, side="right").astype(np.int32)
    return (own if len(own) else np.zeros(1, dtype=np.int32)), lo, hi


def count_traversals_taichi(segments, hit, shape, scan=None):
    """Count, per cell, the beams that end in it with a return and the beams that pass through it.

    Parameters
    ----------
    segments : array_like (R, 4) float64
        The beams as (u0, v0, u1, v1) in grid coordinates (cells; u column, v row), from the
        laser to the endpoint. Finite, at most ``MAX_COORDINATE`` in magnitude.
    hit : array_like (R,) int32
        1 if the beam has a return (its endpoint cell is hit), 0 if not.
    shape : (int, int)
        The grid's (rows, cols).
    scan : array_like (R,) int, optional
        The scan of each beam, non-decreasing: a beam does not miss the cells where beams of its
        own scan end with a return. None: every beam is a scan of its own.

    Returns
    -------
    hits, misses : ndarray of ``shape``, int32
        Per cell, the beams with a return ending in it, and the beams passing through it
        otherwise (each beam once per cell; a beam without a return also misses its endpoint's
        cell). Cells outside the grid are not counted. Equal to ``scans.count_traversals`` with
        ``engine="numpy"``.

    Raises
    ------
    InvalidOptionError
        If the arrays have the wrong shape, or a coordinate is not finite or too large.
    """
    rows, cols = (int(n) for n in shape)
    segments = np.ascontiguousarray(segments, dtype=np.float64)
    hit = np.ascontiguousarray(hit, dtype=np.int32)
    if segments.ndim != 2 or segments.shape[1] != 4 or hit.shape != (segments.shape[0],):
        raise InvalidOptionError(f"segments must be (R, 4) and hit (R,); got {segments.shape} and {hit.shape}")
    if rows < 0 or cols < 0:
        raise InvalidOptionError(f"shape must be (rows, cols) >= 0; got {shape!r}")
    hits = np.zeros((rows, cols), dtype=np.int32)
    misses = np.zeros((rows, cols), dtype=np.int32)
    if segments.shape[0] == 0 or hits.size == 0:
        return hits, misses
    if not np.all(np.abs(segments) <= MAX_COORDINATE):          # also false for NaN
        raise InvalidOptionError(f"segment coordinates must be finite and at most {MAX_COORDINATE:g} cells")
    own, lo, hi = own_hit_cells(segments, hit, scan, (rows, cols))
    with kernel_lock():
        ensure_initialized()
        if _KERNEL["traverse"] is None:
            _KERNEL["traverse"] = _build_kernel(_STATE["ti"])
        _KERNEL["traverse"](segments, hit, own, lo, hi, hits, misses)
    return hits, misses
