"""The envelope discrepancy: walls against the other map's free space, both ways (an option
beyond the paper, and the default for maps built from laser scans).

The paper's e (eq. 6) sums |p_A - p_B| over every known cell of B. On laser-built maps, whose
walls are one cell thick at the edge of the known area, that sum is dominated by free cells and
by the blur's grey halos, and it is lower away from the truth than at it (bench/TUNING.md). This
discrepancy keeps the paper's idea, conflicts between what two maps saw, occupied against free,
unknown cells not compared, and counts only the occupied cells, each against the other map:

    e = sum_{b occupied in B} w_b c_A(T(r) b) + sum_{a occupied in A} w_a c_B(T(r)^-1 a)

- ``c_M(x) = 1 - hi_M(x)`` on a known cell of M, where ``hi_M`` is the Gaussian envelope of M's
  occupied cells (``_blur``, kind "envelope": 1 on a wall, ``exp(-d^2 / 2 sigma^2)`` at distance
  d from the nearest one). A wall landing on the other map's wall costs 0, on its free space far
  from any wall 1, and in between a smooth bowl of width sigma.
- On an unknown cell of the other map a wall costs ``min(unknown_cost, 1 - hi_M(x))``, the
  envelope reaching into unknown cells too (0: not compared, as in the paper; > 0: a wall the
  other map cannot explain pays a little, so pushing a map into the other map's unknown area is
  no longer free). Behind a wall a laser sees nothing: a wall of the other map landing there, next
  to this map's wall, is explained by it and pays its distance, as it would in front. Charged
  the full ``unknown_cost`` there, a thick wall paid more behind a thin one than in front of it,
  and a lone scan matched against a submap came out 1-2 cm ahead of the truth on average
  (simulated run, seattle, csail: a forward bias of 7-16 mm, 4-10 mm since; median errors
  15 -> 10 mm and 0.19 -> 0.14 degree on the simulated run). Off the other map's grid it costs
  nothing: a grid's edge is often only where a map was cropped (the paper's corridor), and
  charging for it would turn the crop into structure (a corridor would lose its degenerate
  direction). Where the grid is only the box around what was seen (a laser submap's), that free
  edge is structure instead: with ``grid_edge="unknown"`` a wall off the grid pays
  ``unknown_cost``, as on an unknown cell no wall reaches.
- ``w`` is the cell's occupancy (1 on trinary maps; grey on coarse pyramid levels).
- ``interpolation="bilinear"`` (an option): a wall's cost is the bilinear blend of the costs
  above at the four cell centres around where it lands (a corner off the grid costing as above), so e
  no longer steps as walls cross cell boundaries. With the nearest cell, e along a path of poses
  on laser submaps rises and falls by a wall's worth between poses a few millimetres apart, the
  optimiser's stencil meets those steps, and a match on the given maps alone (one pyramid level)
  often stopped at its guess with a pose 2-15 cm off (2026-12-06, aces: 124 of 439 scan matches);
  the blend costs four lookups a wall. The overlap is still counted at the nearest cell.

Both sums visit occupied cells only (5-15 % of the known cells of a building map), so one
evaluation costs a fraction of the paper's. It is symmetric: swapping A and B and inverting r
gives the same value (up to the nearest-cell lookups). The number of occupied cells that land on
known cells of the other map is the overlap.

The kernel: for a batch of N poses, per (pose, chunk of ``CHUNK`` points) one partial sum, no
atomics (bit-identical run after run). It takes the poses themselves and makes each one's affine
maps (eq. 5: ``_cost.AffineMap.matrix`` times its cosine, sine and translation, A's points
through the inverse pose), which NumPy made before each launch in a tenth of a front-end match's
time (measured: the match 0.93-0.95 of its time, the same float32 coefficients). Small batches run on
one thread (``SERIAL_BELOW``). Grids are float32 padded with ``PAD`` cells off the map (-4),
``1 - hi`` on known cells and ``-1 - (1 - hi)`` on unknown ones (in [-2, -1]); points are a
(4, M) float32 array of columns ``(row, col, w, w * unknown_cost)``, cell indices in their own
grid (laid out by component: measured 3.5x faster than (M, 4) rows, whose loads do not
vectorise).
"""

import functools

import numpy as np

from ._cost import AffineMap
from ._distance import _SCRATCH, _taichi_type, wall_runs
from ._grid import GridMap, cells
from ._kernels import PAD
from ._launch import Launcher, launch, row_spread
from ._se2 import as_poses, inverse, transform_points
from ._taichi import kernel_lock, kernels

__all__ = ["conflict_grid", "envelope_reach", "envelope_profile", "near_conflict_grid", "wall_points", "points_array",
           "EnvelopeEngine", "NumpyEnvelope", "CHUNK"]

CHUNK = 256
# Batches of fewer point lookups (poses times walls of both maps) run on one thread: waking
# Taichi's worker threads costs more than they save there (measured on the 2-core machine: at
# 24k lookups 11-18 us serial against 16-24 us in parallel, even at 96k; at 190k parallel wins).
# The sums are the same either way (one per chunk, each summed in order).
SERIAL_BELOW = 100_000
_OFF_MAP = np.float32(-4.0)
_EDGE = {False: np.zeros(1, dtype=np.float32), True: np.ones(1, dtype=np.float32)}   # ``envelope_chunks``'s flag
WALL = 0.5                      # a cell with p >= this is a wall, weighing p (``wall_points``)


def conflict_grid(hi: np.ndarray, unknown: np.ndarray) -> np.ndarray:
    """The padded float32 lookup grid: ``1 - hi`` on known cells, ``-1 - (1 - hi)`` (in [-2, -1])
    on ``unknown`` ones, -4 on the ring off the map. ``hi`` is the envelope on every cell (NaN,
    where no wall reaches, counts as 0)."""
    out = np.full((hi.shape[0] + 2 * PAD, hi.shape[1] + 2 * PAD), _OFF_MAP, dtype=np.float32)
    inner = out[PAD:PAD + hi.shape[0], PAD:PAD + hi.shape[1]]
    np.subtract(1.0, hi, out=inner, casting="unsafe")          # in float64, rounded to float32 once
    inner[np.isnan(hi)] = 1.0
    np.subtract(np.float32(-1.0), inner, out=inner, where=unknown)
    return out


def envelope_reach(width_cells: float) -> int:
    """Cells beyond which the envelope exp(-d^2 / 2 width^2) (width in cells) is below 2**-25, so
    that 1 - hi rounds to 1 in float32: the conflict grid is the same as if it reached farther."""
    return int(np.ceil(width_cells * np.sqrt(50.0 * np.log(2.0)))) + 1


def envelope_profile(reach: int, ratio: float) -> np.ndarray:
    """exp(-(d * ratio)^2 / 2) at d = sqrt(k) for the squared distances k = 0 .. reach^2, and a
    last 0 for farther (ratio = resolution / width): the envelope of a wall at 1 by squared
    distance in cells, in the blur's own arithmetic (``_blur``)."""
    d = np.sqrt(np.arange(reach * reach + 1, dtype=np.float64))
    d *= ratio
    profile = d * -0.5
    profile *= d
    np.exp(profile, out=profile)
    return np.append(profile, 0.0)


def near_conflict_grid(known: np.ndarray, prob, reach: int, ratio: float, walls, *, squared: bool = False):
    """``conflict_grid`` from the walls' envelope stamped within its reach: hi = max(p, envelope)
    on known cells, the envelope on unknown ones. Returns (conflict grid, squared distances or None).

    ``known``: (H, W) bool or uint8, nonzero on the known cells: a mask, or a map's codes
    (``_grid._from_code``: 0 unknown). ``prob``: the probabilities, (H, W) float64, or with codes
    a float64 table of each code's, or None. With codes no mask and no float64 map is made: the
    mapping loop's front-end targets and scans prepared (both levels) in 0.96-0.98 of the time
    against their coarse levels' float64 probabilities and unknown masks, the same bits
    (``bench/ab_front_end.py --captured``, edmonton, seattle, aces, 2026-12-07).

    ``walls``: (rows, cols, weights). ``squared``: the walls all weigh 1, and their squared
    distances within ``reach`` (``envelope_reach``) are kept as ``_distance.near_squared_distance``
    gives them (returned, for the verdict) and read through ``envelope_profile(reach, ratio)``
    (beyond the reach the envelope is below 2**-25 and changes nothing in float32): the same grid
    bit for bit as from the exact transform and the blur; with codes their walls at 1 go by the
    grey stamps instead, which give the same grid (the profile never increases), and no squared
    distances are returned (one kernel variant fewer for a process to load, 0.1-0.16 s from
    Taichi's offline cache: the mapping loop's coarse levels meet this 0-20 times a run). Else the
    walls are grey, each stamping weight * profile (the largest wins): ``conflict_grid`` of max(p,
    envelope) bit for bit, without that grid. ``prob`` None (only with ``squared``): every known
    cell is 0 or 1 (a trinary map) and hi is the envelope alone (1 on the walls).

    NumPy fills the grid with the value of an unknown cell that no wall reaches (-2; -4 on the ring
    off the map); then one Taichi launch works a row per work item over the runs of walls near it
    (``_distance.wall_runs``): each run lowers the squared distances (walls at 1; the least wins,
    no branch) or raises the envelope (grey walls, in a float64 scratch row: the largest wins) of
    the cells it reaches, then the row's values are written from those over its known span (first
    known cell to last) and every cell a run reached. Laser submaps know 3-16 % of their cells
    (median, edmonton and seattle), and the spans hold a third of the cells or less: against the
    kernel that wrote every cell and each stamp's value as it went (b2d6744), the loop's front-end
    targets prepared in 0.91-0.93 of the time, its scans in 0.94-0.96, the same bits
    (``bench/ab_front_end.py --captured``, edmonton, seattle, aces). Grey walls wrote each stamp's
    value as it went, min(value, 1 - max(p, e)), until 2026-12-07: the envelope's maximum first
    and each value once, from a table of the profile by row and column offset (contiguous
    reads), is the same (both are monotone in e), and took 0.70-0.75 of the launch's time on
    edmonton's coarse levels. NumPy writing every cell's value before the launch (its own
    arithmetic, not a fill) was slower in the loop than the kernel writing them.
    """
    coded = prob is not None and np.ndim(prob) == 1             # a table of the codes' probabilities
    if prob is None and not squared:
        raise ValueError("grey walls need the map's probabilities")
    squared = squared and not coded
    h, w = known.shape
    out = np.full((h + 2 * PAD, w + 2 * PAD), np.float32(-2.0))  # unknown where no wall reaches
    out[:PAD], out[h + PAD:] = _OFF_MAP, _OFF_MAP                 # the ring off the map
    out[PAD:h + PAD, :PAD], out[PAD:h + PAD, w + PAD:] = _OFF_MAP, _OFF_MAP
    profile, costs, table, monotone = _stamp_tables(int(reach), float(ratio))
    rows, cols, weights = walls
    rows, starts, ends, weights, first, half = wall_runs(rows, cols, None if squared else weights, (h, w), reach,
                                                         squared or monotone)
    p = np.zeros(1) if prob is None else np.ascontiguousarray(prob, dtype=np.float64).reshape(-1)
    known = np.ascontiguousarray(known).view(np.uint8).reshape(-1)
    runs = (rows, starts, ends, weights, first, half, row_spread(h), known, p)
    if not squared:
        if h and w:
            with kernel_lock():
                envelope = _SCRATCH.get("envelope", (h * w,), np.float64)
                launch(kernels(_build_conflict)[1], (*runs, table, envelope, out.reshape(-1), _CODED[coded]))
        return out, None
    dtype = next(t for t in (np.uint8, np.uint16, np.uint32) if reach * reach < np.iinfo(t).max)
    distances = np.empty((h, w), dtype=dtype)
    distances.fill(np.iinfo(dtype).max)
    if h and w:
        with kernel_lock():
            launch(kernels(_build_conflict)[0], (*runs, profile, costs, distances.reshape(-1), out.reshape(-1)),
                   (prob is not None, _taichi_type(dtype)))
    return out, distances


@functools.lru_cache(maxsize=32)
def _stamp_tables(reach: int, ratio: float):
    """``near_conflict_grid``'s tables for a reach and ratio, made once (read-only): the profile by
    squared distance (``envelope_profile``); the costs by squared distance, of a known and of an
    unknown cell (float32, 1 - hi rounded once from float64); the profile by row and column offset
    (grey walls); and whether the profile never increases."""
    profile = envelope_profile(reach, ratio)
    costs = np.empty((2, len(profile)), dtype=np.float32)
    costs[0] = 1.0 - profile
    np.subtract(np.float32(-1.0), costs[0], out=costs[1])
    offsets = np.arange(reach + 1)
    table = profile[np.minimum(offsets[:, None] ** 2 + offsets ** 2, reach * reach + 1)]
    for array in (profile, costs, table):
        array.setflags(write=False)
    return profile, costs, table, bool(np.all(np.diff(profile) <= 0))


# ``weighted``'s flag, an array read at run time: ``prob`` is a table of the codes' probabilities
_CODED = {False: np.zeros(1, dtype=np.int32), True: np.ones(1, dtype=np.int32)}


def _build_conflict(ti):
    i32 = ti.types.ndarray(dtype=ti.i32, ndim=1)
    f64 = ti.types.ndarray(dtype=ti.f64, ndim=1)

    # Both kernels: a row of the map per work item (the rows spread out: ``_launch.row_spread``),
    # which stamps the runs of walls within reach rows of it (sorted by row, ``first[r]`` the first
    # on row r or later), each reaching ``half[d + reach]`` cells beyond either end on row d away;
    # the row belongs to its work item, so no atomics, and the extrema do not depend on the order.
    # The grids come flat (a loop over 1-D indices ran several times faster than one over 2-D ones
    # here, and each array argument costs a launch a few microseconds): the map's h x w cells
    # (h + 1 entries in ``first``), the conflict grid's (h + 2 PAD) x (w + 2 PAD)

    @ti.func
    def span(known: ti.template(), cell, w, i, h, reach, first: ti.template(), rows_: ti.template(),
             starts: ti.template(), ends: ti.template(), half: ti.template()):
        # the cells of the row to write: from its first known cell to its last, and every cell a
        # run reaches
        lo, hi = 0, w
        while lo < w and known[cell + lo] == 0:
            lo += 1
        while hi > lo and known[cell + hi - 1] == 0:
            hi -= 1
        if lo == hi:
            lo, hi = w, 0
        for k in range(first[ti.max(i - reach, 0)], first[ti.min(i + reach + 1, h)]):
            chord = half[rows_[k] - i + reach]
            lo, hi = ti.min(lo, ti.max(starts[k] - chord, 0)), ti.max(hi, ti.min(ends[k] + chord + 1, w))
        return lo, hi

    @ti.func
    def p_at(prob: ti.template(), known: ti.template(), c, coded):
        # the probability of cell c: its own, or its code's (``known`` then holds the codes)
        p = ti.f64(0.0)
        if coded:
            p = prob[ti.cast(known[c], ti.i32)]
        else:
            p = prob[c]
        return p

    @ti.kernel
    def nearest(rows_: i32, starts: i32, ends: i32, weights: f64, first: i32, half: i32, spread: i32,
                known: ti.types.ndarray(dtype=ti.u8, ndim=1), prob: f64, profile: f64,
                costs: ti.types.ndarray(dtype=ti.f32, ndim=2), squared: ti.types.ndarray(ndim=1),
                out: ti.types.ndarray(dtype=ti.f32, ndim=1), grey: ti.template(), dt: ti.template()):
        # walls at 1: the squared distances first (the least per cell, no branch), then the values
        # from them (``grey``: a probability map, hi = max(p, envelope); never a codes' table)
        h = first.shape[0] - 1
        w = known.shape[0] // h
        width = w + 2 * PAD
        reach = (half.shape[0] - 1) // 2
        last = profile.shape[0] - 1                      # beyond reach: the profile's 0
        for i, part in ti.ndrange(h, spread.shape[0]):
            if part == 0:
                cell, row = i * w, (i + PAD) * width + PAD
                lo, hi = span(known, cell, w, i, h, reach, first, rows_, starts, ends, half)
                for k in range(first[ti.max(i - reach, 0)], first[ti.min(i + reach + 1, h)]):
                    di = rows_[k] - i
                    dy2 = di * di
                    chord = half[di + reach]
                    a, b = starts[k], ends[k]
                    for j in range(ti.max(a - chord, 0), ti.min(b + chord + 1, w)):
                        dx = ti.max(ti.max(a - j, j - b), 0)
                        squared[cell + j] = ti.cast(ti.min(ti.cast(squared[cell + j], ti.i32), dy2 + dx * dx), dt)
                for j in range(lo, hi):
                    q = ti.min(ti.cast(squared[cell + j], ti.i32), last)
                    c = costs[0, q]
                    if ti.static(grey):
                        c = ti.cast(1.0 - ti.max(prob[cell + j], profile[q]), ti.f32)
                    out[row + j] = ti.select(known[cell + j] != 0, c, costs[1, q])

    @ti.kernel
    def weighted(rows_: i32, starts: i32, ends: i32, weights: f64, first: i32, half: i32, spread: i32,
                 known: ti.types.ndarray(dtype=ti.u8, ndim=1), prob: f64,
                 table: ti.types.ndarray(dtype=ti.f64, ndim=2), envelope: f64,
                 out: ti.types.ndarray(dtype=ti.f32, ndim=1), mode: i32):
        # grey walls: the envelope's maximum per cell (weight * ``table[row offset, column
        # offset]``, the profile at that squared distance), then the values from it. Whether
        # ``prob`` is the codes' table (``mode[0]``) is read at run time, not a template argument:
        # one variant for Taichi to load in a process (0.1-0.15 s from its offline cache), and the
        # front end's preparations took the same time (ratios 0.99-1.02, ``bench/ab_front_end.py
        # --captured``, 2026-12-07)
        h = first.shape[0] - 1
        w = known.shape[0] // h
        width = w + 2 * PAD
        reach = (half.shape[0] - 1) // 2
        coded = mode[0] != 0
        for i, part in ti.ndrange(h, spread.shape[0]):
            if part == 0:
                cell, row = i * w, (i + PAD) * width + PAD
                lo, hi = span(known, cell, w, i, h, reach, first, rows_, starts, ends, half)
                for j in range(lo, hi):
                    envelope[cell + j] = 0.0
                for k in range(first[ti.max(i - reach, 0)], first[ti.min(i + reach + 1, h)]):
                    di = rows_[k] - i
                    chord = half[di + reach]
                    a, b, weight = starts[k], ends[k], weights[k]
                    t = ti.abs(di)
                    for j in range(ti.max(a - chord, 0), a):
                        envelope[cell + j] = ti.max(envelope[cell + j], weight * table[t, a - j])
                    along = weight * table[t, 0]
                    for j in range(a, b + 1):
                        envelope[cell + j] = ti.max(envelope[cell + j], along)
                    for j in range(b + 1, ti.min(b + chord + 1, w)):
                        envelope[cell + j] = ti.max(envelope[cell + j], weight * table[t, j - b])
                for j in range(lo, hi):
                    e = envelope[cell + j]
                    value = ti.cast(1.0 - ti.max(p_at(prob, known, cell + j, coded), e), ti.f32)
                    out[row + j] = ti.select(known[cell + j] != 0, value, ti.f32(-1.0) - ti.cast(1.0 - e, ti.f32))

    return nearest, weighted


def wall_points(grid: GridMap, occupied: float = WALL):
    """(rows, cols, weights): the cells of ``grid`` with p >= ``occupied``, weighted by p."""
    p = grid.prob
    rows, cols = cells(p >= occupied)           # False on unknown (NaN) cells
    return rows, cols, p[rows, cols]


def points_array(rows, cols, weights, unknown_cost):
    """The walls as the kernel reads them: (4, M) float32 columns (row, col, w, w * unknown_cost)."""
    w = np.asarray(weights, dtype=np.float64)
    return np.ascontiguousarray(np.vstack([rows, cols, w, w * unknown_cost]), dtype=np.float32)


def _build(ti):
    f32_2d = ti.types.ndarray(dtype=ti.f32, ndim=2)
    f64_2d = ti.types.ndarray(dtype=ti.f64, ndim=2)

    @ti.func
    def wall_cost(grid: ti.template(), points: ti.template(), m, iv, iu, edge):
        v = grid[iv, iu]
        # unknown: w * min(unknown_cost, 1 - hi) (v = -1 - (1 - hi)); off the map (v = -4): ``edge``
        # (0 or 1) times w * unknown_cost: nothing, or as on an unknown cell no wall reaches
        near = ti.min(points[3, m], points[2, m] * (-1.0 - v))
        off = points[3, m] * edge
        return ti.select(v >= 0.0, points[2, m] * v, ti.select(v > -3.0, near, off))

    @ti.func
    def coefficients(matrix: ti.template(), f0, f1, f2, f3):
        # eq. (5)'s affine map of a pose, (f0, f1, f2, f3, 1) @ matrix (``_cost.AffineMap``); a pose
        # that puts the map millions of cells away goes to the unknown ring (u = v = 0): coordinates
        # are converted to int32, and every such point is off the map either way
        a = ti.Vector([0.0] * 6, dt=ti.f64)
        for q in ti.static(range(6)):
            a[q] = f0 * matrix[0, q] + f1 * matrix[1, q] + f2 * matrix[2, q] + f3 * matrix[3, q] + matrix[4, q]
        if ti.abs(a[2]) >= 1e7 or ti.abs(a[5]) >= 1e7:
            a = ti.Vector([0.0] * 6, dt=ti.f64)
        return a

    @ti.func
    def chunk_sum(grid: ti.template(), points: ti.template(), affine, c, bilinear: ti.template(), edge):
        u_max = grid.shape[1] - 1
        v_max = grid.shape[0] - 1
        c0, c1, c2 = ti.f32(affine[0]), ti.f32(affine[1]), ti.f32(affine[2])
        c3, c4, c5 = ti.f32(affine[3]), ti.f32(affine[4]), ti.f32(affine[5])
        acc = ti.f32(0.0)
        cnt = 0
        for m in range(c * CHUNK, ti.min((c + 1) * CHUNK, points.shape[1])):
            i = points[0, m]
            j = points[1, m]
            u = c0 * j + c1 * i + c2
            v = c3 * j + c4 * i + c5
            iu = ti.min(ti.max(ti.cast(u, ti.i32), 0), u_max)
            iv = ti.min(ti.max(ti.cast(v, ti.i32), 0), v_max)
            cnt += ti.select(grid[iv, iu] >= 0.0, 1, 0)
            if ti.static(bilinear):
                # the cost interpolated between the four nearest cell centres
                uf = ti.min(ti.max(u - 0.5, 0.0), ti.f32(u_max - 1))
                vf = ti.min(ti.max(v - 0.5, 0.0), ti.f32(v_max - 1))
                u0 = ti.cast(ti.floor(uf), ti.i32)
                v0 = ti.cast(ti.floor(vf), ti.i32)
                fu = uf - ti.cast(u0, ti.f32)
                fv = vf - ti.cast(v0, ti.f32)
                top = ((1.0 - fu) * wall_cost(grid, points, m, v0, u0, edge)
                       + fu * wall_cost(grid, points, m, v0, u0 + 1, edge))
                low = ((1.0 - fu) * wall_cost(grid, points, m, v0 + 1, u0, edge)
                       + fu * wall_cost(grid, points, m, v0 + 1, u0 + 1, edge))
                acc += (1.0 - fv) * top + fv * low
            else:
                acc += wall_cost(grid, points, m, iv, iu, edge)
        return acc, cnt

    @ti.kernel
    def envelope_chunks(grid_a: f32_2d, points_b: f32_2d, matrix_b2a: f64_2d,
                        grid_b: f32_2d, points_a: f32_2d, matrix_a2b: f64_2d, poses: f64_2d,
                        edge_unknown: ti.types.ndarray(dtype=ti.f32, ndim=1),
                        out: ti.types.ndarray(dtype=ti.f32, ndim=3), serial: ti.template(), bilinear: ti.template()):
        # ``edge_unknown[0]``, 0 or 1, read at run time rather than a template argument: one variant
        # fewer for Taichi to load in a process (0.15-0.2 s from its offline cache), the same bits
        edge = edge_unknown[0]
        chunks_b = (points_b.shape[1] + CHUNK - 1) // CHUNK
        chunks_a = (points_a.shape[1] + CHUNK - 1) // CHUNK
        ti.loop_config(serialize=serial)
        for k, c in ti.ndrange(poses.shape[0], chunks_b + chunks_a):
            acc = ti.f32(0.0)
            cnt = 0
            x, y = poses[k, 0], poses[k, 1]
            cs, sn = ti.cos(poses[k, 2]), ti.sin(poses[k, 2])
            # B's walls in A through r, A's through r^-1 = (-R^T t, -theta)
            if c < chunks_b:
                acc, cnt = chunk_sum(grid_a, points_b, coefficients(matrix_b2a, cs, sn, x, y), c, bilinear, edge)
            else:
                acc, cnt = chunk_sum(grid_b, points_a, coefficients(matrix_a2b, cs, -sn, -(cs * x + sn * y),
                                                                    sn * x - cs * y), c - chunks_b, bilinear, edge)
            out[0, k, c] = acc
            out[1, k, c] = ti.f32(cnt)          # exact: a chunk has far fewer than 2**24 points

    return envelope_chunks


def _kernel():
    return kernels(_build)


class EnvelopeEngine:
    """The envelope discrepancy of B in A for batches of poses r_A2B, one launch per batch.

    ``a`` and ``b`` are ``PreparedMap`` objects of the "envelope" kind (their ``lower`` is the map,
    their ``blurred`` the envelope hi). ``bilinear``: each wall's cost interpolated between the four
    cell centres around where it lands; ``edge_unknown``: a wall off the other map's grid pays
    ``unknown_cost`` (else nothing; see the module docstring).
    """

    def __init__(self, a, b, unknown_cost=0.0, bilinear=False, edge_unknown=False):
        self._bilinear = bool(bilinear)
        self._edge = bool(edge_unknown)
        self._grid_a, self._grid_b = a.conflict, b.conflict
        self._points_b = b.wall_array(unknown_cost)
        self._points_a = a.wall_array(unknown_cost)
        self._b2a = AffineMap(a.frame, b.frame, PAD)
        self._a2b = AffineMap(b.frame, a.frame, PAD)
        self._launcher = Launcher(_kernel, (self._grid_a, self._points_b, self._b2a.matrix, self._grid_b,
                                            self._points_a, self._a2b.matrix, None, _EDGE[self._edge]))

    def __call__(self, poses, count="all"):
        """(e (N,), overlap (N,) int64): the overlap is counted in the same launch; with ``count``
        "none" it is not added up and None is returned in its place; with "b_walls" it is B's
        walls alone that land on known cells of A."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        n = len(poses)
        chunks = -(-self._points_b.shape[1] // CHUNK) + -(-self._points_a.shape[1] // CHUNK)
        if chunks == 0:
            return np.zeros(n), np.zeros(n, dtype=np.int64)
        serial = n * (self._points_b.shape[1] + self._points_a.shape[1]) < SERIAL_BELOW
        out = self._launcher.run((poses,), (2, n, chunks), (serial, self._bilinear))
        values = out[0].sum(axis=1, dtype=np.float64)
        if count == "none":
            return values, None
        counted = out[1, :, :-(-self._points_b.shape[1] // CHUNK)] if count == "b_walls" else out[1]
        return values, counted.sum(axis=1, dtype=np.float64).astype(np.int64)


class NumpyEnvelope:
    """The envelope discrepancy in plain NumPy from the maps alone (the oracle): each map's
    envelope written wall by wall, every wall looked up in the other map's cell, or with
    ``bilinear`` its cost interpolated between the four cell centres around it."""

    def __init__(self, a: GridMap, b: GridMap, width_a: float, width_b: float, unknown_cost=0.0,
                 bilinear: bool = False, edge_unknown: bool = False):
        self._sides = []
        for src, dst, width, forward in ((b, a, width_a, True), (a, b, width_b, False)):
            rows, cols, w = wall_points(src)
            self._sides.append((src.cell_centres(rows, cols), w, dst, _envelope_everywhere(dst, width), forward))
        self._unknown_cost = unknown_cost
        self._off = unknown_cost if edge_unknown else 0.0
        self._bilinear = bilinear

    def _cost(self, dst, hi_dst, rows, cols):
        """Each wall's cost at the cells (``rows``, ``cols``) of ``dst``: 1 - hi on a known cell,
        min(unknown_cost, 1 - hi) on an unknown one, 0 off the grid (``edge_unknown``: unknown_cost)."""
        inside = (rows >= 0) & (rows < dst.shape[0]) & (cols >= 0) & (cols < dst.shape[1])
        r, c = np.where(inside, rows, 0).astype(np.intp), np.where(inside, cols, 0).astype(np.intp)
        hi = hi_dst[r, c]
        known = ~np.isnan(dst.prob[r, c])
        return np.where(inside, np.where(known, 1.0 - hi, np.minimum(self._unknown_cost, 1.0 - hi)), self._off)

    def __call__(self, poses, count="all"):
        """(e (N,), overlap (N,) int64), whatever ``count`` says."""
        poses = as_poses(poses)
        values = np.zeros(len(poses))
        counts = np.zeros(len(poses), dtype=np.int64)
        for k, pose in enumerate(poses):
            for centres, w, dst, hi_dst, forward in self._sides:
                points = transform_points(pose if forward else inverse(pose), centres)
                rows, cols = dst.cell_of(points)
                inside = (rows >= 0) & (rows < dst.shape[0]) & (cols >= 0) & (cols < dst.shape[1])
                known = ~np.isnan(dst.prob[rows[inside].astype(np.intp), cols[inside].astype(np.intp)])
                counts[k] += int(known.sum())
                if not self._bilinear:
                    values[k] += np.sum(w * self._cost(dst, hi_dst, rows, cols))
                    continue
                # the four cell centres around each wall, and its place between them
                v, u = dst.grid_coordinates(points)
                u0, v0 = np.floor(u - 0.5), np.floor(v - 0.5)
                fu, fv = u - 0.5 - u0, v - 0.5 - v0
                for dv, dr in ((1.0 - fv, 0), (fv, 1)):
                    for du, dc in ((1.0 - fu, 0), (fu, 1)):
                        values[k] += np.sum(w * dv * du * self._cost(dst, hi_dst, v0 + dr, u0 + dc))
        return values, counts


def _envelope_everywhere(grid: GridMap, width: float) -> np.ndarray:
    """hi on every cell, unknown ones too: max(p, max_o p(o) exp(-d^2 / 2 width^2)) over the cells o
    with p >= 0.5, each wall's Gaussian written into the square around it out to 8 widths (beyond,
    below 1e-13); p of an unknown cell counts 0."""
    p = np.nan_to_num(grid.prob, nan=0.0)
    hi = p.copy()
    if width == 0.0:
        return hi
    reach = int(np.ceil(8.0 * width / grid.resolution))
    offsets = np.arange(-reach, reach + 1)
    gauss = np.exp(-0.5 * ((offsets[:, None] ** 2 + offsets[None, :] ** 2) * (grid.resolution / width) ** 2))
    h, w = p.shape
    for r, c in zip(*np.nonzero(p >= 0.5)):
        r0, r1, c0, c1 = max(r - reach, 0), min(r + reach + 1, h), max(c - reach, 0), min(c + reach + 1, w)
        window = p[r, c] * gauss[r0 - r + reach:r1 - r + reach, c0 - c + reach:c1 - c + reach]
        np.maximum(hi[r0:r1, c0:c1], window, out=hi[r0:r1, c0:c1])
    return hi
