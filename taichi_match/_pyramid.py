"""A resolution pyramid: maps coarsened by 2 per level, for coarse-to-fine matching."""

from typing import Literal

import numpy as np

from ._errors import InvalidOptionError
from ._grid import GridMap

__all__ = ["coarsen"]


def coarsen(grid: GridMap, factor: int = 2, reduce: Literal["mean", "max", "line"] = "mean") -> GridMap:
    """``grid`` with cells ``factor`` times larger, unknown where a coarse cell has no known fine
    cell. Each coarse cell is the mean of its known fine cells; with ``reduce="max"`` their
    maximum; with ``reduce="line"`` ``min(1, factor * mean)``: a one-cell wall fills 1 / factor of
    a block it crosses, so it stays a wall at every level while a lone occupied cell fades (1/2,
    then 1/4 ...), where the mean fades both and the maximum keeps both. The corner pose is kept; a
    last partial row or column is reduced over the cells it has."""
    if reduce not in ("mean", "max", "line"):
        raise InvalidOptionError(f"reduce must be 'mean', 'max' or 'line'; got {reduce!r}")
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
