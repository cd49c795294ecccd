"""Synthetic scenes of the paper's experiments (sec. 5)."""

import numpy as np

from ._grid import GridMap

__all__ = ["corridor"]


def corridor(*, size=12.0, resolution=0.025, width=6.0, wall=0.05, free=0.0, occupied=1.0):
    """The paper's straight corridor along x, centred on the map frame's origin.

    A ``size`` metres square map at ``resolution``; free space for |y| < width / 2, walls
    ``wall`` metres thick just outside, unknown beyond. With the defaults: 480 x 480 cells,
    a 6 m corridor, 2-cell walls.
    """
    n = int(round(size / resolution))
    grid = GridMap(np.zeros((1, 1)), resolution, (-size / 2, -size / 2))   # only for the geometry
    y = grid.origin[1] + (np.arange(n) + 0.5) * resolution                 # row centres
    half = width / 2.0
    row = np.full(n, np.nan)
    row[np.abs(y) < half] = free
    row[(np.abs(y) >= half) & (np.abs(y) < half + wall)] = occupied
    prob = np.repeat(row[:, None], n, axis=1)
    return GridMap(prob, resolution, grid.origin)
