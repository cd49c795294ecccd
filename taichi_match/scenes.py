"""Synthetic scenes of the paper's experiments (sec. 5) and noise for them."""

import numpy as np

from ._grid import GridMap

__all__ = ["corridor", "room", "parallel_corridors_y", "noisy_copy"]


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


def room(*, origin=(0.0, 0.0)) -> GridMap:
    """A small room for examples: 4.5 x 3.5 m of free space inside one-cell walls, a pillar and
    nothing else, on an 80 x 100 grid at 0.05 m with unknown outside; ``origin`` is the grid's.

    The pillar breaks the room's symmetry, so the room matches itself at one pose only.
    """
    prob = np.full((80, 100), np.nan)
    prob[5:75, 5:95] = 0.0                      # free inside
    prob[5:75, [5, 94]] = 1.0                   # walls
    prob[[5, 74], 5:95] = 1.0
    prob[30:50, 40:42] = 1.0                    # the pillar
    return GridMap(prob, 0.05, origin)


def parallel_corridors_y(*, width=6.0, wall=0.05):
    """The y of B in A where two copies of ``corridor`` lie side by side sharing a wall (Table 2).

    B's lower wall [-w/2 - wall, -w/2) then covers A's upper wall [w/2, w/2 + wall).
    """
    return width + wall


def noisy_copy(grid: GridMap, *, flip=0.0, drop=0.0, rng=None):
    """A copy of ``grid`` with a fraction ``flip`` of its known cells flipped (p -> 1 - p) and a
    fraction ``drop`` of them turned unknown, chosen at random by ``rng`` (a NumPy Generator)."""
    rng = np.random.default_rng(rng)
    prob = np.array(grid.prob)
    known = np.flatnonzero(~np.isnan(prob))
    picks = rng.permutation(known)
    n_flip = int(round(flip * known.size))
    n_drop = int(round(drop * known.size))
    flat = prob.reshape(-1)
    flat[picks[:n_flip]] = 1.0 - flat[picks[:n_flip]]
    flat[picks[n_flip:n_flip + n_drop]] = np.nan
    return grid.with_prob(prob)
