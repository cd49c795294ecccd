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
- A return farther than ``max_ray_length`` is cut there and counts as free up to the cut (no hit).
- A beam with no return (``r >= max_range``, the sensor's saturation value) counts as free up to
  ``no_return_length`` metres (0: ignored): nothing was hit that close.
- Readings that are NaN, infinite or at most ``min_range`` are ignored.
- Per cell: ``L = clip(hit * hits + miss * misses, -clamp, clamp)``; the probability is
  ``1 / (1 + exp(-L))``; a cell no beam reached is unknown (NaN). Counting hits and misses as
  integers makes the result independent of the order of the beams (and so bit-identical
  whatever the parallel schedule).

The grid is axis-aligned in the frame the poses are given in, its cell boundaries on multiples of
the resolution, just large enough for every segment (plus ``margin`` cells of unknown around).

``engine="taichi"`` casts all beams of all scans in one parallel launch; ``engine="numpy"`` is the
plain reference it is tested against.
"""

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ._errors import InvalidOptionError, InvalidPoseError
from ._grid import GridMap, _trusted, trinary
from ._se2 import as_poses

__all__ = ["SensorModel", "beam_segments", "scans_to_grid", "trinary", "count_traversals"]


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

    def __post_init__(self):
        for name in ("hit", "miss", "clamp", "min_range", "max_ray_length", "no_return_length"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise InvalidOptionError(f"SensorModel.{name} must be a number; got {value!r}")
        for name in ("hit", "clamp", "min_range", "max_ray_length", "no_return_length"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0.0:
                raise InvalidOptionError(f"SensorModel.{name} must be finite and >= 0; got {value!r}")
        if not np.isfinite(self.miss) or self.miss > 0.0:
            raise InvalidOptionError(f"SensorModel.miss must be finite and <= 0; got {self.miss!r}")
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


def count_traversals(starts, ends, hit, origin, resolution, shape, engine: Literal["taichi", "numpy"] = "taichi",
                     scan=None):
    """(hits, misses) int32 arrays of ``shape``: per cell, the beams ending in it with a return and
    the beams passing through it otherwise (see the module docstring). Segments in metres in the
    grid's frame; the grid's cell (0, 0) has its outer corner at ``origin``. ``scan`` (R,)
    non-decreasing: each beam's scan (a beam does not miss where its own scan's beams end with a
    return); None: each beam a scan of its own."""
    u0 = (starts[:, 0] - origin[0]) / resolution
    v0 = (starts[:, 1] - origin[1]) / resolution
    u1 = (ends[:, 0] - origin[0]) / resolution
    v1 = (ends[:, 1] - origin[1]) / resolution
    if engine == "taichi":
        from ._raycast import count_traversals_taichi

        return count_traversals_taichi(np.column_stack([u0, v0, u1, v1]), np.asarray(hit, dtype=np.int32), shape,
                                       scan)
    if engine != "numpy":
        raise InvalidOptionError(f"engine must be 'taichi' or 'numpy'; got {engine!r}")
    hits = np.zeros(shape, dtype=np.int32)
    misses = np.zeros(shape, dtype=np.int32)
    own = {}                                    # scan -> the cells its beams end in with a return
    for k in range(len(u0)):
        row, col = int(np.floor(v1[k])), int(np.floor(u1[k]))
        if hit[k] and scan is not None and 0 <= row < shape[0] and 0 <= col < shape[1]:
            own.setdefault(scan[k], set()).add(row * shape[1] + col)
    for k in range(len(u0)):
        rows, cols = _cells_of_segment(u0[k], v0[k], u1[k], v1[k])
        if hit[k]:
            end_row, end_col = int(np.floor(v1[k])), int(np.floor(u1[k]))
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


def scans_to_grid(scans, poses, *, resolution: float = 0.05, model: SensorModel = SensorModel(),
                  margin: int = 2, engine: Literal["taichi", "numpy"] = "taichi") -> GridMap:
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
    """
    if not np.isfinite(resolution) or resolution <= 0.0:
        raise InvalidOptionError(f"resolution must be finite and > 0; got {resolution!r}")
    starts, ends, hit, scan = beam_segments(scans, poses, model)
    if len(starts) == 0:
        raise InvalidOptionError("no usable beam in the scans (all readings invalid)")
    points = np.vstack([starts, ends])
    lo = (np.floor(points.min(axis=0) / resolution) - margin) * resolution
    hi = (np.floor(points.max(axis=0) / resolution) + 1 + margin) * resolution
    cols, rows = np.rint((hi - lo) / resolution).astype(int)
    if rows * cols > MAX_GRID_CELLS:
        raise InvalidOptionError(f"the beams span {cols} x {rows} cells at {resolution} m, more than {MAX_GRID_CELLS}: "
                                 f"a coarser resolution, shorter rays (SensorModel.max_ray_length) or fewer scans")
    hits, misses = count_traversals(starts, ends, hit, lo, resolution, (rows, cols), engine, scan)
    # 1 / (1 + exp(-clip(hit * hits + miss * misses))) on the cells a beam reached only (a fifth
    # of a laser submap's canvas: 0.56 of the time over the whole canvas, bit for bit the same),
    # in place (fresh arrays cost page faults)
    known = (hits | misses) != 0
    p = model.hit * hits[known]
    p += model.miss * misses[known]
    np.clip(p, -model.clamp, model.clamp, out=p)
    np.negative(p, out=p)
    np.exp(p, out=p)
    p += 1.0
    np.divide(1.0, p, out=p)
    prob = np.full((rows, cols), np.nan)
    prob[known] = p
    return _trusted(prob, resolution, (float(lo[0]), float(lo[1]), 0.0))     # in (0, 1) or NaN by construction
