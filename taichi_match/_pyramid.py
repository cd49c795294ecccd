"""A resolution pyramid: maps coarsened by 2 per level, for coarse-to-fine matching."""

from typing import Literal

import numpy as np

from ._errors import InvalidOptionError
from ._grid import FREE, OCCUPIED, UNKNOWN, GridMap, _trusted
from ._kernels import _STATE, _launch, ensure_initialized, kernel_lock

__all__ = ["coarsen", "halve_code"]


def coarsen(grid: GridMap, factor: int = 2, reduce: Literal["mean", "max", "line"] = "mean", *,
            binary: bool = False) -> GridMap:
    """``grid`` with cells ``factor`` times larger, unknown where a coarse cell has no known fine
    cell. Each coarse cell is the mean of its known fine cells; with ``reduce="max"`` their
    maximum; with ``reduce="line"`` ``min(1, factor * mean)``: a one-cell wall fills 1 / factor of
    a block it crosses, so it stays a wall at every level while a lone occupied cell fades (1/2,
    then 1/4 ...), where the mean fades both and the maximum keeps both. The corner pose is kept; a
    last partial row or column is reduced over the cells it has. ``binary``: the caller knows every
    known cell is 0 or 1 (a trinary map), which factor 2 then reduces from counts (the same numbers,
    in a fifth of the time on laser submaps)."""
    if reduce not in ("mean", "max", "line"):
        raise InvalidOptionError(f"reduce must be 'mean', 'max' or 'line'; got {reduce!r}")
    rows, cols = grid.shape
    r2, c2 = -(-rows // factor), -(-cols // factor)
    if factor == 2 and reduce != "max" and binary:
        return _trusted(_halve_binary(grid.prob, reduce), grid.resolution * factor, grid.corner_pose)
    padded = grid.prob
    if (rows, cols) != (r2 * factor, c2 * factor):
        padded = np.full((r2 * factor, c2 * factor), np.nan)
        padded[:rows, :cols] = grid.prob
    if factor == 2 and reduce != "max":
        return _trusted(_halve(padded, reduce), grid.resolution * factor, grid.corner_pose)
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
    """``_halve`` of a grid whose known cells are 0 or 1 (any shape, a last odd row or column
    reduced over the cells it has)."""
    return _halve_counts((prob == 1.0).view(np.uint8), (prob == prob).view(np.uint8), reduce)   # NaN != NaN


def halve_code(code: np.ndarray, reduce: Literal["mean", "line"] = "line") -> np.ndarray:
    """``coarsen``'s float64 probabilities, factor 2, of a map given as ``_grid.trinary_code``: each
    block's occupied and known cells counted and its value read from ``_BINARY_BLOCKS`` (the same
    numbers as ``coarsen``), in one Taichi launch (a pass over the bytes: a fifth of NumPy's time
    for the counts and the lookup, measured on laser submaps)."""
    code = np.ascontiguousarray(code, dtype=np.uint8)
    out = np.empty((-(-code.shape[0] // 2), -(-code.shape[1] // 2)))
    if out.size:
        with kernel_lock():
            ensure_initialized()
            if "halve" not in _KERNEL:
                _KERNEL["halve"] = _build_halve(_STATE["ti"])
            _launch(_KERNEL["halve"], (code, _BINARY_BLOCKS[reduce], out), None)
    return out


_KERNEL = {}


def _build_halve(ti):
    @ti.kernel
    def halve(code: ti.types.ndarray(dtype=ti.u8, ndim=2), table: ti.types.ndarray(dtype=ti.f64, ndim=1),
              out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
        # a cell adds 5 if occupied and 1 if known: v + 2 v (v - 1) for the codes v = 0, 1, 2
        ti.static_assert(UNKNOWN == 0 and FREE == 1 and OCCUPIED == 2)
        h, w = code.shape[0], code.shape[1]
        for r in range(out.shape[0]):                     # a row of blocks per work item
            i1 = ti.min(2 * r + 1, h - 1)                 # a last odd row: its own cells only
            row = ti.select(2 * r + 1 < h, 1, 0)
            for c in range(out.shape[1]):
                j1 = ti.min(2 * c + 1, w - 1)
                col = ti.select(2 * c + 1 < w, 1, 0)
                total = 0
                for i, j, keep in ti.static(((0, 0, None), (0, 1, "col"), (1, 0, "row"), (1, 1, "both"))):
                    v = ti.cast(code[2 * r if i == 0 else i1, 2 * c if j == 0 else j1], ti.i32)
                    add = v + 2 * v * (v - 1)
                    if ti.static(keep == "col"):
                        add *= col
                    elif ti.static(keep == "row"):
                        add *= row
                    elif ti.static(keep == "both"):
                        add *= row * col
                    total += add
                out[r, c] = table[total]

    return halve


def _halve_counts(ones, seen, reduce):
    """``_halve`` from a binary map's occupied and known cells (uint8 0/1 grids): each block's
    counts added in bytes, its value read from ``_BINARY_BLOCKS``, which holds ``_halve``'s float64
    arithmetic on every pair of counts (the same numbers, in a third of the time)."""
    if ones.shape[0] % 2 or ones.shape[1] % 2:           # a ring of unknown cells, in bytes
        ones, seen = (np.pad(x, ((0, ones.shape[0] % 2), (0, ones.shape[1] % 2))) for x in (ones, seen))
    code = (ones[0::2, 0::2] + ones[0::2, 1::2]) + (ones[1::2, 0::2] + ones[1::2, 1::2])
    code *= 5                                            # occupied * 5 + known: 0 .. 24
    for block in (seen[0::2, 0::2], seen[0::2, 1::2], seen[1::2, 0::2], seen[1::2, 1::2]):
        code += block
    return _BINARY_BLOCKS[reduce][code]


def _binary_blocks(reduce):
    """``_halve``'s value of a block with ``occupied`` occupied and ``known`` known cells (of 4) at
    index ``occupied * 5 + known``."""
    occupied, known = np.divmod(np.arange(25), 5)
    total = occupied.astype(np.float64)
    if reduce == "line":
        reduced = np.minimum(2 * total / np.maximum(known, 1), 1.0)
    else:
        reduced = total / np.maximum(known, 1)
    return np.where(known > 0, reduced, np.nan)


_BINARY_BLOCKS = {reduce: _binary_blocks(reduce) for reduce in ("mean", "line")}
