"""A resolution pyramid: maps coarsened by 2 per level, for coarse-to-fine matching."""

from typing import Literal

import numpy as np

from ._errors import InvalidOptionError
from ._grid import GridMap, _trusted

__all__ = ["coarsen"]


def coarsen(grid: GridMap, factor: int = 2, reduce: Literal["mean", "max", "line"] = "mean", *,
            binary: bool = False) -> GridMap:
    """``grid`` with cells ``factor`` times larger, unknown where a coarse cell has no known fine
    cell. Each coarse cell is the mean of its known fine cells; with ``reduce="max"`` their
    maximum; with ``reduce="line"`` ``min(1, factor * mean)``: a one-cell wall fills 1 / factor of
    a block it crosses, so it stays a wall at every level while a lone occupied cell fades (1/2,
    then 1/4 ...), where the mean fades both and the maximum keeps both. The corner pose is kept; a
    last partial row or column is reduced over the cells it has. ``binary``: the caller knows every
    known cell is 0 or 1 (a trinary map), which factor 2 then adds up as counts (the same numbers,
    in half the time)."""
    if reduce not in ("mean", "max", "line"):
        raise InvalidOptionError(f"reduce must be 'mean', 'max' or 'line'; got {reduce!r}")
    rows, cols = grid.shape
    r2, c2 = -(-rows // factor), -(-cols // factor)
    padded = grid.prob
    if (rows, cols) != (r2 * factor, c2 * factor):
        padded = np.full((r2 * factor, c2 * factor), np.nan)
        padded[:rows, :cols] = grid.prob
    if factor == 2 and reduce != "max":
        return _trusted((_halve_binary if binary else _halve)(padded, reduce), grid.resolution * factor,
                        grid.corner_pose)
    blocks = padded.reshape(r2, factor, c2, factor)
    unknown = np.isnan(blocks)
    known = (~unknown).sum(axis=(1, 3))
    if reduce == "max":
        reduced = np.where(unknown, -np.inf, blocks).max(axis=(1, 3))
    else:
        total = np.where(unknown, 0.0, blocks).sum(axis=(1, 3))          # np.nansum, sharing the mask
        if reduce == "line":
            reduced = np.minimum(factor * total / np.maximum(known, 1), 1.0)
        else:
            reduced = total / np.maximum(known, 1)
    prob = np.where(known > 0, reduced, np.nan)
    return _trusted(prob, grid.resolution * factor, grid.corner_pose)     # from a checked map: in [0, 1] or NaN


def _halve(prob, reduce):
    """``coarsen``'s mean or line reduction for factor 2 on a grid of even shape: the four cells of
    a block added as (a00 + a01) + (a10 + a11), which is what NumPy's sum over the block axes does
    bit for bit, in half the time (a multi-axis reduction over axes of length 2 is slow)."""
    unknown = np.isnan(prob)
    z = np.where(unknown, 0.0, prob)
    total = (z[0::2, 0::2] + z[0::2, 1::2]) + (z[1::2, 0::2] + z[1::2, 1::2])
    seen = ~unknown
    known = (seen[0::2, 0::2].astype(np.int64) + seen[0::2, 1::2]) + (seen[1::2, 0::2].astype(np.int64) + seen[1::2, 1::2])
    if reduce == "line":
        reduced = np.minimum(2 * total / np.maximum(known, 1), 1.0)
    else:
        reduced = total / np.maximum(known, 1)
    return np.where(known > 0, reduced, np.nan)


def _halve_binary(prob, reduce):
    """``_halve`` of a grid whose known cells are 0 or 1: the blocks' occupied and known cells
    counted in bytes (exact), then the same float64 arithmetic on the counts."""
    ones = (prob == 1.0).view(np.uint8)
    seen = (~np.isnan(prob)).view(np.uint8)
    total = ((ones[0::2, 0::2] + ones[0::2, 1::2]) + (ones[1::2, 0::2] + ones[1::2, 1::2])).astype(np.float64)
    known = (seen[0::2, 0::2] + seen[0::2, 1::2]) + (seen[1::2, 0::2] + seen[1::2, 1::2])
    if reduce == "line":
        reduced = np.minimum(2 * total / np.maximum(known, 1), 1.0)
    else:
        reduced = total / np.maximum(known, 1)
    return np.where(known > 0, reduced, np.nan)
