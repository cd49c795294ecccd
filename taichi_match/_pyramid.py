"""A resolution pyramid: maps coarsened by 2 per level, for coarse-to-fine matching."""

import numpy as np

from ._grid import GridMap

__all__ = ["coarsen"]


def coarsen(grid: GridMap, factor: int = 2) -> GridMap:
    """``grid`` with cells ``factor`` times larger: each coarse cell is the mean of its known fine
    cells, unknown where it has none. The corner pose is kept; a last partial row or column is
    averaged over the cells it has."""
    rows, cols = grid.shape
    r2, c2 = -(-rows // factor), -(-cols // factor)
    padded = np.full((r2 * factor, c2 * factor), np.nan)
    padded[:rows, :cols] = grid.prob
    blocks = padded.reshape(r2, factor, c2, factor)
    known = (~np.isnan(blocks)).sum(axis=(1, 3))
    total = np.nansum(blocks, axis=(1, 3))
    prob = np.where(known > 0, total / np.maximum(known, 1), np.nan)
    return GridMap(prob, grid.resolution * factor, grid.corner_pose)
