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

**The bounds.** A node is one angle and a square of 2^L x 2^L translations. For each wall, its
best value over the square is at most ``P_L(t + q)``, A's ``v`` max-pooled over the square of
cells starting at ``t + q``; the free cells' terms are <= 0 and are dropped. So the node's bound
is one lookup per wall, the same work as one pose. Best-first in batches: the ``BATCH`` nodes of
highest bound are split into their children, all evaluated in one launch (leaves with the full
score), and nodes whose bound cannot beat the threshold are dropped. The threshold is the
``HYPOTHESES``-th best distinct leaf found so far, or ``RUNNER_UP_FRACTION`` of the best when
higher: the best pose is exact, and the runner-ups are exact above that fraction of its score.
"""

import dataclasses
import math

import numpy as np
from scipy import ndimage

from ._errors import InvalidMapError, InvalidOptionError
from ._grid import GridMap, trinary
from ._kernels import _STATE, _launch, ensure_initialized, kernel_lock
from ._se2 import wrap_angle

__all__ = ["SearchOptions", "Hypothesis", "SearchResult", "search", "lattice_cells", "score_grids"]

CLEAR_CELLS = 2.0          # free cells of B nearer its walls than this (cells) are not scored
HYPOTHESES = 3             # distinct hypotheses kept (the best and its runner-ups)
RUNNER_UP_FRACTION = 0.5   # runner-ups are exact above this fraction of the best's score
BATCH = 512                # nodes split per launch
MAX_LEVEL = 7              # the coarsest node: 128 x 128 translations
SMALL_LATTICE = 4096       # lattices of at most this many poses are scored whole (no tree)


@dataclasses.dataclass(frozen=True)
class SearchOptions:
    """Settings of a search. Units: metres, radians.

    window : (metres, radians) around the guess; None searches every pose where the maps overlap.
    blur : sigma of A's envelope in the score, metres; None: 0.1 m or two cells of A if wider
        (a lattice pose puts a point up to a cell and a half from where the true pose does).
    separation : (metres, radians): lattice poses closer than this in both (c's position, angle)
        are the same hypothesis.
    rotation_step : the lattice's angle step; None: the farthest point of B moves one cell of A.
    """

    window: tuple = None
    blur: float = None
    separation: tuple = (0.5, math.radians(10.0))
    rotation_step: float = None


@dataclasses.dataclass(frozen=True)
class Hypothesis:
    """A lattice pose r_A2B = (x, y, theta) and its score S (higher is better)."""

    pose: np.ndarray
    score: float


@dataclasses.dataclass(frozen=True)
class SearchResult:
    """The distinct hypotheses, best first, and what the search did."""

    hypotheses: list
    nodes: int              # lattice nodes scored (bounds and leaves)
    lattice_size: int       # poses in the lattice (what brute force would score)
    rotation_step: float


def score_grids(a: GridMap, blur: float, levels: int):
    """A's values as the score reads them: (pooled (levels + 1, H + S, W + S) float32, free (H, W)
    float32, offset S = 2**levels - 1). ``pooled[L][S + i, S + j]`` is the maximum of v_A over
    the cells (i .. i + 2^L - 1, j .. j + 2^L - 1), 0 off the grid; ``free`` is -1 on A's walls."""
    p = a.prob
    known = ~np.isnan(p)
    walls = p >= 0.5                       # False on unknown (NaN) cells
    if walls.any():
        d = ndimage.distance_transform_edt(~walls) * a.resolution
        hi = np.exp(-0.5 * (d / blur) ** 2) if blur > 0 else walls.astype(np.float64)
    else:
        hi = np.zeros(p.shape)
    v = np.where(known, 2.0 * hi - 1.0, hi).astype(np.float32)
    s = 2**levels - 1
    h, w = p.shape
    pooled = np.zeros((levels + 1, h + s + 2**levels, w + s + 2**levels), dtype=np.float32)
    pooled[0, s:s + h, s:s + w] = v
    for level in range(1, levels + 1):          # max over [x, x + 2^L) from two windows of 2^(L-1)
        half = 2**(level - 1)
        prev, cur = pooled[level - 1], pooled[level]
        np.copyto(cur, prev)
        np.maximum(cur[:-half], prev[half:], out=cur[:-half])
        np.maximum(cur[:, :-half], cur[:, half:].copy(), out=cur[:, :-half])
    return pooled, np.where(walls, np.float32(-1.0), np.float32(0.0)), s


def _points(b: GridMap):
    """B's walls and clear free cells, (x, y) in B's frame (metres)."""
    p = b.prob
    walls = p >= 0.5
    free = p < 0.5                          # False on unknown cells
    if walls.any():
        clear = ndimage.distance_transform_edt(~walls) >= CLEAR_CELLS
        free &= clear
    return b.cell_centres(*np.nonzero(walls)), b.cell_centres(*np.nonzero(free))


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
        self.centre = centre
        self._a = a
        if opts.window is None:
            n = max(int(math.ceil(2.0 * math.pi / step)), 1)
            self.step = 2.0 * math.pi / n
            self.thetas = np.arange(n) * self.step
            known = np.argwhere(~np.isnan(a.prob))
            reach = int(math.ceil(radius / res)) + 1
            self.lo = known.min(axis=0) - reach
            self.hi = known.max(axis=0) + reach + 1            # exclusive
        else:
            metres, radians = (float(v) for v in opts.window)
            n = int(math.ceil(radians / step))
            self.step = step
            self.thetas = guess[2] + np.arange(-n, n + 1) * step
            landing = guess[:2] + _rotate(guess[2], centre)      # c at the guess, in A's frame
            row, col = a.grid_coordinates(landing)
            span = int(math.ceil(metres / res))
            self.lo = np.array([math.floor(row) - span, math.floor(col) - span])
            self.hi = np.array([math.floor(row) + span + 1, math.floor(col) + span + 1])

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
    """Scores nodes (angle index, level, c's cell) in batches, one launch each (``engine``
    "taichi"), or in NumPy ("numpy", the same sums in another order)."""

    def __init__(self, a, walls, free, centre, lattice, blur, levels, engine):
        self.pooled, self.free_grid, self.offset = score_grids(a, blur, levels)
        self.walls, self.free, self.centre = walls, free, centre
        self.a, self.lattice, self.engine = a, lattice, engine
        n = len(lattice.thetas)
        self.wall_cells = np.zeros((n, max(len(walls), 1), 2), dtype=np.int32)
        self.free_cells = np.zeros((n, max(len(free), 1), 2), dtype=np.int32)
        self._have = np.zeros((2, n), dtype=bool)
        self.scored = 0

    def _cells(self, ks, leaf):
        """Fill the angles' cells of the walls (and of the free cells for leaves) when first used."""
        for kind, points, table in ((0, self.walls, self.wall_cells), (1, self.free, self.free_cells))[:1 + leaf]:
            for k in np.unique(ks[~self._have[kind, ks]]):
                if len(points):
                    table[k, :len(points)] = lattice_cells(self.a, points, self.centre, self.lattice.thetas[k])
                self._have[kind, k] = True

    def __call__(self, level, nodes, leaf):
        """(N,) float64 sums over B's walls of pooled level ``level`` at nodes (N, 3) int32
        (angle, c's row, c's col), and with ``leaf`` of its free cells on A's walls."""
        self.scored += len(nodes)
        self._cells(nodes[:, 0], leaf)
        n_walls, n_free = len(self.walls), len(self.free) if leaf else 0
        if self.engine == "numpy":
            return self._numpy(level, nodes, n_walls, n_free)
        out = np.empty(len(nodes), dtype=np.float64)
        sizes = np.array([n_walls, n_free, self.offset], dtype=np.int32)
        with kernel_lock():
            kernel = _kernel()
            _launch(kernel, (self.wall_cells, self.free_cells, sizes, self.pooled[level], self.free_grid,
                             np.ascontiguousarray(nodes, dtype=np.int32), out), None)
        return out

    def _numpy(self, level, nodes, n_walls, n_free):
        out = np.zeros(len(nodes), dtype=np.float64)
        s = self.offset
        grid = self.pooled[level]
        for m, (k, row, col) in enumerate(nodes):
            q = self.wall_cells[k, :n_walls] + (row + s, col + s)
            inside = (q >= 0).all(axis=1) & (q[:, 0] < grid.shape[0]) & (q[:, 1] < grid.shape[1])
            total = grid[q[inside, 0], q[inside, 1]].astype(np.float64).sum()
            if n_free:
                f = self.free_cells[k, :n_free] + (row, col)
                h, w = self.free_grid.shape
                inside = (f >= 0).all(axis=1) & (f[:, 0] < h) & (f[:, 1] < w)
                total += self.free_grid[f[inside, 0], f[inside, 1]].astype(np.float64).sum()
            out[m] = total
        return out


_KERNEL = {}


def _kernel():
    ensure_initialized()
    if "score" not in _KERNEL:
        _KERNEL["score"] = _build(_STATE["ti"])
    return _KERNEL["score"]


def _build(ti):
    @ti.kernel
    def score(wall_cells: ti.types.ndarray(dtype=ti.i32, ndim=3), free_cells: ti.types.ndarray(dtype=ti.i32, ndim=3),
              sizes: ti.types.ndarray(dtype=ti.i32, ndim=1), pooled: ti.types.ndarray(dtype=ti.f32, ndim=2),
              free: ti.types.ndarray(dtype=ti.f32, ndim=2), nodes: ti.types.ndarray(dtype=ti.i32, ndim=2),
              out: ti.types.ndarray(dtype=ti.f64, ndim=1)):
        n_walls, n_free, s = sizes[0], sizes[1], sizes[2]
        h, w = pooled.shape[0], pooled.shape[1]
        fh, fw = free.shape[0], free.shape[1]
        for m in range(nodes.shape[0]):                     # a node per work item, its points in order
            k, row, col = nodes[m, 0], nodes[m, 1], nodes[m, 2]
            total = ti.f64(0.0)
            for p in range(n_walls):
                i = wall_cells[k, p, 0] + row + s
                j = wall_cells[k, p, 1] + col + s
                inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
                total += ti.select(inside, ti.cast(pooled[ti.min(ti.max(i, 0), h - 1), ti.min(ti.max(j, 0), w - 1)],
                                                   ti.f64), 0.0)
            for p in range(n_free):
                i = free_cells[k, p, 0] + row
                j = free_cells[k, p, 1] + col
                inside = (i >= 0) & (i < fh) & (j >= 0) & (j < fw)
                total += ti.select(inside, ti.cast(free[ti.min(ti.max(i, 0), fh - 1), ti.min(ti.max(j, 0), fw - 1)],
                                                   ti.f64), 0.0)
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
            raise InvalidOptionError(f"window must be (0..1e4 metres, 0..4 pi radians); got {opts.window!r}")
        guess = np.asarray(guess, dtype=np.float64)
    if opts.blur is not None and not (0.0 < opts.blur <= 1e3):
        raise InvalidOptionError(f"blur must be in (0, 1e3] metres or None; got {opts.blur!r}")
    if engine not in ("taichi", "numpy"):
        raise InvalidOptionError(f"engine must be 'taichi' or 'numpy'; got {engine!r}")
    a, b = trinary(a), trinary(b)
    walls, free = _points(b)
    if len(walls) == 0:
        raise InvalidMapError("B has no occupied cell: nothing to search with")
    if not np.isfinite(a.prob).any():
        raise InvalidMapError("A has no known cell")
    centre = walls.mean(axis=0)
    radius = float(np.sqrt(((np.concatenate([walls, free]) - centre) ** 2).sum(axis=1).max()))
    lattice = _Lattice(a, centre, radius, opts, guess)
    span = int((lattice.hi - lattice.lo).max())
    levels = min(MAX_LEVEL, max(int(math.ceil(math.log2(max(span, 1)))) - 2, 0))
    if lattice.size <= SMALL_LATTICE:
        levels = 0
    wall_radius = float(np.sqrt(((walls - centre) ** 2).sum(axis=1).max()))
    tree = _Tree(levels, lattice.step * wall_radius / a.resolution)
    blur = max(0.1, 2.0 * a.resolution) if opts.blur is None else opts.blur
    scorer = _Scorer(a, walls, free, centre, lattice, blur, levels + 1, engine)
    leaves = _branch_and_bound(scorer, lattice, tree, opts)
    hypotheses = [Hypothesis(pose, float(score)) for pose, score in leaves]
    return SearchResult(hypotheses, scorer.scored, lattice.size, lattice.step)


class _Tree:
    """The nodes' shape per level L: 2^L x 2^L translations and ``angles[L]`` consecutive angles.

    A node of several angles is bounded from its middle angle: every point of B lies within
    ``spread[L]`` cells (per axis) of where it lies at that angle, so the node's cells are those
    of the middle angle's node widened by ``spread[L]`` on each side, which the pooled grid of
    level L + 1 covers from ``spread[L]`` cells before (its window is 2^(L+1) >= 2^L + 2 spread).
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

    def grid_level(self, level):
        """The pooled level a node's bound reads."""
        return level + 1 if self.angles[level] > 1 else level

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
        offsets = [(dk, dr, dc) for dk in ((0, n) if self.angles[level] > n else (0,)) for dr in (0, half) for dc in (0, half)]
        children = np.concatenate([parents + np.array(o, dtype=np.int32) for o in offsets])
        inside = (children[:, 0] < len(lattice.thetas)) & (children[:, 1] < lattice.hi[0]) & (children[:, 2] < lattice.hi[1])
        return children[inside]

    def probes(self, nodes, level, n_angles):
        """The nodes as the scorer reads them: (middle angle, row - spread, col - spread)."""
        k = nodes[:, 0]
        middle = k + np.minimum(self.angles[level], n_angles - k) // 2
        spread = self.spread[level]
        return np.stack([middle, nodes[:, 1] - spread, nodes[:, 2] - spread], axis=1).astype(np.int32)


def _branch_and_bound(scorer, lattice, tree, opts):
    """Best-first branch and bound; returns [(pose, score)] of the distinct hypotheses, best first."""
    levels, n_angles = tree.levels, len(lattice.thetas)

    def evaluate(level, nodes):
        return scorer(tree.grid_level(level), tree.probes(nodes, level, n_angles), leaf=level == 0)

    nodes = tree.top(lattice)
    bounds = evaluate(levels, nodes)
    if levels == 0:
        return _hypotheses(lattice, bounds, nodes, _distinct(lattice, bounds, nodes, opts, -np.inf)[1])
    node_levels = np.full(len(nodes), levels)
    leaf_scores, leaf_nodes = np.empty(0), np.empty((0, 3), dtype=np.int32)
    threshold = -np.inf
    while len(bounds):
        keep = bounds > threshold
        bounds, node_levels, nodes = bounds[keep], node_levels[keep], nodes[keep]
        if not len(bounds):
            break
        # the BATCH highest bounds (argpartition is deterministic for the same frontier)
        if len(bounds) > BATCH:
            order = np.argpartition(-bounds, BATCH - 1)
            take, rest = order[:BATCH], order[BATCH:]
        else:
            take, rest = np.arange(len(bounds)), np.empty(0, dtype=np.int64)
        new_bounds, new_levels, new_nodes = [bounds[rest]], [node_levels[rest]], [nodes[rest]]
        for level in np.unique(node_levels[take]):
            children = tree.children(nodes[take][node_levels[take] == level], level, lattice)
            values = evaluate(level - 1, children)
            if level - 1 == 0:
                leaf_scores = np.concatenate([leaf_scores, values])
                leaf_nodes = np.concatenate([leaf_nodes, children])
            else:
                new_bounds.append(values)
                new_levels.append(np.full(len(children), level - 1))
                new_nodes.append(children)
        bounds = np.concatenate(new_bounds)
        node_levels = np.concatenate(new_levels)
        nodes = np.concatenate(new_nodes)
        threshold, _ = _distinct(lattice, leaf_scores, leaf_nodes, opts, threshold)
        above = leaf_scores > threshold
        if np.isfinite(threshold) and not above.all():
            # keep only the leaves that may still be hypotheses (and the best's ties)
            above |= leaf_scores >= leaf_scores.max()
            leaf_scores, leaf_nodes = leaf_scores[above], leaf_nodes[above]
    return _hypotheses(lattice, leaf_scores, leaf_nodes, _distinct(lattice, leaf_scores, leaf_nodes, opts, threshold)[1])


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
    floor = RUNNER_UP_FRACTION * best if best > 0 else -np.inf
    if len(picked) == HYPOTHESES:
        floor = max(floor, scores[picked[-1]])
    return max(threshold, floor), picked
