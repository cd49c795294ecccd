"""A resolution pyramid: maps coarsened by 2 per level, for coarse-to-fine matching."""

from typing import Literal

import numpy as np

from ._errors import InvalidOptionError
from ._grid import FREE, OCCUPIED, UNKNOWN, GridMap, _trusted
from ._launch import launch
from ._taichi import kernel_lock, kernels

__all__ = ["coarsen", "halve_code"]


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
    if factor == 2 and reduce != "max":
        total, known = _block_sums(grid.prob, grid.known)
    else:
        padded = grid.prob
        if (rows, cols) != (r2 * factor, c2 * factor):
            padded = np.full((r2 * factor, c2 * factor), np.nan)
            padded[:rows, :cols] = grid.prob
        if reduce == "max":             # fmax skips NaN: NaN only where a block knows no cell
            prob = padded[0::factor, 0::factor].copy()
            for i in range(factor):     # over the blocks' cells, a strided slice each (5x a reduction over axes)
                for j in range(factor):
                    np.fmax(prob, padded[i::factor, j::factor], out=prob)
            return _trusted(prob, grid.resolution * factor, grid.corner_pose)
        blocks = padded.reshape(r2, factor, c2, factor)
        unknown = np.isnan(blocks)
        known = (~unknown).sum(axis=(1, 3))
        total = np.where(unknown, 0.0, blocks).sum(axis=(1, 3))          # np.nansum, sharing the mask
    return _trusted(_reduced(total, known, factor, reduce), grid.resolution * factor, grid.corner_pose)


def _reduced(total, known, factor, reduce):
    """The coarse cells from their blocks' sums and known counts; NaN where a block knows nothing.
    (From a checked map: in [0, 1] or NaN.)"""
    if reduce == "line":
        reduced = np.minimum(factor * total / np.maximum(known, 1), 1.0)
    else:
        reduced = total / np.maximum(known, 1)
    return np.where(known > 0, reduced, np.nan)


def halve_code(code: np.ndarray, reduce: Literal["mean", "line"] = "line") -> np.ndarray:
    """``coarsen``'s float64 probabilities, factor 2, of a map given as ``_grid.trinary_code``: each
    block's occupied and known cells counted and its value read from ``_BINARY_BLOCKS`` (the same
    numbers as ``coarsen``), in one pass over the bytes."""
    code = np.ascontiguousarray(code, dtype=np.uint8)
    out = np.empty((-(-code.shape[0] // 2), -(-code.shape[1] // 2)))
    if out.size:
        with kernel_lock():
            launch(kernels(_build).halve_code, (code, _BINARY_BLOCKS[reduce], out), None)
    return out


def _block_sums(prob, known):
    """(sums of the known cells, known cells) of each 2 x 2 block, a last odd row or column over
    the cells it has: float64 and uint8 grids. Added as (a00 + a01) + (a10 + a11), what NumPy's sum
    over the block axes does, bit for bit, in one Taichi pass (measured: a third of NumPy's time,
    its passes over the grid and copies of it, on laser submaps' coarse levels)."""
    total = np.empty((-(-prob.shape[0] // 2), -(-prob.shape[1] // 2)))
    count = np.empty(total.shape, dtype=np.uint8)
    if total.size:
        with kernel_lock():
            launch(kernels(_build).block_sums, (np.ascontiguousarray(prob), np.ascontiguousarray(known).view(np.uint8),
                                            total, count), None)
    return total, count


class _Kernels:
    def __init__(self, halve_code, block_sums):
        self.halve_code, self.block_sums = halve_code, block_sums


def _build(ti):
    # Each kernel takes a row of blocks per work item; a block's second row and column are clamped
    # into the grid and weighed 0 when the grid has none (odd shapes), so the loops have no branches.
    blocks = ((0, 0, False, False), (0, 1, False, True), (1, 0, True, False), (1, 1, True, True))

    @ti.kernel
    def halve_code(code: ti.types.ndarray(dtype=ti.u8, ndim=2), table: ti.types.ndarray(dtype=ti.f64, ndim=1),
                   out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
        # a cell adds 5 if occupied and 1 if known: v + 2 v (v - 1) for the codes v = 0, 1, 2
        ti.static_assert(UNKNOWN == 0 and FREE == 1 and OCCUPIED == 2)
        h, w = code.shape[0], code.shape[1]
        for r in range(out.shape[0]):
            i1, row = ti.min(2 * r + 1, h - 1), ti.select(2 * r + 1 < h, 1, 0)
            for c in range(out.shape[1]):
                j1, col = ti.min(2 * c + 1, w - 1), ti.select(2 * c + 1 < w, 1, 0)
                index = 0
                for di, dj, second_row, second_col in ti.static(blocks):
                    v = ti.cast(code[2 * r if di == 0 else i1, 2 * c if dj == 0 else j1], ti.i32)
                    add = v + 2 * v * (v - 1)
                    if ti.static(second_row):
                        add *= row
                    if ti.static(second_col):
                        add *= col
                    index += add
                out[r, c] = table[index]

    @ti.kernel
    def block_sums(prob: ti.types.ndarray(dtype=ti.f64, ndim=2), known: ti.types.ndarray(dtype=ti.u8, ndim=2),
                   total: ti.types.ndarray(dtype=ti.f64, ndim=2), count: ti.types.ndarray(dtype=ti.u8, ndim=2)):
        h, w = prob.shape[0], prob.shape[1]
        for r in range(total.shape[0]):
            i1, row = ti.min(2 * r + 1, h - 1), ti.select(2 * r + 1 < h, 1, 0)
            for c in range(total.shape[1]):
                j1, col = ti.min(2 * c + 1, w - 1), ti.select(2 * c + 1 < w, 1, 0)
                z = ti.Vector([0.0, 0.0, 0.0, 0.0], dt=ti.f64)
                n = 0
                for di, dj, second_row, second_col in ti.static(blocks):
                    i, j = 2 * r if di == 0 else i1, 2 * c if dj == 0 else j1
                    k = ti.cast(known[i, j], ti.i32)
                    if ti.static(second_row):
                        k *= row
                    if ti.static(second_col):
                        k *= col
                    z[di * 2 + dj] = ti.select(k > 0, prob[i, j], 0.0)     # (a select: NaN left out)
                    n += k
                total[r, c] = (z[0] + z[1]) + (z[2] + z[3])
                count[r, c] = ti.cast(n, ti.u8)

    return _Kernels(halve_code, block_sums)


def _binary_blocks(reduce):
    """``coarsen``'s value, factor 2, of a block with ``occupied`` occupied and ``known`` known
    cells (of 4) at index ``occupied * 5 + known``."""
    occupied, known = np.divmod(np.arange(25), 5)
    return _reduced(occupied.astype(np.float64), known, 2, reduce)


_BINARY_BLOCKS = {reduce: _binary_blocks(reduce) for reduce in ("mean", "line")}
