"""Taichi kernel counting, per grid cell, the laser beams that end in it and the beams that pass through.
(And one that reads each cell's value from a table of its two counts: ``lookup_pairs_taichi``.)

The Taichi engine of ``scans.count_traversals``; it returns exactly what the NumPy reference does.
Conventions:

- A segment is (u0, v0, u1, v1) in lattice coordinates, in cells (metres / resolution, in the
  grid's frame): u the column, v the row; lattice cell (row, col) spans [col, col + 1) x
  [row, row + 1). The counts' array holds the lattice cells from ``offset`` = (row0, col0) on: its
  cell [r, c] is lattice cell (row0 + r, col0 + c). The walk runs on the lattice and only the
  counting subtracts the (integer) offset, so a beam's cells do not depend on the array's extent:
  counts of several launches into one array (``out``, an array grown between them) are those of
  one launch, bit for bit.
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
  counts are added with integer atomics, so the result does not depend on the schedule. A beam
  takes at most |u1 - u0| + |v1 - v0| + 3 steps and stops early once it has left the grid for good.

Taichi is initialised lazily by ``_taichi.taichi`` (which also refuses a forked
child) and launches are serialised with its lock. The kernel is built on first use and kept:
Taichi keeps a kernel across ``ti.init`` and ``ti.reset`` and compiles it again for the new
program, as it does for the kernels of ``_kernels``.
"""

import numpy as np

from ._errors import InvalidOptionError, shown
from ._launch import launch
from ._taichi import kernel_lock, kernels

__all__ = ["count_traversals_taichi", "lookup_pairs_taichi"]

# Segment coordinates beyond this many cells are refused: cell indices stay well inside int32
# and the number of steps of a beam stays bounded.
MAX_COORDINATE = float(2 ** 28)



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
                 hits: ti.types.ndarray(dtype=ti.i32, ndim=2), misses: ti.types.ndarray(dtype=ti.i32, ndim=2),
                 offset: ti.types.ndarray(dtype=ti.i32, ndim=1)):
        rows = hits.shape[0]
        cols = hits.shape[1]
        row0 = offset[0]
        col0 = offset[1]
        for k in range(segments.shape[0]):
            end_col = ti.cast(ti.floor(segments[k, 2]), ti.i32) - col0
            end_row = ti.cast(ti.floor(segments[k, 3]), ti.i32) - row0
            if hit[k] != 0 and 0 <= end_row < rows and 0 <= end_col < cols:
                ti.atomic_add(hits[end_row, end_col], 1)
        for k in range(segments.shape[0]):
            u0 = segments[k, 0]
            v0 = segments[k, 1]
            u1 = segments[k, 2]
            v1 = segments[k, 3]
            end_col = ti.cast(ti.floor(u1), ti.i32) - col0          # in the array
            end_row = ti.cast(ti.floor(v1), ti.i32) - row0
            has_hit = hit[k] != 0
            lo = own_lo[k]
            hi = own_hi[k]
            # direction per axis from the endpoints themselves (no subtraction to round to 0)
            su = ti.select(u1 > u0, 1, ti.select(u1 < u0, -1, 0))
            sv = ti.select(v1 > v0, 1, ti.select(v1 < v0, -1, 0))
            # the first cell (on the lattice): on a grid line, the one the segment moves into
            col = ti.cast(ti.select(su < 0, ti.ceil(u0) - 1.0, ti.floor(u0)), ti.i32)
            row = ti.cast(ti.select(sv < 0, ti.ceil(v0) - 1.0, ti.floor(v0)), ti.i32)
            # the next grid line along each axis: the far edge of the current cell
            line_u = col + ti.select(su > 0, 1, 0)
            line_v = row + ti.select(sv > 0, 1, 0)
            t_u = next_crossing(line_u, u0, u1, su)
            t_v = next_crossing(line_v, v0, v1, sv)
            steps = ti.cast(ti.abs(u1 - u0) + ti.abs(v1 - v0), ti.i32) + 3
            for _ in range(steps):
                r = row - row0                                  # in the array
                c = col - col0
                inside = 0 <= r < rows and 0 <= c < cols
                if inside and not (has_hit and r == end_row and c == end_col):
                    counted = True
                    if lo < hi:
                        if hits[r, c] > 0:                      # a hit there: its own scan's?
                            counted = not own_hit(own, lo, hi, r * cols + c)
                    if counted:
                        ti.atomic_add(misses[r, c], 1)
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
                if (col < col0 and su <= 0) or (col >= col0 + cols and su >= 0) or (row < row0 and sv <= 0) or \
                        (row >= row0 + rows and sv >= 0):
                    break                               # outside and moving away: never back in

    return traverse


def own_hit_cells(segments, hit, scan, shape, offset=(0, 0)):
    """(own, lo, hi): the linear indices (r * cols + c, in the array) of the cells where each
    scan's beams end with a return, sorted within each scan, and per beam the range
    ``own[lo:hi]`` of its own scan's (empty when ``scan`` is None: each beam its own scan)."""
    rows, cols = shape
    n = segments.shape[0]
    if scan is None:
        return np.zeros(1, dtype=np.int32), np.zeros(n, dtype=np.int32), np.zeros(n, dtype=np.int32)
    scan = np.ascontiguousarray(scan, dtype=np.int64)
    if scan.shape != (n,) or (n > 1 and np.any(np.diff(scan) < 0)):
        raise InvalidOptionError(f"scan must be (R,) and non-decreasing (beams grouped by scan); got {scan.shape}")
    end_col, end_row = np.floor(segments[:, 2]) - offset[1], np.floor(segments[:, 3]) - offset[0]
    keep = (hit != 0) & (end_row >= 0) & (end_row < rows) & (end_col >= 0) & (end_col < cols)
    cells = (end_row[keep] * cols + end_col[keep]).astype(np.int64)
    order = np.lexsort((cells, scan[keep]))
    own = cells[order].astype(np.int32)
    owner = scan[keep][order]
    lo = np.searchsorted(owner, scan, side="left").astype(np.int32)
    hi = np.searchsorted(owner, scan, side="right").astype(np.int32)
    return (own if len(own) else np.zeros(1, dtype=np.int32)), lo, hi


def count_traversals_taichi(segments, hit, shape, scan=None, offset=(0, 0), out=None):
    """Count, per cell, the beams that end in it with a return and the beams that pass through it.

    Parameters
    ----------
    segments : array_like (R, 4) float64
        The beams as (u0, v0, u1, v1) in lattice coordinates (cells; u column, v row), from the
        laser to the endpoint. Finite, at most ``MAX_COORDINATE`` in magnitude.
    hit : array_like (R,) int32
        1 if the beam has a return (its endpoint cell is hit), 0 if not.
    shape : (int, int)
        The array's (rows, cols).
    scan : array_like (R,) int, optional
        The scan of each beam, non-decreasing: a beam does not miss the cells where beams of its
        own scan end with a return. None: every beam is a scan of its own.
    offset : (int, int)
        The lattice cell (row0, col0) of the array's cell [0, 0].
    out : (hits, misses), optional
        C-contiguous int32 arrays of ``shape`` to add the counts into (returned).

    Returns
    -------
    hits, misses : ndarray of ``shape``, int32
        Per cell, the beams with a return ending in it, and the beams passing through it
        otherwise (each beam once per cell; a beam without a return also misses its endpoint's
        cell). Cells outside the array are not counted. Equal to ``scans.count_traversals`` with
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
        raise InvalidOptionError(f"shape must be (rows, cols) >= 0; got {shown(shape)}")
    row0, col0 = (int(n) for n in offset)
    if out is None:
        hits, misses = np.zeros((rows, cols), dtype=np.int32), np.zeros((rows, cols), dtype=np.int32)
    else:
        hits, misses = out
        if any(a.shape != (rows, cols) or a.dtype != np.int32 or not a.flags.c_contiguous for a in out):
            raise InvalidOptionError(f"out must be two C-contiguous int32 arrays of shape {(rows, cols)}")
    if abs(row0) > MAX_COORDINATE or abs(col0) > MAX_COORDINATE:
        raise InvalidOptionError(f"offset must be at most {MAX_COORDINATE:g} cells; got {shown(offset)}")
    if segments.shape[0] == 0 or hits.size == 0:
        return hits, misses
    if not np.all(np.abs(segments) <= MAX_COORDINATE):          # also false for NaN
        raise InvalidOptionError(f"segment coordinates must be finite and at most {MAX_COORDINATE:g} cells")
    own, lo, hi = own_hit_cells(segments, hit, scan, (rows, cols), (row0, col0))
    with kernel_lock():
        launch(kernels(_build_kernel),
               (segments, hit, own, lo, hi, hits, misses, np.array([row0, col0], dtype=np.int32)), None)
    return hits, misses


def _build_lookup(ti):
    @ti.kernel
    def lookup(hits: ti.types.ndarray(dtype=ti.i32, ndim=1), misses: ti.types.ndarray(dtype=ti.i32, ndim=1),
               table: ti.types.ndarray(ndim=2), out: ti.types.ndarray(ndim=1)):
        for k in range(hits.shape[0]):
            out[k] = table[hits[k], misses[k]]

    return lookup


def lookup_pairs_taichi(hits, misses, table):
    """(H, W) ``table[hits, misses]`` per cell, in one pass, of the table's dtype (float64 or
    uint8): the counts must lie within the table (0 <= hits < table rows, 0 <= misses < table
    columns)."""
    hits = np.ascontiguousarray(hits, dtype=np.int32)
    misses = np.ascontiguousarray(misses, dtype=np.int32)
    table = np.ascontiguousarray(table)
    out = np.empty(hits.shape, dtype=table.dtype)
    if out.size:
        with kernel_lock():
            launch(kernels(_build_lookup), (hits.reshape(-1), misses.reshape(-1), table, out.reshape(-1)), None)
    return out
