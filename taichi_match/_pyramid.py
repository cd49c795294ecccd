"""A resolution pyramid: maps coarsened by 2 per level, for coarse-to-fine matching."""

from typing import Literal

import numpy as np

from ._grid import GridMap

__all__ = ["coarsen"]


def coarsen(grid: GridMap, factor: int = 2, reduce: Literal["mean", "max"] = "mean") -> GridMap:
    """``grid`` with cells ``factor`` times larger, unknown where a coarse cell has no known fine
    cell. Each coarse cell is the mean of its known fine cells, or with ``reduce="max"`` their
    maximum: a one-cell wall then stays a wall at every level instead of fading to grey (a 2 x 2
    block holding one wall cell has mean 1/4). The corner pose is kept; a last partial row or
    column is reduced over the cells it has."""
    rows, cols = grid.shape
    r2, c2 = -(-rows // factor), -(-cols // factor)
    padded = np.full((r2 * factor, c2 * factor), np.nan)
    padded[:rows, :cols] = grid.prob
    blocks = padded.reshape(r2, factor, c2, factor)
    known = (~np.isnan(blocks)).sum(axis=(1, 3))
    if reduce == "max":
        reduced = np.where(np.isnan(blocks), -np.inf, blocks).max(axis=(1, 3))
    elif reduce == "line":
        reduced = np.minimum(factor * np.nansum(blocks, axis=(1, 3)) / np.maximum(known, 1), 1.0)
    else:
        reduced = np.nansum(blocks, axis=(1, 3)) / np.maximum(known, 1)
    prob = np.where(known > 0, reduced, np.nan)
    return GridMap(prob, grid.resolution * factor, grid.corner_pose)
