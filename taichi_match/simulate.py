"""A simulated robot: a floor plan made by code, laser scans cast in it, odometry that drifts.

Data with an exact truth for tests and for the README's mapping-loop demo, made on any machine
(nothing to download, no licence to carry). Apart from the core (which never imports it).

- ``floor_plan``: a building as a trinary ``GridMap`` (1 wall, 0 free): an outer wall, a ring
  corridor around a block of rooms, rooms between the ring and the outer wall, each with a door
  onto the corridor, and furniture (boxes) in the rooms; the doors and boxes follow ``seed``.
- ``cast_scan``: the ranges a 2-D laser at a pose reads in such a map, ray-marched at a quarter
  cell, with Gaussian range noise; no return (``max_range``) where nothing is hit.
- ``simulate_log``: the robot twice round the ring (a loop to close), one scan every ``step``
  metres, with odometry integrated from the true motion with the model of ``shared/logs``
  (SOURCES.md): each step's (dx, dy) in the robot frame scaled by ``1 + scale_error`` and
  perturbed by N(0, 0.02 d) forward and N(0, 0.005 d) sideways, its rotation by a bias of
  ``bias_deg_per_m`` degrees per metre plus N(0, 0.02 |dtheta| + 0.15 degrees per metre).

Frames: the plan's map frame is the world frame; poses are (x, y, theta) in it, metres and radians.
"""

from dataclasses import dataclass

import numpy as np

from ._grid import GridMap
from ._se2 import compose, inverse, wrap_angle
from .logs import LaserLog, Scan

__all__ = ["floor_plan", "cast_scan", "ring_path", "simulate_log", "SimulatedRun"]

_SIZE = (24.0, 16.0)           # the building, metres (x, y)
_WALL = 0.15                   # wall thickness, metres


def _fill(prob, resolution, x0, y0, x1, y1, value):
    """Set the cells whose centres lie in the rectangle [x0, x1] x [y0, y1] (metres)."""
    c0, c1 = int(np.ceil(x0 / resolution - 0.5)), int(np.floor(x1 / resolution - 0.5)) + 1
    r0, r1 = int(np.ceil(y0 / resolution - 0.5)), int(np.floor(y1 / resolution - 0.5)) + 1
    prob[max(r0, 0):max(r1, 0), max(c0, 0):max(c1, 0)] = value


def floor_plan(seed: int = 0, resolution: float = 0.05) -> GridMap:
    """A 24 x 16 m building (see the module docstring); origin at its lower left corner.

    Parameters
    ----------
    seed : int
        Chooses the doors' places and the furniture.
    resolution : float
        Cell side, metres.
    """
    rng = np.random.default_rng(seed)
    width, height = _SIZE
    prob = np.zeros((int(round(height / resolution)), int(round(width / resolution))))
    w = _WALL

    def wall(x0, y0, x1, y1):
        _fill(prob, resolution, x0, y0, x1, y1, 1.0)

    def free(x0, y0, x1, y1):
        _fill(prob, resolution, x0, y0, x1, y1, 0.0)

    wall(0, 0, width, w), wall(0, height - w, width, height), wall(0, 0, w, height), wall(width - w, 0, width, height)
    # the ring corridor runs between the outer rooms (2.5 m deep) and the inner block
    outer = (2.5, 2.5, width - 2.5, height - 2.5)
    inner = (5.0, 5.0, width - 5.0, height - 5.0)
    for x0, y0, x1, y1 in (outer, inner):
        wall(x0, y0, x1, y0 + w), wall(x0, y1 - w, x1, y1), wall(x0, y0, x0 + w, y1), wall(x1 - w, y0, x1, y1)
    # outer rooms: partitions every 4 m along the long sides, 4 m along the short ones; a door
    # (0.9 m) in each room's corridor wall at a random place
    for x in np.arange(4.0, width - 3.9, 4.0):
        wall(x, 0, x + w, outer[1]), wall(x, outer[3], x + w, height)
    for y in np.arange(6.0, height - 5.9, 4.0):
        wall(0, y, outer[0], y + w), wall(outer[2], y, width, y + w)
    for lo, hi in zip(np.r_[0.0, np.arange(4.0, width - 3.9, 4.0)], np.r_[np.arange(4.0, width - 3.9, 4.0), width]):
        for y_wall in (outer[1], outer[3]):
            d = rng.uniform(max(lo, outer[0]) + 0.3, min(hi, outer[2]) - 1.2)
            free(d, y_wall - 0.01, d + 0.9, y_wall + w + 0.01)
    for lo, hi in zip(np.r_[outer[1], np.arange(6.0, height - 5.9, 4.0)],
                      np.r_[np.arange(6.0, height - 5.9, 4.0), outer[3]]):
        for x_wall in (outer[0], outer[2]):
            d = rng.uniform(lo + 0.3, hi - 1.2)
            free(x_wall - 0.01, d, x_wall + w + 0.01, d + 0.9)
    # the inner block: two rooms, a door each onto the long corridors
    mid = width / 2.0
    wall(mid, inner[1], mid + w, inner[3])
    for lo, hi in ((inner[0], mid), (mid, inner[2])):
        d = rng.uniform(lo + 0.5, hi - 1.4)
        free(d, inner[1] - 0.01, d + 0.9, inner[1] + w + 0.01)
        d = rng.uniform(lo + 0.5, hi - 1.4)
        free(d, inner[3] - w - 0.01, d + 0.9, inner[3] + 0.01)
    # furniture: boxes in the rooms, kept off the corridor
    for _ in range(14):
        side = rng.integers(4)
        bw, bh = rng.uniform(0.4, 1.0, 2)
        if side < 2:
            x = rng.uniform(0.5, width - 1.5)
            y = rng.uniform(0.4, outer[1] - bh - 0.3) if side == 0 else rng.uniform(outer[3] + 0.3, height - bh - 0.4)
        else:
            x = rng.uniform(inner[0] + 0.5, inner[2] - bw - 0.5)
            y = rng.uniform(inner[1] + 0.5, inner[3] - bh - 0.5)
        wall(x, y, x + bw, y + bh)
    # pillars in the corridor's inner corners, so that no stretch of it is a featureless tube
    for x, y in ((inner[0] - 0.6, inner[1] - 0.6), (inner[2] + 0.3, inner[3] + 0.3)):
        wall(x, y, x + 0.3, y + 0.3)
    return GridMap(prob, resolution, (0.0, 0.0))


def cast_scan(world: GridMap, pose, angles, *, max_range: float = 20.0, noise: float = 0.01, rng=None):
    """Ranges (n,) read by a laser at ``pose`` along ``angles`` (laser frame) in ``world``.

    A beam stops at the first cell with p >= 0.5 (ray-marched at a quarter cell); beyond
    ``max_range`` or off the map it reads ``max_range`` (no return). ``noise``: the standard
    deviation of the Gaussian range noise, metres (``rng``: a NumPy Generator or seed).
    """
    rng = np.random.default_rng(rng)
    x, y, theta = np.asarray(pose, dtype=np.float64)
    step = world.resolution / 4.0
    d = np.arange(step, max_range, step)
    a = theta + np.asarray(angles, dtype=np.float64)
    px = x + np.outer(np.cos(a), d)
    py = y + np.outer(np.sin(a), d)
    rows, cols = world.cell_of(np.column_stack([px.ravel(), py.ravel()]))
    h, w = world.shape
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    blocked = np.zeros(rows.shape, dtype=bool)
    p = np.nan_to_num(world.prob, nan=0.0)
    blocked[inside] = p[rows[inside].astype(np.intp), cols[inside].astype(np.intp)] >= 0.5
    blocked = blocked.reshape(px.shape)
    first = np.where(blocked.any(axis=1), blocked.argmax(axis=1), -1)
    ranges = np.where(first >= 0, d[np.maximum(first, 0)], max_range)
    hit = first >= 0
    ranges[hit] = np.maximum(ranges[hit] + rng.normal(0.0, noise, int(hit.sum())), step)
    return ranges


def ring_path(laps: float = 2.0, step: float = 0.5):
    """Poses every ``step`` metres along the ring corridor's centre line of ``floor_plan``,
    counter-clockwise from its lower left corner, ``laps`` times round, heading along the path."""
    width, height = _SIZE
    c = (2.5 + 5.0) / 2.0
    corners = np.array([[c, c], [width - c, c], [width - c, height - c], [c, height - c], [c, c]])
    seg = np.diff(corners, axis=0)
    lengths = np.hypot(seg[:, 0], seg[:, 1])
    perimeter = lengths.sum()
    s = np.arange(0.0, laps * perimeter, step)
    along = np.mod(s, perimeter)
    k = np.minimum(np.searchsorted(np.cumsum(lengths), along, side="right"), len(seg) - 1)
    t = (along - np.r_[0.0, np.cumsum(lengths)][k]) / lengths[k]
    xy = corners[k] + t[:, None] * seg[k]
    heading = np.arctan2(seg[k, 1], seg[k, 0])
    return np.column_stack([xy, heading])


def _odometry(truth, rng, scale_error, bias_deg_per_m):
    odo = [truth[0].copy()]
    for a, b in zip(truth[:-1], truth[1:]):
        dx, dy, dth = compose(inverse(a), b)
        d = float(np.hypot(dx, dy))
        dx = dx * (1.0 + scale_error) + rng.normal(0.0, 0.02 * d)
        dy = dy * (1.0 + scale_error) + rng.normal(0.0, 0.005 * d)
        dth = dth + np.radians(bias_deg_per_m) * d + rng.normal(0.0, 0.02 * abs(dth) + np.radians(0.15) * d)
        odo.append(compose(odo[-1], np.array([dx, dy, dth])))
    odo = np.array(odo)
    odo[:, 2] = wrap_angle(odo[:, 2])
    return odo


@dataclass(frozen=True)
class SimulatedRun:
    """A simulated log (scans with odometry poses), its true poses (S, 3) and the world."""

    log: LaserLog
    truth: np.ndarray
    world: GridMap


def simulate_log(seed: int = 0, *, laps: float = 2.0, step: float = 0.5, beams: int = 181,
                 max_range: float = 20.0, noise: float = 0.01, scale_error: float = 0.01,
                 bias_deg_per_m: float = 0.15, resolution: float = 0.05) -> SimulatedRun:
    """The robot ``laps`` times round ``floor_plan(seed)``'s ring corridor (see the module docstring).

    Scans every ``step`` metres with ``beams`` beams over 180 degrees (-90 to +90), 1 s apart.
    """
    rng = np.random.default_rng(seed)
    world = floor_plan(seed, resolution)
    truth = ring_path(laps, step)
    truth[:, :2] += rng.normal(0.0, 0.15, truth[:, :2].shape)          # not on a rail
    truth[:, 2] = wrap_angle(truth[:, 2] + rng.normal(0.0, np.radians(3.0), len(truth)))
    odo = _odometry(truth, rng, scale_error, bias_deg_per_m)
    angles = np.linspace(-np.pi / 2, np.pi / 2, beams)
    scans = tuple(Scan(timestamp=float(k),
                       ranges=cast_scan(world, p, angles, max_range=max_range, noise=noise, rng=rng),
                       angles=angles, pose=o, max_range=max_range)
                  for k, (p, o) in enumerate(zip(truth, odo)))
    return SimulatedRun(LaserLog(scans=scans, odometry=np.column_stack([np.arange(len(odo), dtype=float), odo])),
                        truth, world)
