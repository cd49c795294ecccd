"""The search without a guess: the best pose of a lattice, by branch and bound (issue 13).

The local matcher needs a guess within its basin (a few cells, a few degrees). This module finds
one: it scores every pose of a lattice, over all relative poses where the maps can overlap or
within a window around a guess, and returns the best ones. It is complete at the lattice's
resolution (the result is the brute-force maximum over the same lattice, ``tests/test_search.py``)
and prunes with admissible bounds over max-pooled copies of A, as Cartographer's branch and bound
does (Hess et al., ICRA 2016, sec. V).

**The score** (maximised). On the trinary maps (``_grid.trinary``):

    S(r) = sum_{b wall of B} v_A(T(r) b)  -  #{f clear free cell of B : T(r) f on a wall of A}

- ``v_A = 2 hi_A - 1`` on A's known cells, where ``hi_A = exp(-d^2 / 2 sigma^2)`` is the envelope
  of A's walls (d: distance to the nearest, sigma: the blur width, as in ``_envelope``): a wall of
  B on a wall of A scores 1, on A's free space far from walls -1 (occupied over free: a conflict).
- ``v_A = hi_A`` on A's unknown cells (a wall seen behind a wall still counts as near it), 0 off
  A's grid.
- A wall of A under B's free space is the other conflict (negative information both ways). Free
  cells of B within ``CLEAR_CELLS`` of B's walls are left out: there a beam grazing a wall decides
  and a one-cell offset at the truth would pay.

The prior of eq. (8) is absent. Pushing B off A or onto A's unknown cells scores nothing, so a
real overlap, whose walls meet walls, always scores more than no overlap: unlike e, the score does
not reward pushing the maps apart. Its sums visit points of B only, so a bound needs A's values
alone.

**The lattice.** B turns about its walls' centroid c by angles ``theta_k`` in steps of
``rotation_step`` (Cartographer's: the farthest point of B from c moves by one cell of A); c lands
on the corners of A's cells. A point p of B then lands in cell ``t + q_k(p)`` of A, where t is
c's cell and ``q_k(p) = floor(G R(theta_k) (p - c))`` (G: A's frame to grid coordinates), computed
once per angle in float64 NumPy: the lattice's definition, shared by the kernel and the tests.

**The bounds.** A node is ``_Tree.angles[L]`` consecutive angles and a square of 2^L x 2^L
translations. Each wall of B lies, at the node's angles, within ``_Tree.spread[L]`` cells of where
it lies at the middle one, so its value over the node is at most the maximum of v_A over a square
of 2^L + 2 spread cells (``window_max``: Cartographer's precomputed grids, widened for the angles);
the free cells' terms are <= 0 and are dropped. So a node's bound is one lookup per wall, the work
of one pose. Best-first in batches: the ``BATCH`` nodes of highest bound are split into their
children, all evaluated in one launch (leaves with the full score), and nodes whose bound cannot
beat the threshold are dropped. The threshold is the ``HYPOTHESES``-th best distinct leaf found so
far, or ``RUNNER_UP_FRACTION`` of the best when higher: the best pose is exact, and the runner-ups
are exact above that fraction of its score. When the budget of nodes runs out first, the search
still counts as complete if every node left bounds below ``COMPLETE_FRACTION`` of the best: the
best is then exact and the runner-ups are exact above the highest bound left (``SearchResult.proven``).
"""

import dataclasses
import math
import threading
import weakref

import numpy as np

from ._distance import wall_distance
from ._errors import InvalidMapError, InvalidOptionError, shown
from ._grid import GridMap, cells, trinary
from ._launch import launch
from ._pyramid import coarsen
from ._se2 import wrap_angle
from ._taichi import kernel_lock, kernels

__all__ = ["SearchOptions", "Hypothesis", "SearchResult", "search", "lattice_cells", "score_values", "window_max"]

CLEAR_CELLS = 2.0          # free cells of B nearer its walls than this (cells) are not scored
HYPOTHESES = 3             # distinct hypotheses kept (the best and its runner-ups)
# Runner-ups are proven down to this fraction of the best's score: where the matcher calls a match
# ambiguous (``_matcher``). Over every laser-submap pair of bench/global.py (623, 2026-12-03), the
# accepted matches were 98.3 % correct at 0.9 (9 wrong of 531, four of them aliases 5-23 m away
# whose true pose scored 0.44-0.86 of the best), 99.2 % at 0.8 (4 of 504), 99.8 % at 0.75 (1 of
# 488, 0.14 m off); the crops of two seeds 399 of 399 at 0.9. Proving more runner-ups takes
# longer (intel's cross-run pair: 1.2 M -> 2.0 M nodes), bounded by ``max_nodes`` and
# ``COMPLETE_FRACTION``.
RUNNER_UP_FRACTION = 0.75
# ... and at least down to this one, or the search is not complete (``SearchResult.complete``):
# where the budget of nodes runs out, the proof may stop between the two (intel's cross-run pair
# needed 1.2 M nodes down to 0.9, 2.2 M down to 0.8).
COMPLETE_FRACTION = 0.9
BATCH = 2048               # nodes split per launch (512: 1.35x the time on laser submaps, 8192: 1.05x)
MAX_LEVEL = 7              # the coarsest node: 128 x 128 translations
SMALL_LATTICE = 4096       # lattices of at most this many poses are scored whole (no tree)
DEFAULT_RESOLUTION = 0.2   # metres


@dataclasses.dataclass(frozen=True)
class SearchOptions:
    """Settings of a search. Units: metres, radians.

    window : (metres, radians) around the guess: every angle within that many radians of the
        guess's, each with every translation within that many metres of the guess's along x and y
        (as far as B can touch A); None searches every pose where the maps overlap.
    blur : sigma of A's envelope in the score, metres; None: 0.1 m or one cell of A as searched
        if wider (0.2 m at the default resolution).
    separation : (metres, radians): lattice poses closer than this in both (c's position, angle)
        are the same hypothesis.
    rotation_step : the lattice's angle step; None: the farthest point of B moves one cell of A.
    max_nodes : a budget of nodes scored (bounds and leaves; about 0.5 M a second on laser
        submaps): past it the search stops with the best found so far and says it is not
        complete (``SearchResult.complete``). Unambiguous pairs take 10^4-10^5; an ambiguous pair of
        laser submaps took 25 M (56 s) without a budget.
    resolution : the cell side the search runs at, metres: both maps are coarsened by a power of
        two to about it (walls kept: a coarse cell holding a wall is one, ``_pyramid.coarsen``
        "max"); None: ``DEFAULT_RESOLUTION`` or the maps' own if coarser. The lattice, and with
        it the search's work, shrinks with its cube (translations squared, angles); the local
        matcher then refines the best pose on the given maps.
    """

    window: tuple = None
    blur: float = None
    separation: tuple = (0.5, math.radians(10.0))
    rotation_step: float = None
    resolution: float = None
    max_nodes: int = 2_000_000


@dataclasses.dataclass(frozen=True)
class Hypothesis:
    """A lattice pose r_A2B = (x, y, theta) and its score S (higher is better)."""

    pose: np.ndarray
    score: float


@dataclasses.dataclass(frozen=True)
class SearchResult:
    """The distinct hypotheses, best first (none when no pose of the window puts B on A), and what
    the search did."""

    hypotheses: list
    nodes: int              # lattice nodes scored (bounds and leaves)
    lattice_size: int       # poses in the lattice (what brute force would score)
    rotation_step: float    # the lattice's angle step, radians
    resolution: float       # the cell side it searched at, metres (its translation step)
    complete: bool = True   # False: stopped at ``max_nodes``; the best is the best found, not proven
    # runner-ups are exact at and above this fraction of the best's score: RUNNER_UP_FRACTION, or
    # up to COMPLETE_FRACTION where the budget ran out; 1.0 when not complete (none proven)
    proven: float = RUNNER_UP_FRACTION


def score_values(a: GridMap, blur: float):
    """(v, w): the score's values on A's cells, float32: v for B's walls (2 hi - 1 on known cells,
    hi on unknown ones), w for B's clear free cells (-1 on A's walls, else 0)."""
    p = a.prob
    known = ~np.isnan(p)
    walls = p >= 0.5                       # False on unknown (NaN) cells
    if walls.any():
        d = wall_distance(walls) * a.resolution
        hi = np.exp(-0.5 * (d / blur) ** 2)
    else:
        hi = np.zeros(p.shape)
    v = np.where(known, 2.0 * hi - 1.0, hi).astype(np.float32)
    return v, np.where(walls, np.float32(-1.0), np.float32(0.0))


def window_max(canvas: np.ndarray, sizes) -> list:
    """For each size w: the grid whose cell x holds the maximum of ``canvas`` over the w x w square
    of cells starting at x (0 beyond the canvas): from the maxima over 2^k squares (k = floor
    log2 w) at x and x + w - 2^k on each axis, as a sparse table does."""
    tables = [canvas]
    while 2 ** len(tables) <= max(sizes):
        prev, half = tables[-1], 2 ** (len(tables) - 1)
        cur = prev.copy()
        np.maximum(cur[:-half], prev[half:], out=cur[:-half])
        np.maximum(cur[:, :-half], cur[:, half:].copy(), out=cur[:, :-half])
        tables.append(cur)
    out = []
    for w in sizes:
        k = int(math.floor(math.log2(w)))
        table, d = tables[k], w - 2**k
        g = table.copy()
        if d:
            np.maximum(g[:-d], table[d:], out=g[:-d])
            np.maximum(g[:, :-d], g[:, d:].copy(), out=g[:, :-d])
        out.append(g)
    return out


def _points(b: GridMap):
    """B's walls and clear free cells, (x, y) in B's frame (metres)."""
    p = b.prob
    walls = p >= 0.5
    free = p < 0.5                          # False on unknown cells
    free &= ~_near(walls)
    return b.cell_centres(*cells(walls)), b.cell_centres(*cells(free))


def _near(walls: np.ndarray) -> np.ndarray:
    """The cells nearer a True cell of ``walls`` than ``CLEAR_CELLS`` (centre to centre): the OR of
    ``walls`` shifted by every offset that short (at 2 cells, the 3 x 3 square), which is what a
    distance transform's ``< CLEAR_CELLS`` gives. On a front-end target of 288 x 495 cells SciPy's
    transform took 7 ms and this 0.1, and SciPy's first call 0.24 s more to import
    ``scipy.ndimage``: the mapping loop's jump checks paid both. (Not ``_distance``'s stamps: a
    kernel variant the loop does not otherwise load.)"""
    reach = int(math.ceil(CLEAR_CELLS)) - 1
    padded = np.pad(walls, reach)
    h, w = walls.shape
    out = np.zeros_like(walls)
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            if dr * dr + dc * dc < CLEAR_CELLS * CLEAR_CELLS:
                out |= padded[reach + dr:reach + dr + h, reach + dc:reach + dc + w]
    return out


_GRIDS = weakref.WeakKeyDictionary()      # GridMap -> {resolution: its trinary map as searched}
_GRIDS_LOCK = threading.Lock()


def _searched_grid(grid: GridMap, resolution: float) -> GridMap:
    """``trinary(grid)`` coarsened by the power of two that brings its cells nearest
    ``resolution`` (never finer than given), a coarse cell a wall when it holds one; kept for as
    long as ``grid`` lives (a mapping loop searches each submap against many)."""
    with _GRIDS_LOCK:
        known = _GRIDS.get(grid, {}).get(resolution)
    if known is not None:
        return known
    factor = 2 ** max(int(round(math.log2(resolution / grid.resolution))), 0)
    searched = trinary(grid)
    if factor > 1:
        searched = coarsen(searched, factor, reduce="max")
    with _GRIDS_LOCK:
        _GRIDS.setdefault(grid, {})[resolution] = searched
    return searched


def lattice_cells(a: GridMap, points: np.ndarray, centre: np.ndarray, theta: float) -> np.ndarray:
    """q(p) = floor(G R(theta) (p - centre)): (N, 2) int32 (row, col) offsets of the cells of A
    that points p of B land in, relative to the cell whose corner the centre lands on."""
    c, s = math.cos(theta), math.sin(theta)
    d = points - centre
    x, y = c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]      # turned, in A's frame
    ca, sa = math.cos(a.yaw), math.sin(a.yaw)
    rows, cols = (-sa * x + ca * y) / a.resolution, (ca * x + sa * y) / a.resolution
    return np.stack([np.floor(rows), np.floor(cols)], axis=1).astype(np.int32)


class _Lattice:
    """The lattice's angles, c's cell range and the poses of its nodes."""

    def __init__(self, a, centre, radius, opts, guess):
        res = a.resolution
        step = opts.rotation_step
        if step is None:          # the farthest point moves by one cell: chord res at radius
            step = math.acos(max(1.0 - res * res / (2.0 * radius * radius), -1.0)) if radius > res else math.pi / 2
        self.centre, self.radius = centre, radius
        self._a = a
        # c's cells from which B can touch A's known cells: beyond them every pose scores 0
        rows, cols = np.flatnonzero(a.known.any(axis=1)), np.flatnonzero(a.known.any(axis=0))
        reach = int(math.ceil(radius / res)) + 1
        self.lo = np.array([rows[0], cols[0]]) - reach
        self.hi = np.array([rows[-1], cols[-1]]) + reach + 1            # exclusive
        if opts.window is None:
            n = max(int(math.ceil(2.0 * math.pi / step)), 1)
            self.step = 2.0 * math.pi / n
            self.thetas = np.arange(n) * self.step
        else:
            metres, radians = (float(v) for v in opts.window)
            n = int(math.ceil(radians / step))
            self.step = step
            self.thetas = guess[2] + np.arange(-n, n + 1) * step
            # the poses within ``metres`` of the guess's translation at every angle of the window:
            # c lands within that distance of guess + R(theta) c, an arc when c is far from B's origin
            landing = guess[:2] + np.stack([_rotate(t, centre) for t in self.thetas])
            rows_, cols_ = a.grid_coordinates(landing)
            span = int(math.ceil(metres / res))
            lo = np.array([math.floor(rows_.min()) - span, math.floor(cols_.min()) - span])
            hi = np.array([math.floor(rows_.max()) + span + 1, math.floor(cols_.max()) + span + 1])
            self.lo, self.hi = np.maximum(self.lo, lo), np.minimum(self.hi, hi)

    @property
    def size(self):
        return len(self.thetas) * int(np.prod(self.hi - self.lo))

    def poses(self, k, rows, cols):
        """r_A2B (N, 3) of the nodes (angle index k, c in the cell whose corner is (rows, cols))."""
        a = self._a
        corner = a.cell_centres(rows, cols) - _rotate(a.yaw, np.array([0.5, 0.5]) * a.resolution)
        theta = self.thetas[k]
        c, s = np.cos(theta), np.sin(theta)
        x = corner[:, 0] - (c * self.centre[0] - s * self.centre[1])
        y = corner[:, 1] - (s * self.centre[0] + c * self.centre[1])
        return np.stack([x, y, np.full(len(x), wrap_angle(theta))], axis=1)


def _rotate(theta, v):
    c, s = math.cos(theta), math.sin(theta)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


class _Scorer:
    """Scores nodes in batches, one launch each (``engine`` "taichi"), or in NumPy ("numpy").

    Every level's grid lies on one canvas of A's cells, wide enough that no lookup leaves it
    sideways, so a point's cell is one flat index: the point's offset at its angle (row * width +
    col, made once per angle) plus the node's base. Lookups before the first row or after the last
    read 0 (off A: every window there is off A).
    """

    def __init__(self, a, walls, free, centre, lattice, tree, blur, engine):
        self.walls, self.free, self.centre = walls, free, centre
        self.a, self.lattice, self.tree, self.engine = a, lattice, tree, engine
        reach = int(math.ceil(lattice.radius / a.resolution)) + 2             # |q| at most, any angle
        sizes = [2**level + 2 * tree.spread[level] for level in range(tree.levels + 1)]
        spread = max(tree.spread)
        h, w = a.shape
        # rows: every window that touches A; columns: every lookup
        self._r0 = -max(sizes)
        self._c0 = min(int(lattice.lo[1]) - reach - spread, -max(sizes))
        rows = h - self._r0
        self.width = max(int(lattice.hi[1]) + reach + 1, w) - self._c0
        if rows * self.width >= 2**31 - 1:
            raise InvalidMapError(f"the search's canvas ({rows} x {self.width} cells) is too large: search at a "
                                  f"coarser resolution or within a window")
        v, free_values = score_values(a, blur)
        canvas = np.zeros((rows + max(sizes), self.width + max(sizes)), dtype=np.float32)
        canvas[-self._r0:-self._r0 + h, -self._c0:-self._c0 + w] = v
        self.grids = [np.ascontiguousarray(g[:rows, :self.width]).ravel() for g in window_max(canvas, sizes)]
        self.free_grid = np.zeros((rows, self.width), dtype=np.float32)
        self.free_grid[-self._r0:-self._r0 + h, -self._c0:-self._c0 + w] = free_values
        self.free_grid = self.free_grid.ravel()
        n = len(lattice.thetas)
        self.wall_offsets = np.zeros((n, max(len(walls), 1)), dtype=np.int32)
        self.free_offsets = np.zeros((n, max(len(free), 1)), dtype=np.int32)
        self._have = np.zeros((2, n), dtype=bool)
        self.scored = 0

    def _offsets(self, ks, leaf):
        """Fill the angles' offsets of the walls (and of the free cells for leaves) when first used."""
        for kind, points, table in ((0, self.walls, self.wall_offsets), (1, self.free, self.free_offsets))[:1 + leaf]:
            for k in np.unique(ks[~self._have[kind, ks]]):
                if len(points):
                    q = lattice_cells(self.a, points, self.centre, self.lattice.thetas[k])
                    table[k, :len(points)] = q[:, 0] * self.width + q[:, 1]
                self._have[kind, k] = True

    def __call__(self, level, nodes):
        """(N,) float64: nodes (N, 3) int32 (first angle, c's row, c's col) of ``level`` scored
        (level 0) or bounded: their middle angle's walls on that level's grid, from ``spread``
        cells before (``_Tree``), and at level 0 the free cells on A's walls."""
        self.scored += len(nodes)
        tree, leaf = self.tree, level == 0
        k = nodes[:, 0] + np.minimum(tree.angles[level], len(self.lattice.thetas) - nodes[:, 0]) // 2
        spread = tree.spread[level]
        base = (nodes[:, 1] - spread - self._r0) * self.width + (nodes[:, 2] - spread - self._c0)
        probes = np.ascontiguousarray(np.stack([k, base], axis=1), dtype=np.int32)
        self._offsets(probes[:, 0], leaf)
        sizes = np.array([len(self.walls), len(self.free) if leaf else 0], dtype=np.int32)
        if self.engine == "numpy":
            return self._numpy(self.grids[level], probes, sizes)
        out = np.empty(len(nodes), dtype=np.float64)
        with kernel_lock():
            launch(kernels(_build), (self.wall_offsets, self.free_offsets, sizes, self.grids[level], self.free_grid,
                                probes, out), None)
        return out

    def _numpy(self, grid, probes, sizes):
        out = np.zeros(len(probes), dtype=np.float64)
        for m, (k, base) in enumerate(probes):
            for offsets, n, values in ((self.wall_offsets, sizes[0], grid),
                                       (self.free_offsets, sizes[1], self.free_grid)):
                idx = offsets[k, :n].astype(np.int64) + base
                idx = idx[(idx >= 0) & (idx < len(values))]
                out[m] += values[idx].astype(np.float64).sum()
        return out




def _build(ti):
    @ti.kernel
    def score(wall_offsets: ti.types.ndarray(dtype=ti.i32, ndim=2),
              free_offsets: ti.types.ndarray(dtype=ti.i32, ndim=2),
              sizes: ti.types.ndarray(dtype=ti.i32, ndim=1), grid: ti.types.ndarray(dtype=ti.f32, ndim=1),
              free: ti.types.ndarray(dtype=ti.f32, ndim=1), probes: ti.types.ndarray(dtype=ti.i32, ndim=2),
              out: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        n_walls, n_free = sizes[0], sizes[1]
        size = ti.cast(grid.shape[0], ti.u32)
        for m in range(probes.shape[0]):                    # a node per work item, its points in order
            k, base = probes[m, 0], probes[m, 1]
            total = ti.f64(0.0)
            for p in range(n_walls):
                i = wall_offsets[k, p] + base
                inside = ti.cast(i, ti.u32) < size
                total += ti.select(inside, ti.cast(grid[ti.select(inside, i, 0)], ti.f64), 0.0)
            for p in range(n_free):
                i = free_offsets[k, p] + base
                inside = ti.cast(i, ti.u32) < size
                total += ti.select(inside, ti.cast(free[ti.select(inside, i, 0)], ti.f64), 0.0)
            out[m] = total

    return score


def search(a: GridMap, b: GridMap, guess=None, options: SearchOptions = None, engine: str = "taichi") -> SearchResult:
    """The best poses r_A2B of B in A over the lattice (see the module's docstring), best first.

    ``guess`` is needed with ``options.window`` and ignored without it. Maps are read as trinary
    (``_grid.trinary``). Raises InvalidMapError when B has no wall or A no known cell.
    """
    opts = options or SearchOptions()
    if opts.window is not None:
        if guess is None:
            raise InvalidOptionError("a search window needs a guess")
        metres, radians = (float(v) for v in opts.window)
        if not (0.0 <= metres <= 1e4 and 0.0 <= radians <= 4.0 * math.pi):
            raise InvalidOptionError(f"window must be (0..1e4 metres, 0..4 pi radians); got {shown(opts.window)}")
        guess = np.asarray(guess, dtype=np.float64)
    if isinstance(opts.max_nodes, bool) or not isinstance(opts.max_nodes, int) or opts.max_nodes < 1:
        raise InvalidOptionError(f"max_nodes must be an integer >= 1; got {shown(opts.max_nodes)}")
    if opts.blur is not None and not (0.0 < opts.blur <= 1e3):
        raise InvalidOptionError(f"blur must be in (0, 1e3] metres or None; got {shown(opts.blur)}")
    if engine not in ("taichi", "numpy"):
        raise InvalidOptionError(f"engine must be 'taichi' or 'numpy'; got {engine!r}")
    if opts.resolution is not None and not (0.0 < opts.resolution <= 1e3):
        raise InvalidOptionError(f"resolution must be in (0, 1e3] metres or None; got {shown(opts.resolution)}")
    target = DEFAULT_RESOLUTION if opts.resolution is None else opts.resolution
    a, b = _searched_grid(a, target), _searched_grid(b, target)
    walls, free = _points(b)
    if len(walls) == 0:
        raise InvalidMapError("B has no occupied cell: nothing to search with")
    if not np.isfinite(a.prob).any():
        raise InvalidMapError("A has no known cell")
    centre = walls.mean(axis=0)
    radius = float(np.sqrt(((np.concatenate([walls, free]) - centre) ** 2).sum(axis=1).max()))
    lattice = _Lattice(a, centre, radius, opts, guess)
    if np.any(lattice.hi <= lattice.lo):         # no pose of the window puts B on A: nothing to find
        return SearchResult([], 0, 0, lattice.step, a.resolution, True)
    span = int((lattice.hi - lattice.lo).max())
    levels = min(MAX_LEVEL, max(int(math.ceil(math.log2(max(span, 1)))) - 2, 0))
    if lattice.size <= SMALL_LATTICE:
        levels = 0
    wall_radius = float(np.sqrt(((walls - centre) ** 2).sum(axis=1).max()))
    tree = _Tree(levels, lattice.step * wall_radius / a.resolution)
    blur = max(0.1, a.resolution) if opts.blur is None else opts.blur
    scorer = _Scorer(a, walls, free, centre, lattice, tree, blur, engine)
    leaves, complete, proven = _branch_and_bound(scorer, lattice, tree, opts)
    hypotheses = [Hypothesis(pose, float(score)) for pose, score in leaves]
    return SearchResult(hypotheses, scorer.scored, lattice.size, lattice.step, a.resolution, complete, proven)


class _Tree:
    """The nodes' shape per level L: 2^L x 2^L translations and ``angles[L]`` consecutive angles.

    A node of several angles is bounded from its middle angle: every wall of B lies within
    ``spread[L]`` cells (per axis) of where it lies at that angle, so the node's cells are those
    of the middle angle's node widened by ``spread[L]`` on each side. A level takes twice the
    angles of the one below while that widening stays within half its translations.
    """

    def __init__(self, levels, ratio):
        # ratio: cells a wall of B moves per angle step at most (about 1 with the default step)
        self.levels = levels
        self.angles, self.spread = [1], [0]
        for level in range(1, levels + 1):
            n = 2 * self.angles[-1]
            spread = int(math.ceil(n / 2 * ratio + 1e-9))
            if 2 * spread > 2**level:
                n, spread = self.angles[-1], self.spread[-1]
            self.angles.append(n)
            self.spread.append(spread if n > 1 else 0)

    def top(self, lattice):
        """(k_first, row, col) of the coarsest nodes, covering the lattice."""
        size = 2**self.levels
        ks = np.arange(0, len(lattice.thetas), self.angles[self.levels])
        rows = np.arange(lattice.lo[0], lattice.hi[0], size)
        cols = np.arange(lattice.lo[1], lattice.hi[1], size)
        k, r, c = np.meshgrid(ks, rows, cols, indexing="ij")
        return np.stack([k.ravel(), r.ravel(), c.ravel()], axis=1).astype(np.int32)

    def children(self, parents, level, lattice):
        """The children (level - 1) of nodes of ``level`` inside the lattice: their angles halved
        when the level below has fewer, their translations quartered."""
        half = 2**(level - 1)
        n = self.angles[level - 1]
        offsets = [(dk, dr, dc) for dk in ((0, n) if self.angles[level] > n else (0,))
                   for dr in (0, half) for dc in (0, half)]
        children = np.concatenate([parents + np.array(o, dtype=np.int32) for o in offsets])
        inside = ((children[:, 0] < len(lattice.thetas)) & (children[:, 1] < lattice.hi[0])
                  & (children[:, 2] < lattice.hi[1]))
        return children[inside]


class _Frontier:
    """The nodes waiting to be split, for taking the ``BATCH`` of highest bound again and again
    while children arrive. A pool of about ``POOL`` nodes holds every node that bounds above
    ``cold_max``; the others wait in chunks, all bounded by ``cold_max``, and refill the pool when
    it runs low. A batch is the pool's highest bounds, which are the whole frontier's (ties taken
    in another order than a partition of the whole frontier would): the partition over every node
    each batch, with its copies of the frontier, took more time than the scoring on large
    searches (willow's cross-run pair, 2 M nodes: 8 of 14.5 s)."""

    POOL = 4 * BATCH

    def __init__(self, bounds, levels, nodes):
        self.pool = [(bounds[:0], levels[:0], nodes[:0])]
        self.cold, self.cold_max = [(bounds, levels, nodes)], float(bounds.max()) if len(bounds) else -np.inf
        self.refilled = 0              # the size of the last refill

    @staticmethod
    def _joined(parts, threshold):
        """The nodes of ``parts`` that bound above ``threshold``, as one (bounds, levels, nodes)."""
        bounds, levels, nodes = (np.concatenate([part[i] for part in parts]) for i in range(3))
        keep = bounds > threshold
        return (bounds, levels, nodes) if keep.all() else (bounds[keep], levels[keep], nodes[keep])

    @staticmethod
    def _split(part, count):
        """(the ``count`` highest bounds, the rest) of ``part``."""
        order = np.argpartition(-part[0], count - 1)
        return tuple(x[order[:count]] for x in part), tuple(x[order[count:]] for x in part)

    def push(self, bounds, levels, nodes):
        """Children: to the pool where they bound above every waiting node, else to wait."""
        hot = bounds > self.cold_max
        if hot.all():
            self.pool.append((bounds, levels, nodes))
        elif hot.any():
            self.pool.append((bounds[hot], levels[hot], nodes[hot]))
            self.cold.append((bounds[~hot], levels[~hot], nodes[~hot]))
        else:
            self.cold.append((bounds, levels, nodes))

    def _refill(self, threshold):
        """The highest bounds above ``threshold`` of every node into the pool: ``POOL``, or
        sqrt(nodes x ``BATCH``) when more (a batch costs the pool's size, a refill the frontier's:
        that balances them)."""
        every = self._joined(self.pool + self.cold, threshold)
        size = max(self.POOL, int(math.sqrt(len(every[0]) * BATCH)))
        self.refilled = size
        if len(every[0]) <= size:
            self.pool, self.cold, self.cold_max = [every], [], -np.inf
            return
        top, rest = self._split(every, size)
        self.pool, self.cold, self.cold_max = [top], [rest], float(rest[0].max())

    def take(self, threshold):
        """The ``BATCH`` nodes of highest bound above ``threshold`` (fewer when no more are), out
        of the frontier (nodes at or below it are dropped)."""
        pool = self._joined(self.pool, threshold)
        if len(pool[0]) < BATCH and self.cold_max > threshold:
            self.pool = [pool]
            self._refill(threshold)
            pool = self.pool[0]
        if len(pool[0]) <= BATCH:
            self.pool = [(pool[0][:0], pool[1][:0], pool[2][:0])]
            return pool
        taken, rest = self._split(pool, BATCH)
        if len(rest[0]) > 4 * max(self.POOL, self.refilled):    # grown by children bounding high
            rest, lower = self._split(rest, max(self.POOL, self.refilled))
            self.cold.append(lower)
            self.cold_max = max(self.cold_max, float(lower[0].max()))
        self.pool = [rest]
        return taken

    def highest(self, threshold):
        """(bound, level, node (1, 3)) of the highest bound above ``threshold``, or None."""
        pool = self._joined(self.pool, threshold)
        top = float(pool[0].max()) if len(pool[0]) else -np.inf
        self.pool = [pool]
        if self.cold_max > max(top, threshold):
            self._refill(threshold)
            pool = self.pool[0]
            top = float(pool[0].max()) if len(pool[0]) else -np.inf
        if top <= threshold:
            return None
        m = int(np.argmax(pool[0]))
        return top, int(pool[1][m]), pool[2][m:m + 1]


def _branch_and_bound(scorer, lattice, tree, opts):
    """Best-first branch and bound: ([(pose, score)] of the distinct hypotheses, best first,
    whether the best is proven (the search ran to the end, or to ``opts.max_nodes`` with every
    node left bounded below ``COMPLETE_FRACTION`` of it), the fraction of the best down to which
    the runner-ups are proven)."""
    levels = tree.levels

    evaluate = scorer

    nodes = tree.top(lattice)
    bounds = evaluate(levels, nodes)
    if levels == 0:
        return _hypotheses(lattice, bounds, nodes, _distinct(lattice, bounds, nodes, opts, -np.inf)[1]), True, \
            RUNNER_UP_FRACTION
    frontier = _Frontier(bounds, np.full(len(nodes), levels), nodes)
    leaf_scores, leaf_nodes = np.empty(0), np.empty((0, 3), dtype=np.int32)
    threshold = -np.inf
    complete, proven = True, RUNNER_UP_FRACTION
    while True:
        if scorer.scored >= opts.max_nodes:
            highest = frontier.highest(threshold)
            if highest is None:
                break
            best_leaf = leaf_scores.max() if len(leaf_scores) else -np.inf
            if best_leaf > 0 and highest[0] < COMPLETE_FRACTION * best_leaf:
                # over budget with the best proven: runner-ups exact down to the highest bound left
                proven = max(highest[0] / best_leaf, RUNNER_UP_FRACTION)
                break
            # over budget: the best node so far followed down to a leaf, its best child each level
            complete, proven = False, 1.0
            _, level, node = highest
            while level > 0:
                children = tree.children(node, level, lattice)
                values = evaluate(level - 1, children)
                node, level = children[int(np.argmax(values)):int(np.argmax(values)) + 1], level - 1
            leaf_scores = np.concatenate([leaf_scores, values])
            leaf_nodes = np.concatenate([leaf_nodes, children])
            break
        _, node_levels, nodes = frontier.take(threshold)
        if not len(nodes):
            break
        for level in np.unique(node_levels):
            children = tree.children(nodes[node_levels == level], level, lattice)
            values = evaluate(level - 1, children)
            if level - 1 == 0:
                leaf_scores = np.concatenate([leaf_scores, values])
                leaf_nodes = np.concatenate([leaf_nodes, children])
            else:
                frontier.push(values, np.full(len(children), level - 1), children)
        threshold, _ = _distinct(lattice, leaf_scores, leaf_nodes, opts, threshold)
        above = leaf_scores > threshold
        if np.isfinite(threshold) and not above.all():
            # keep only the leaves that may still be hypotheses (and the best's ties)
            above |= leaf_scores >= leaf_scores.max()
            leaf_scores, leaf_nodes = leaf_scores[above], leaf_nodes[above]
    return _hypotheses(lattice, leaf_scores, leaf_nodes,
                       _distinct(lattice, leaf_scores, leaf_nodes, opts, threshold)[1]), complete, proven


def _hypotheses(lattice, scores, nodes, picked):
    """[(pose, score)] of the picked leaves."""
    return [(lattice.poses(k, np.array([r]), np.array([c]))[0], scores[m])
            for m, (k, r, c) in zip(picked, nodes[picked])]


def _distinct(lattice, scores, nodes, opts, threshold):
    """(threshold, indices): the distinct hypotheses among the leaves, best first (greedy:
    a leaf within ``opts.separation`` of a better one is the same hypothesis), and the threshold
    a node's bound must beat to matter: the ``HYPOTHESES``-th one's score, or
    ``RUNNER_UP_FRACTION`` of the best when higher (never lower than ``threshold``)."""
    if not len(scores):
        return threshold, []
    order = np.lexsort((nodes[:, 2], nodes[:, 1], nodes[:, 0], -scores))
    metres, radians = opts.separation
    res = lattice._a.resolution
    picked = []
    for m in order:
        k, row, col = nodes[m]
        if any(abs(row - r) * res <= metres and abs(col - c) * res <= metres
               and abs(wrap_angle(lattice.thetas[k] - lattice.thetas[kk])) <= radians for kk, r, c in
               (nodes[p] for p in picked)):
            continue
        picked.append(m)
        if len(picked) == HYPOTHESES:
            break
    best = scores[picked[0]]
    # a node must beat the threshold to be kept: one just below the fraction keeps a runner-up at it
    floor = np.nextafter(RUNNER_UP_FRACTION * best, -np.inf) if best > 0 else -np.inf
    if len(picked) == HYPOTHESES:
        floor = max(floor, scores[picked[-1]])
    return max(threshold, floor), picked
