"""Squared distance transforms on the grid, as Taichi kernels (Felzenszwalb & Huttenlocher, "Distance
Transforms of Sampled Functions", Theory of Computing 8, 2012).

``squared_distance(f)`` returns, per cell c, ``min_o (|c - o|^2 + f(o))`` over the cells o where
``f`` is finite (distances in cells; +inf where no cell is): with ``f = 0`` on the walls and +inf
elsewhere, the squared Euclidean distance to the nearest wall, exact (integers in float64); with
``f(o) = -2 s^2 ln p(o)``, ``exp(-D / (2 s^2))`` is the upper envelope of grey walls' Gaussians
(``_blur``'s envelope of coarse levels). Two passes of the one-dimensional transform, down every
column then along every row, each line a work item (the lower envelope of parabolas, with its
scratch arrays per line), so the result does not depend on the schedule. Equal to
``scipy.ndimage.distance_transform_edt`` bit for bit in the tests, and 3x faster here on
800 x 800 cells (20 ms against 60: no feature indices). On large grids the column pass reads the
columns in place: a thread's columns are neighbours, whose cells share cache lines (against
transposing for a pass along rows and back, measured: 2000 x 2000 cells 97 -> 78-86 ms, 1000 x
1000 19-21 -> 16); up to ``SMALL_CELLS`` it runs on the transposed grid (one kernel fewer to load).

For the few walls of a laser-built map (0.1-2 % of its cells) and a short reach, stamping is
faster still: ``near_squared_distance`` (each wall writes its squared distance into the disc
around it, the least wins: exact within the reach) and ``near_weighted_envelope`` (each grey wall
its weighted Gaussian, the largest wins). Both are integer or floating-point extrema, the same
whatever the order of the parallel writes.
"""

import functools

import numpy as np

from ._launch import launch, row_spread
from ._taichi import kernel_lock, kernels, taichi

__all__ = ["squared_distance", "wall_distance", "near_squared_distance", "near_weighted_envelope", "wall_runs", "far"]

# Grids of up to this many cells take ``squared_distance``'s column pass as the row kernel on the
# transposed grid: a process then loads one kernel variant instead of two (0.05-0.07 s from
# Taichi's offline cache), and the mapping loop meets this transform only on the coarsest levels
# of its loop closures' maps (under 10 k cells)
SMALL_CELLS = 1 << 16


def far(squared: np.ndarray) -> int:
    """``near_squared_distance``'s value where no wall is within reach: its dtype's largest."""
    return int(np.iinfo(squared.dtype).max)


def _build(ti):
    f64_2d = ti.types.ndarray(dtype=ti.f64, ndim=2)
    i32_2d = ti.types.ndarray(dtype=ti.i32, ndim=2)

    @ti.func
    def at(a: ti.template(), line, q, down: ti.template()):
        # element q of line ``line``: a row, or with ``down`` a column
        return a[q, line] if ti.static(down) else a[line, q]

    def lines_kernel(down):
        @ti.kernel
        def lines(f: f64_2d, d: f64_2d, v: i32_2d, z: f64_2d, spread: ti.types.ndarray(dtype=ti.i32, ndim=1)):
            # per line (a row, or a column: ``down``; the lines spread out: ``_launch.row_spread``):
            # the lower envelope of the parabolas (x - q)^2 + f(q) over its finite f(q), in v
            # (their q) and z (where each takes over), then read off at every x
            n = f.shape[0] if ti.static(down) else f.shape[1]
            for line, part in ti.ndrange(f.shape[1] if ti.static(down) else f.shape[0], spread.shape[0]):
                if part == 0:
                    k = -1
                    for q in range(n):
                        fq = at(f, line, q, down)
                        if fq < ti.math.inf:
                            qf = ti.cast(q, ti.f64)
                            s = ti.f64(-ti.math.inf)
                            while k >= 0:
                                p = v[line, k]
                                pf = ti.cast(p, ti.f64)
                                s = ((fq + qf * qf) - (at(f, line, p, down) + pf * pf)) / (2.0 * (qf - pf))
                                if s > z[line, k]:
                                    break
                                k -= 1
                            k += 1
                            v[line, k] = q
                            z[line, k] = ti.select(k == 0, -ti.math.inf, s)
                            z[line, k + 1] = ti.math.inf
                    if k < 0:
                        for q in range(n):
                            if ti.static(down):
                                d[q, line] = ti.math.inf
                            else:
                                d[line, q] = ti.math.inf
                    else:
                        j = 0
                        for q in range(n):
                            while z[line, j + 1] < q:
                                j += 1
                            p = v[line, j]
                            dq = ti.cast(q - p, ti.f64)
                            if ti.static(down):
                                d[q, line] = dq * dq + at(f, line, p, down)
                            else:
                                d[line, q] = dq * dq + at(f, line, p, down)

        return lines

    rows = lines_kernel(False)
    columns = lines_kernel(True)

    def stamp_kernel(weighted):
        @ti.kernel
        def stamp(rows_: ti.types.ndarray(dtype=ti.i32, ndim=1), starts: ti.types.ndarray(dtype=ti.i32, ndim=1),
                  ends: ti.types.ndarray(dtype=ti.i32, ndim=1), weights: ti.types.ndarray(dtype=ti.f64, ndim=1),
                  profile: ti.types.ndarray(dtype=ti.f64, ndim=1), first: ti.types.ndarray(dtype=ti.i32, ndim=1),
                  half: ti.types.ndarray(dtype=ti.i32, ndim=1), spread: ti.types.ndarray(dtype=ti.i32, ndim=1),
                  out: ti.types.ndarray(ndim=2), dt: ti.template()):
            # a row of the output per work item (the rows spread out: ``_launch.row_spread``; the
            # output filled beforehand with the value beyond reach): the runs of walls within
            # reach rows of it (runs sorted by row, ``first[r]`` the first on row r or later) each
            # write the cells of that row within reach of the run, ``half[d + reach]`` cells
            # beyond either end on row d away, their squared distance to the run's nearest wall
            # (the least wins) or, weighted, weight * profile[that] (the largest wins); the row
            # belongs to its work item, so no atomics, and the result does not depend on the order
            # of the writes
            h, w = out.shape[0], out.shape[1]
            reach = (half.shape[0] - 1) // 2
            for i, part in ti.ndrange(h, spread.shape[0]):
                if part == 0:
                    for k in range(first[ti.max(i - reach, 0)], first[ti.min(i + reach + 1, h)]):
                        di = rows_[k] - i
                        dy2 = di * di
                        chord = half[di + reach]
                        a, b = starts[k], ends[k]
                        # left of the run, along it (its row's distance alone), right of it
                        for j in range(ti.max(a - chord, 0), ti.min(a, w)):
                            q = dy2 + (a - j) * (a - j)
                            if ti.static(weighted):
                                out[i, j] = ti.max(out[i, j], weights[k] * profile[q])
                            else:
                                out[i, j] = ti.cast(ti.min(ti.cast(out[i, j], ti.i32), q), dt)
                        if ti.static(weighted):
                            v = weights[k] * profile[dy2]
                            for j in range(a, b + 1):
                                out[i, j] = ti.max(out[i, j], v)
                        else:
                            for j in range(a, b + 1):
                                out[i, j] = ti.cast(ti.min(ti.cast(out[i, j], ti.i32), dy2), dt)
                        for j in range(b + 1, ti.min(b + chord + 1, w)):
                            q = dy2 + (j - b) * (j - b)
                            if ti.static(weighted):
                                out[i, j] = ti.max(out[i, j], weights[k] * profile[q])
                            else:
                                out[i, j] = ti.cast(ti.min(ti.cast(out[i, j], ti.i32), q), dt)

        return stamp

    stamp, stamp_weighted = stamp_kernel(False), stamp_kernel(True)

    return rows, stamp, stamp_weighted, columns


class _Scratch:
    """Flat buffers kept between calls, grown as needed: fresh arrays of megabytes cost a page
    fault per 4 KiB on first touch, which here cost more than the transform itself (measured:
    34 ms against 13 ms for 800 x 800 cells). Grids above ``KEEP_CELLS`` get fresh arrays, so
    at most about 55 MB stay held."""

    KEEP_CELLS = 2**21

    def __init__(self):
        self._flat = {}

    def get(self, name, shape, dtype):
        size = int(np.prod(shape))
        if size > self.KEEP_CELLS:
            self._flat.pop(name, None)
            return np.empty(shape, dtype=dtype)
        flat = self._flat.get(name)
        if flat is None or flat.size < size or flat.dtype != dtype:
            flat = self._flat[name] = np.empty(max(size, 1), dtype=dtype)
        return flat[:size].reshape(shape)


_SCRATCH = _Scratch()


def squared_distance(f: np.ndarray) -> np.ndarray:
    """``min_o (|c - o|^2 + f(o))`` per cell c (see the module docstring); ``f`` (H, W), +inf where
    no source is. Returns float64 (H, W), +inf everywhere when ``f`` has no finite value."""
    f = np.ascontiguousarray(f, dtype=np.float64)
    h, w = f.shape
    d = np.empty((h, w))
    with kernel_lock():
        rows = kernels(_build)[0]
        # down the columns, then along the rows. The columns in place (a thread's columns are
        # neighbours, whose rows share cache lines: faster than transposing for a pass along
        # rows); up to SMALL_CELLS as rows of the transposed grid, the same lines and bits
        scratch = (_SCRATCH.get("v", (w, h + 1), np.int32), _SCRATCH.get("z", (w, h + 2), np.float64), row_spread(w))
        if h * w <= SMALL_CELLS:
            down = np.empty((w, h))
            launch(rows, (np.ascontiguousarray(f.T), down, *scratch), None)
            g = np.ascontiguousarray(down.T)
        else:
            g = _SCRATCH.get("g", (h, w), np.float64)
            launch(kernels(_build)[3], (f, g, *scratch), None)
        launch(rows, (g, d, _SCRATCH.get("v", (h, w + 1), np.int32), _SCRATCH.get("z", (h, w + 2), np.float64),
                      row_spread(h)), None)
    return d


def _taichi_type(dtype):
    """Taichi's type for a NumPy dtype of the stamps."""
    ti = taichi()
    return {"uint8": ti.u8, "uint16": ti.u16, "uint32": ti.u32, "float64": ti.f64}[np.dtype(dtype).name]


@functools.lru_cache(maxsize=32)
def _chords(reach: int) -> np.ndarray:
    """The disc's chord on the row d away, at d + ``reach`` (int32, read-only, made once a reach)."""
    d = np.arange(-reach, reach + 1)
    half = np.floor(np.sqrt(reach * reach - d * d)).astype(np.int32)
    while np.any(half * half + d * d > reach * reach):                    # (sqrt rounding up at squares)
        half -= (half * half + d * d > reach * reach)
    half.setflags(write=False)
    return half


def wall_runs(rows, cols, weights, shape, reach, merge_weights: bool = True):
    """The stamp kernels' walls: (rows, starts, ends, weights, first, half) for walls at (``rows``,
    ``cols``) (in any order; ``weights`` None: all 0) on a grid of ``shape``: runs of walls next to
    each other on a row (of one weight, unless ``merge_weights``), sorted by row, each run's row,
    first and last column and weight; ``first[r]`` the first run on row r or later; ``half[d +
    reach]`` the disc's chord on the row d away. Each run writes a row's cells within reach of it
    once, where each of its walls would write its own overlapping chord: the same least distance,
    and for a weighted envelope the same largest value where the profile does not increase (else
    ``merge_weights`` False: runs of one weight only)."""
    rows = np.ascontiguousarray(rows, dtype=np.int32)
    cols = np.ascontiguousarray(cols, dtype=np.int32)
    reach = int(reach)
    if rows.shape != cols.shape or rows.ndim != 1 or not 0 <= reach <= 2**14:
        raise ValueError(f"rows and cols must be 1-D of one length and 0 <= reach <= 16384; got {rows.shape}, "
                         f"{cols.shape}, {reach}")
    weights = np.zeros(len(rows)) if weights is None else np.ascontiguousarray(weights, dtype=np.float64)
    half = _chords(reach)
    if len(rows) == 0:
        return rows, cols, cols, weights, np.zeros(shape[0] + 1, dtype=np.int32), half
    low = int(cols.min())
    key = rows.astype(np.int64) * (int(cols.max()) - low + 2) + (cols - low)         # row, then column
    if np.any(key[1:] <= key[:-1]):                         # nonzero()'s walls come in order already
        order = np.argsort(key, kind="stable")
        rows, cols, weights = rows[order], cols[order], weights[order]
    new = np.ones(len(rows), dtype=bool)
    new[1:] = (rows[1:] != rows[:-1]) | (cols[1:] != cols[:-1] + 1)
    if len(weights) > 1:
        new[1:] |= weights[1:] != weights[:-1] if merge_weights else True
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], len(rows)) - 1
    rows, weights = rows[starts], weights[starts]
    starts, ends = cols[starts], cols[ends]
    first = np.searchsorted(rows, np.arange(shape[0] + 1)).astype(np.int32)
    return rows, starts, ends, weights, first, half


def _stamp(kernel, rows, cols, weights, profile, shape, reach, dtype):
    """The stamp kernel's output of ``shape`` for walls at (``rows``, ``cols``) (in any order);
    unweighted, ``far(out)`` beyond the reach."""
    shape = tuple(int(n) for n in shape)
    beyond = 0 if weights is not None else np.iinfo(dtype).max
    runs = wall_runs(rows, cols, weights, shape, reach, weights is None or bool(np.all(np.diff(profile) <= 0)))
    if len(runs[0]) == 0 or 0 in shape:
        return np.full(shape, beyond, dtype=dtype)
    rows, starts, ends, weights, first, half = runs
    out = np.empty(shape, dtype=dtype)
    # the value beyond reach first, by NumPy: a Taichi loop over the cells runs scalar, about 1 ns
    # a cell here, NumPy's fill a hundredth of that (measured on the mapping loop's front-end
    # targets, seattle, 240 of them: the squared distances' launch 0.75 -> 0.57 ms)
    out.fill(beyond)
    with kernel_lock():
        launch(kernels(_build)[kernel], (rows, starts, ends, weights, np.ascontiguousarray(profile, dtype=np.float64),
                                         first, half, row_spread(shape[0]), out), _taichi_type(dtype))
    return out


def near_squared_distance(rows, cols, shape, reach: int) -> np.ndarray:
    """The squared Euclidean distance, in cells, from every cell of a grid of ``shape`` to the
    nearest of the walls at (``rows``, ``cols``), where it is at most ``reach`` cells; ``far``
    elsewhere. Exact (``squared_distance``'s value within reach), in the smallest unsigned integer
    type that holds reach**2 + 1 (uint8 for the envelope of laser submaps: a quarter of int32's
    memory, whose first touch is most of the cost). Each wall stamps the disc
    of radius ``reach`` around it: for the few walls of a laser-built map (0.1-2 % of its cells)
    and a short reach, a fraction of the exact transform's time (which visits every cell twice
    and keeps a lower envelope of parabolas per line)."""
    reach = int(reach)
    dtype = next(t for t in (np.uint8, np.uint16, np.uint32) if reach * reach < np.iinfo(t).max)
    return _stamp(1, rows, cols, None, np.zeros(1), shape, reach, dtype)


def near_weighted_envelope(rows, cols, weights, shape, reach: int, profile: np.ndarray) -> np.ndarray:
    """max over the walls at (``rows``, ``cols``) within ``reach`` cells of ``weights[k] *
    profile[squared distance]`` per cell of a grid of ``shape`` (0 where none is within reach):
    the upper envelope of grey walls, each wall stamping its disc (float64; ``profile`` has
    reach**2 + 1 entries)."""
    return _stamp(2, rows, cols, np.asarray(weights, dtype=np.float64), profile, shape, reach, np.float64)


def wall_distance(walls: np.ndarray) -> np.ndarray:
    """The Euclidean distance, in cells, from every cell to the nearest True cell of ``walls``
    (+inf when there is none): ``scipy.ndimage.distance_transform_edt(~walls)``, bit for bit."""
    return np.sqrt(squared_distance(np.where(walls, 0.0, np.inf)))
