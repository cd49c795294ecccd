"""Occupancy grids from 2-D laser scans: log-odds ray casting.

The hit/miss model (an inverse sensor model in log-odds, as in Thrun, Burgard & Fox, ch. 9):

- Each beam is a segment from the laser's position to its endpoint, in the grid's frame. A beam
  with a return (``min_range < r < max_range``) adds ``hit`` to the log-odds of the cell holding
  its endpoint and ``miss`` to every other cell the segment passes through (the exact cell
  traversal of the segment, each cell once per beam), except the cells where a beam of the same
  scan ends with a return: a scan's hits go in before its misses, as Cartographer inserts a scan.
  Otherwise the beam next to a grazing return clears the return's cell: 15-25 % of a lone scan's
  returns were left unknown (p = 0.5) on the shared logs. Each scan matched against the 10 scans
  before it (both cast at the reference poses), median error with the rule against without: 9.2
  mm / 0.105 deg against 10.4 / 0.141 on the simulated run, 21.9 mm / 0.21 deg against 24.7 /
  0.24 on seattle, 25.5 mm / 0.29 deg against 24.8 / 0.27 on csail.
- With ``free_margin`` > 0 a beam with a return counts as free only up to that many metres short of
  its endpoint (its hit stays at the endpoint). Why: a wall seen by several scans is a band of
  cells (range noise); the returns that land short in the band are crossed by the beams of the
  other scans that land long, which clear them, while nothing clears the far side: the wall of a
  submap moves away from the lasers that saw it. A lone scan matched against such a submap came
  out ahead of the truth (a forward-looking laser: its walls ahead pulled onto the submap's):
  mean forward error 3.6 mm on the simulated run and 6.6-19.7 mm on the eight shared logs (each
  third scan against the 7 before it cast at the reference poses), with 0.1 m -0.9 and 0.5-10.8
  mm (bench/FRONT_END_BIAS.md). ``slam``'s submaps use 0.1 (``SlamOptions.free_margin``).
- A return farther than ``max_ray_length`` is cut there and counts as free up to the cut (no hit).
- A beam with no return (``r >= max_range``, the sensor's saturation value) counts as free up to
  ``no_return_length`` metres (0: ignored): nothing was hit that close.
- Readings that are NaN, infinite or at most ``min_range`` are ignored.
- Per cell: ``L = clip(hit * hits + miss * misses, -clamp, clamp)``; the probability is
  ``1 / (1 + exp(-L))``; a cell no beam reached is unknown (NaN). Counting hits and misses as
  integers makes the result independent of the order of the beams (and so bit-identical
  whatever the parallel schedule).

The grid is axis-aligned in the frame the poses are given in, its cell boundaries on multiples of
the resolution (the lattice), just large enough for every segment (plus ``margin`` cells of unknown
around). A beam's cells are found on the lattice, whatever the grid's extent, so ``BeamCounts``
can add scans to a grid that grows and still give ``scans_to_grid``'s grid of them all, bit for bit.

``engine="taichi"`` casts all beams of all scans in one parallel launch; ``engine="numpy"`` is the
plain reference it is tested against.
"""

from dataclasses import dataclass
from typing import Literal, Optional

import numpy as np

from ._errors import InvalidOptionError, InvalidPoseError, shown
from ._grid import GridMap, _from_code, _trusted, trinary, trinary_code
from ._se2 import as_poses

__all__ = ["SensorModel", "beam_segments", "scans_to_grid", "BeamCounts", "trinary", "count_traversals"]


# Grids cast from scans hold at most this many cells (about 6 GB of arrays while casting).
MAX_GRID_CELLS = 2**28


@dataclass(frozen=True)
class SensorModel:
    """The hit/miss model of ``scans_to_grid`` (see the module docstring). Metres, log-odds."""

    hit: float = 0.9
    miss: float = -0.4
    clamp: float = 6.0
    min_range: float = 0.05
    max_ray_length: float = 20.0
    no_return_length: float = 5.0
    free_margin: float = 0.0

    def __post_init__(self):
        for name in ("hit", "miss", "clamp", "min_range", "max_ray_length", "no_return_length", "free_margin"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise InvalidOptionError(f"SensorModel.{name} must be a number; got {shown(value)}")
        for name in ("hit", "clamp", "min_range", "max_ray_length", "no_return_length", "free_margin"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0.0:
                raise InvalidOptionError(f"SensorModel.{name} must be finite and >= 0; got {shown(value)}")
        if not np.isfinite(self.miss) or self.miss > 0.0:
            raise InvalidOptionError(f"SensorModel.miss must be finite and <= 0; got {shown(self.miss)}")
        if self.max_ray_length <= self.min_range:
            raise InvalidOptionError("SensorModel.max_ray_length must exceed min_range")


def beam_segments(scans, poses, model: SensorModel = SensorModel()):
    """The segments the beams of ``scans`` cast, laser at ``poses`` (S, 3) in the grid's frame.

    Returns (starts (R, 2), ends (R, 2), hit (R,) bool, scan (R,) int): one row per usable beam,
    in scan order, ``scan`` the index of its scan in ``scans``.
    """
    poses = as_poses(poses, "poses")
    if len(poses) != len(scans):
        raise InvalidPoseError(f"{len(scans)} scans but {len(poses)} poses")
    starts, ends, hits, owners = [], [], [], []
    for index, (scan, (x, y, theta)) in enumerate(zip(scans, poses)):
        r = np.asarray(scan.ranges, dtype=np.float64)
        a = np.asarray(scan.angles, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(r) & (r > model.min_range)
            no_return = valid & (r >= scan.max_range)
        length = np.where(no_return, model.no_return_length, np.minimum(r, model.max_ray_length))
        hit = valid & ~no_return & (r <= model.max_ray_length)
        keep = valid & (length > 0.0)
        angle = theta + a[keep]
        d = length[keep]
        ends.append(np.column_stack([x + d * np.cos(angle), y + d * np.sin(angle)]))
        starts.append(np.broadcast_to([x, y], (int(keep.sum()), 2)))
        hits.append(hit[keep])
        owners.append(np.full(int(keep.sum()), index, dtype=np.int64))
    if not starts:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=bool), np.zeros(0, dtype=np.int64)
    return np.vstack(starts), np.vstack(ends), np.concatenate(hits), np.concatenate(owners)


def _short_of_returns(starts, ends, hit, scan, margin: float):
    """``beam_segments``' rows with each return's free part ending ``margin`` metres short of its
    endpoint (``SensorModel.free_margin``): a row without a hit up to there (none when the beam is
    no longer than the margin) and a hit of zero length at the endpoint, in scan order."""
    d = ends - starts
    length = np.hypot(d[:, 0], d[:, 1])
    free = ~hit | (length > margin)
    share = np.where(hit, (length - margin) / np.where(length > 0.0, length, 1.0), 1.0)[free]
    owners = np.concatenate([scan[free], scan[hit]])
    order = np.argsort(owners, kind="stable")
    new_hit = np.arange(len(owners)) >= int(free.sum())          # the free rows first, then the hits
    return (np.concatenate([starts[free], ends[hit]])[order],
            np.concatenate([starts[free] + d[free] * share[:, None], ends[hit]])[order], new_hit[order], owners[order])


def _cells_of_segment(u0, v0, u1, v1):
    """(rows, cols) of the cells the segment (u0, v0) -> (u1, v1) passes through, in order; grid
    coordinates in cells (column u, row v). The parameters where it crosses a grid line split it;
    each piece lies in one cell (a piece of zero length is dropped). Along each axis that cell is
    the one the segment starts in (on a grid line, the one it moves into), stepped once per
    crossing before the piece: counted, not found from the piece's midpoint, which rounds onto
    the grid line when the segment moves less than a rounding error along that axis."""
    ts = [np.array([0.0, 1.0])]
    crossings = []
    for a0, a1 in ((u0, u1), (v0, v1)):
        t_axis = np.zeros(0)
        if a1 != a0:
            lo, hi = min(a0, a1), max(a0, a1)
            k = np.arange(np.ceil(lo), np.floor(hi) + 1.0)
            t_axis = np.sort(np.clip((k - a0) / (a1 - a0), 0.0, 1.0))
        ts.append(t_axis)
        crossings.append(t_axis[t_axis > 0.0])
    t = np.unique(np.concatenate(ts))
    start = t[:-1]
    cells = []
    for (a0, a1), t_axis in zip(((u0, u1), (v0, v1)), crossings):
        first = np.ceil(a0) - 1.0 if a1 < a0 else np.floor(a0)
        step = 1 if a1 > a0 else -1
        cells.append((first + step * np.searchsorted(t_axis, start, side="right")).astype(np.int64))
    cols, rows = cells
    return rows, cols


def count_traversals(starts, ends, hit, offset, resolution, shape, engine: Literal["taichi", "numpy"] = "taichi",
                     scan=None, out=None):
    """(hits, misses) int32 arrays of ``shape``: per cell, the beams ending in it with a return and
    the beams passing through it otherwise (see the module docstring). Segments in metres in the
    grid's frame, whose lattice of cells has its lines on multiples of ``resolution``; the array's
    cell [r, c] is the lattice cell (row0 + r, col0 + c), ``offset`` = (row0, col0) (integers), so
    a beam's cells do not depend on the array's extent. ``scan`` (R,) non-decreasing: each beam's
    scan (a beam does not miss where its own scan's beams end with a return); None: each beam a
    scan of its own. ``out``: (hits, misses) C-contiguous int32 arrays of ``shape`` to add into."""
    row0, col0 = (int(n) for n in offset)
    u0, v0 = starts[:, 0] / resolution, starts[:, 1] / resolution
    u1, v1 = ends[:, 0] / resolution, ends[:, 1] / resolution
    if engine == "taichi":
        from ._raycast import count_traversals_taichi

        return count_traversals_taichi(np.column_stack([u0, v0, u1, v1]), np.asarray(hit, dtype=np.int32), shape,
                                       scan, (row0, col0), out)
    if engine != "numpy":
        raise InvalidOptionError(f"engine must be 'taichi' or 'numpy'; got {engine!r}")
    hits, misses = out if out is not None else (np.zeros(shape, dtype=np.int32), np.zeros(shape, dtype=np.int32))
    own = {}                                    # scan -> the cells its beams end in with a return
    for k in range(len(u0)):
        row, col = int(np.floor(v1[k])) - row0, int(np.floor(u1[k])) - col0
        if hit[k] and scan is not None and 0 <= row < shape[0] and 0 <= col < shape[1]:
            own.setdefault(scan[k], set()).add(row * shape[1] + col)
    for k in range(len(u0)):
        rows, cols = _cells_of_segment(u0[k], v0[k], u1[k], v1[k])
        rows, cols = rows - row0, cols - col0
        if hit[k]:
            end_row, end_col = int(np.floor(v1[k])) - row0, int(np.floor(u1[k])) - col0
            if 0 <= end_row < shape[0] and 0 <= end_col < shape[1]:
                hits[end_row, end_col] += 1
            free = (rows != end_row) | (cols != end_col)
            rows, cols = rows[free], cols[free]
        inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])    # as the kernel: skip
        rows, cols = rows[inside], cols[inside]
        cells = np.unique(rows * shape[1] + cols)
        if scan is not None and scan[k] in own:
            cells = cells[~np.isin(cells, list(own[scan[k]]))]
        np.add.at(misses.reshape(-1), cells, 1)
    return hits, misses


class BeamCounts:
    """Hits and misses of scans cast one batch after another (``add``) on a grid that grows to
    hold every beam: ``grid()`` after any number of ``add`` calls is ``scans_to_grid`` of all the
    scans added so far, bit for bit (the counts are integers and a beam's cells do not depend on
    the grid's extent). A mapping loop adds a submap's new scan instead of casting them all again.

    Parameters are ``scans_to_grid``'s.
    """

    def __init__(self, *, resolution: float = 0.05, model: SensorModel = SensorModel(), margin: int = 2,
                 engine: Literal["taichi", "numpy"] = "taichi"):
        if not np.isfinite(resolution) or resolution <= 0.0:
            raise InvalidOptionError(f"resolution must be finite and > 0; got {shown(resolution)}")
        self.resolution, self.model, self.margin, self.engine = resolution, model, margin, engine
        self._offset = np.zeros(2, dtype=np.int64)    # lattice (row, col) of the arrays' cell [0, 0]
        self._hits = self._misses = np.zeros((0, 0), dtype=np.int32)
        self._grids = {}                              # evidence -> the whole grid, until a beam is added

    def add(self, scans, poses) -> "BeamCounts":
        """Cast ``scans`` taken at ``poses`` (S, 3) in the grid's frame into the counts."""
        starts, ends, hit, scan = beam_segments(scans, poses, self.model)
        if len(starts) == 0:
            return self
        if self.model.free_margin > 0.0:
            starts, ends, hit, scan = _short_of_returns(starts, ends, hit, scan, self.model.free_margin)
        points = np.vstack([starts, ends])
        # the lattice cells the beams reach, plus the margin: (row, col) from, to (exclusive)
        lo = np.floor(points.min(axis=0)[::-1] / self.resolution) - self.margin
        hi = np.floor(points.max(axis=0)[::-1] / self.resolution) + 1 + self.margin
        if self._hits.size:
            lo, hi = np.minimum(lo, self._offset), np.maximum(hi, self._offset + self._hits.shape)
        span = hi - lo
        if span[0] * span[1] > MAX_GRID_CELLS or np.abs(lo).max() > MAX_GRID_CELLS:
            raise InvalidOptionError(f"the beams span {span[1]:.0f} x {span[0]:.0f} cells at {self.resolution} m, "
                                     f"more than {MAX_GRID_CELLS}, or lie that many cells from the origin: a coarser "
                                     f"resolution, shorter rays (SensorModel.max_ray_length) or fewer scans")
        lo = lo.astype(np.int64)
        shape = tuple(int(n) for n in span)
        if shape != self._hits.shape or np.any(lo != self._offset):
            hits, misses = np.zeros(shape, dtype=np.int32), np.zeros(shape, dtype=np.int32)
            r, c = (int(n) for n in self._offset - lo)
            h, w = self._hits.shape
            hits[r:r + h, c:c + w], misses[r:r + h, c:c + w] = self._hits, self._misses
            self._hits, self._misses, self._offset = hits, misses, lo
        count_traversals(starts, ends, hit, tuple(self._offset), self.resolution, shape, self.engine, scan,
                         out=(self._hits, self._misses))
        self._grids = {}
        return self

    def grid(self, bounds=None, *, evidence: Literal["probability", "trinary"] = "probability") -> Optional[GridMap]:
        """The occupancy grid of the scans added so far (``scans_to_grid``); with ``bounds``
        (x_min, y_min, x_max, y_max) in the grid's frame, metres, only its cells that the box
        touches (the same cells, bit for bit; a mapping loop matches a scan against the part of a
        submap it can land on); None when the box touches none of its cells. The whole grid is
        the same object until a beam is added (a matcher then finds it prepared). ``evidence``:
        "trinary" gives ``trinary`` of that grid, bit for bit, made from the counts directly."""
        if self._hits.size == 0:
            raise InvalidOptionError("no usable beam in the scans (all readings invalid)")
        if evidence not in ("probability", "trinary"):
            raise InvalidOptionError(f"evidence must be 'probability' or 'trinary'; got {evidence!r}")
        if bounds is None and evidence in self._grids:
            return self._grids[evidence]
        model, hits, misses, offset = self.model, self._hits, self._misses, self._offset
        if bounds is not None:
            try:
                box = np.asarray(bounds, dtype=np.float64) if np.shape(bounds) == (4,) else np.full(4, np.nan)
            except (TypeError, ValueError):
                box = np.full(4, np.nan)
            x_min, y_min, x_max, y_max = box
            if not np.all(np.isfinite(box)) or x_min > x_max or y_min > y_max:
                raise InvalidOptionError(f"bounds must be finite (x_min, y_min, x_max, y_max), the least first; "
                                         f"got {shown(bounds)}")
            # the lattice cells the box touches, within the canvas (row, col)
            lo = np.maximum(np.floor(np.array([y_min, x_min]) / self.resolution), offset)
            hi = np.minimum(np.floor(np.array([y_max, x_max]) / self.resolution) + 1, offset + hits.shape)
            if np.any(hi <= lo):
                return None
            (r0, c0), (r1, c1) = (lo - offset).astype(np.int64), (hi - offset).astype(np.int64)
            hits, misses, offset = hits[r0:r1, c0:c1], misses[r0:r1, c0:c1], lo.astype(np.int64)
        values = _probabilities(hits, misses, model, self.engine, evidence == "trinary")
        # the corner on the lattice: the same float as (floor(x / resolution) - margin) * resolution
        corner = offset[::-1].astype(np.float64) * self.resolution
        corner = (float(corner[0]), float(corner[1]), 0.0)
        if evidence == "trinary":
            grid = _from_code(values, self.resolution, corner)
        else:
            grid = _trusted(values, self.resolution, corner)              # in (0, 1) or NaN
        if bounds is None:
            self._grids[evidence] = grid
        return grid


# ``_probabilities`` reads a table of every (hits, misses) pair up to the grid's largest counts
# while it holds at most this many entries: a laser submap's cells hold a hundred distinct pairs
# (edmonton, 10 scans: 109 in 113k known cells, at most 2 hits and 192 misses a cell), and on
# its 780 x 504 canvas one Taichi pass reading the table took 0.35-0.45 ms (NumPy's take 0.5 ms
# with its index kept, 3-4 ms with a fresh one: page faults) against 1.5-2.1 ms for the known
# cells one by one. The same numbers, bit for bit: the same operations on the same float64 values
# (a mapping loop's trajectories and maps are unchanged on seattle and edmonton).
MAX_TABLE = 2**16


def _probabilities(hits, misses, model, engine="taichi", code=False):
    """(H, W) 1 / (1 + exp(-clip(hit * hits + miss * misses, -clamp, clamp))) per cell, NaN where
    no beam reached (both counts 0): from a table of the count pairs when it is small
    (``MAX_TABLE``), else on the known cells only (a fifth of a laser submap's canvas), in place
    (fresh arrays cost page faults). ``code``: their ``trinary_code`` instead, read from the
    table's codes (a byte a cell written, where the probabilities take eight and the codes a pass
    over them)."""
    most_hits, most_misses = int(hits.max()), int(misses.max())
    from_table = (most_hits + 1) * (most_misses + 1) <= MAX_TABLE
    if from_table:
        h = np.arange(most_hits + 1, dtype=np.int32)[:, None]
        m = np.arange(most_misses + 1, dtype=np.int32)[None, :]
        p = model.hit * h + model.miss * m
    else:
        known = (hits | misses) != 0
        p = model.hit * hits[known]
        p += model.miss * misses[known]
    np.clip(p, -model.clamp, model.clamp, out=p)
    np.negative(p, out=p)
    np.exp(p, out=p)
    p += 1.0
    np.divide(1.0, p, out=p)
    if from_table:
        p[0, 0] = np.nan
        table = trinary_code(p) if code else p
        if engine == "taichi":
            from ._raycast import lookup_pairs_taichi

            return lookup_pairs_taichi(hits, misses, table)
        index = hits.astype(np.intp)              # take() casts other indices first: 10x slower
        index *= most_misses + 1
        index += misses
        return table.reshape(-1).take(index)
    prob = np.full(hits.shape, np.nan)
    prob[known] = p
    return trinary_code(prob) if code else prob


def scans_to_grid(scans, poses, *, resolution: float = 0.05, model: SensorModel = SensorModel(),
                  margin: int = 2, engine: Literal["taichi", "numpy"] = "taichi",
                  evidence: Literal["probability", "trinary"] = "probability") -> GridMap:
    """An occupancy grid (probabilities, NaN unobserved) from ``scans`` taken at ``poses``.

    Parameters
    ----------
    scans : sequence of ``logs.Scan``
    poses : array_like (S, 3)
        Each scan's laser pose (x, y, theta) in the frame the grid is built in.
    resolution : float
        Cell side, metres.
    model : SensorModel
        The hit/miss model.
    margin : int
        Unknown cells added on each side.
    engine : "taichi" (one parallel launch for all beams) or "numpy" (the reference).
    evidence : "probability", or "trinary": the grid's ``trinary`` map (occupied 1, free 0, the
        rest unknown), bit for bit, made from the counts directly (cheaper: a byte a cell).
    """
    counts = BeamCounts(resolution=resolution, model=model, margin=margin, engine=engine).add(scans, poses)
    return counts.grid(evidence=evidence)
