"""The verdict: is a matched pose trustworthy enough to go into a pose graph or a map merge?

A match can converge to a wrong pose: the optimiser only finds a minimum near the guess. The
verdict looks at what the two maps say at the pose found, with the same measure whatever
discrepancy was optimised: the occupied cells ("walls") of each map, taken at their centres,
are placed in the other map (B's by r, A's by r^-1) and sorted by where they land:

- ``walls_compared``: walls landing on known cells of the other map (both ways);
- ``wall_agreement``: the share of those within ``AGREE_CELLS`` cells of one of the other map's
  walls: the maps see the same structure there;
- ``wall_conflict``: the share landing on free space farther than ``CONFLICT_CELLS`` cells from
  any wall of the other map: one map saw an obstacle where the other saw through;
- ``uncertainty``: the largest standard deviation of the calibrated covariance outside the
  degenerate directions, as a distance in metres: of B's centroid in A, and of theta times B's
  rms radius about its centroid (how far a typical cell of B may be off).

``accepted`` = converged, at least ``MIN_WALLS`` walls compared, agreement at least
``MIN_AGREEMENT``, conflict at most ``MAX_CONFLICT`` and uncertainty at most
``MAX_UNCERTAINTY_M``. The thresholds were chosen on laser-built submaps and real-map crops with
good and bad guesses (bench/submaps.py, bench/real_maps.py seeds 0 and 1; bench/TUNING.md): a
right pose makes most walls meet walls; a wrong one, even a "converged" one, leaves many on free
space. MAX_CONFLICT went from 0.2 to 0.14 after gdc_3 crops (seed 1) slid 1.6 m along a repeated
structure with 15 % of their walls on free space; seed 2, not looked at before, then gave 99.5 %
precision and 100 % recall. MAX_UNCERTAINTY_M is absolute: on maps of 0.5 m cells or coarser
nothing is accepted.
Distances are in cells of each map, found from a distance transform of its walls (computed once
per map and kept with the prepared map).
"""

from dataclasses import dataclass

import numpy as np

from ._covariance import centroid_metric
from ._distance import far, wall_distance
from ._grid import cells
from ._se2 import inverse, transform_points

__all__ = ["Evidence", "evidence", "compare_walls", "wall_statistics", "placed_walls", "AGREE_CELLS", "CONFLICT_CELLS",
           "MIN_WALLS", "MIN_AGREEMENT", "MAX_CONFLICT", "MAX_UNCERTAINTY_M"]

AGREE_CELLS = 2.0
CONFLICT_CELLS = 4.0
MIN_WALLS = 50
MIN_AGREEMENT = 0.5
MAX_CONFLICT = 0.14
MAX_UNCERTAINTY_M = 0.05


@dataclass(frozen=True)
class Evidence:
    """What the verdict rests on (see the module docstring)."""

    walls_compared: int
    wall_agreement: float
    wall_conflict: float
    uncertainty: float

    def accepts(self, converged: bool) -> bool:
        return bool(converged and self.walls_compared >= MIN_WALLS and self.wall_agreement >= MIN_AGREEMENT
                    and self.wall_conflict <= MAX_CONFLICT and self.uncertainty <= MAX_UNCERTAINTY_M)


class WallDistance:
    """A map's walls (p >= 0.5) and, per cell, the distance in cells to the nearest one (NaN on
    unknown cells)."""

    def __init__(self, grid, distance=None, walls=None, squared=None, known=None):
        """``distance``: the distance transform of the walls (``_blur.wall_transform``'s first
        array, float64) when the caller has it, which this takes over (its unknown cells become
        NaN); or ``squared``: the squared distances within some reach and ``_distance.far``
        beyond (``near_squared_distance``: beyond a reach of more than ``CONFLICT_CELLS`` the
        verdict's counts are the same), with ``known``, nonzero on the known cells (a mask, or
        ``_grid.trinary_code``); ``walls``: (rows,
        cols) of the cells with p >= 0.5 when the caller has them. With ``squared``, ``grid``
        serves only for its geometry."""
        self.grid = grid
        rows, cols = cells(grid.prob >= 0.5) if walls is None else walls     # False on unknown (NaN) cells
        self.centres = grid.cell_centres(rows, cols)
        self._squared, self._known = squared, known
        if squared is None:
            if distance is None:
                distance = wall_distance(grid.prob >= 0.5)                   # +inf without walls
            distance[np.isnan(grid.prob)] = np.nan
        elif known is None:
            raise ValueError("squared distances need the known cells' mask")
        self.distance = distance

    def lookup(self, rows, cols):
        """Distance to the nearest wall at continuous grid coordinates (``GridMap.grid_coordinates``;
        NaN: unknown or off the map)."""
        rows, cols = np.floor(rows), np.floor(cols)
        h, w = self.grid.shape
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        out = np.full(len(rows), np.nan)
        r, c = rows[inside].astype(np.intp), cols[inside].astype(np.intp)
        if self._squared is None:
            out[inside] = self.distance[r, c]
        else:
            squared = self._squared[r, c]
            d = np.where(squared == far(self._squared), np.inf, np.sqrt(squared.astype(np.float64)))
            d[self._known[r, c] == 0] = np.nan
            out[inside] = d
        return out


def placed_walls(walls_a: WallDistance, walls_b: WallDistance, pose):
    """(B's walls in A's grid, A's walls in B's grid) at ``pose`` (r_A2B), each as continuous
    (rows, cols) coordinates (``GridMap.grid_coordinates``)."""
    return (walls_a.grid.grid_coordinates(transform_points(pose, walls_b.centres)),
            walls_b.grid.grid_coordinates(transform_points(inverse(pose), walls_a.centres)))


def compare_walls(walls_a: WallDistance, walls_b: WallDistance, placed):
    """(walls compared, agreement, conflict) for maps with walls ``walls_a``, ``walls_b`` placed in
    each other's frame by ``placed_walls`` (see the module docstring)."""
    b_in_a, a_in_b = placed
    return wall_statistics(np.concatenate([walls_a.lookup(*b_in_a), walls_b.lookup(*a_in_b)]))


def wall_statistics(d):
    """(walls compared, agreement, conflict) from the distances ``WallDistance.lookup`` found for
    the walls placed both ways (NaN: not on a known cell)."""
    d = d[~np.isnan(d)]
    n = len(d)
    return n, (float(np.mean(d <= AGREE_CELLS)) if n else 0.0), (float(np.mean(d > CONFLICT_CELLS)) if n else 1.0)


def evidence(comparison, pose, covariance, degenerate, centroid, spread) -> Evidence:
    """The evidence from ``compare_walls``'s ``comparison`` at ``pose`` and the covariance there;
    B's known cells have their centroid at ``centroid`` (B's frame) and rms distance ``spread``."""
    return Evidence(*comparison, _uncertainty(covariance, degenerate, pose[2], centroid, spread))


def _uncertainty(covariance, degenerate, theta, centroid, spread):
    """The largest standard deviation, metres, outside the degenerate directions."""
    m = centroid_metric(centroid, spread, theta)
    cov = m @ np.asarray(covariance) @ m.T
    if len(degenerate):
        dirs = np.asarray(degenerate) @ m.T
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        q, _ = np.linalg.qr(dirs.T, mode="complete")
        keep = q[:, len(degenerate):]
        cov = keep.T @ cov @ keep
    if cov.size == 0:
        return float("inf")
    return float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (cov + cov.T)).max(), 0.0)))
