"""A resolution pyramid: maps coarsened by 2 per level, for coarse-to-fine matching."""

from typing import Literal, Tuple

import numpy as np

from ._errors import InvalidOptionError
from ._grid import FREE, OCCUPIED, UNKNOWN, GridMap, _trusted

__all__ = ["coarsen", "halve_code"]

assert (UNKNOWN, FREE, OCCUPIED) == (0, 1, 2)         # ``halve_code``'s arithmetic on the codes


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


def halve_code(code: np.ndarray, reduce: Literal["mean", "line"] = "line") -> Tuple[np.ndarray, np.ndarray]:
    """``coarsen``'s map, factor 2, of a map given as ``_grid.trinary_code``, as codes (a map for
    ``_grid._from_code``): (uint8 codes, their float64 probabilities). A block's code counts its
    occupied and known cells, ``occupied * 5 + known`` (0: unknown), and the table gives its value
    (``_BINARY_BLOCKS``: the same numbers as ``coarsen``). In NumPy, whose loops over bytes are
    vectorised: a Taichi kernel doing the same in one pass ran scalar, 2.5-3x slower (measured on
    the mapping loop's front-end targets and scans: 0.56-0.63 -> 0.20-0.25 ms and 0.19-0.21 ->
    0.08 ms). The codes are a byte a block where its probabilities take eight: a coarse level
    prepared from them (``_prepared``) reads them through the table, and they are never made."""
    code = np.ascontiguousarray(code, dtype=np.uint8)
    h, w = code.shape
    rows, cols = -(-h // 2), -(-w // 2)
    # a cell adds 5 if occupied and 1 if known: v (2 v - 1) = 0, 1, 6 for the codes v = 0, 1, 2
    # (in bytes: 2 v - 1 wraps to 255 at v = 0, times 0); a last odd row or column adds 0s. In
    # place, few fresh arrays: on maps prepared and kept, each costs its pages' first touch
    weight = np.zeros((2 * rows, 2 * cols), dtype=np.uint8) if (h, w) != (2 * rows, 2 * cols) else np.empty_like(code)
    inner = weight[:h, :w]
    np.multiply(code, np.uint8(2), out=inner)
    inner -= np.uint8(1)
    inner *= code
    pairs = np.add(weight[0::2], weight[1::2]).view(np.uint16)     # the block's two columns in one number
    blocks = np.bitwise_and(pairs, np.uint16(0xFF), dtype=np.uint8, casting="unsafe")
    np.add(blocks, np.right_shift(pairs, np.uint16(8)), out=blocks, casting="unsafe")
    return blocks, _BINARY_BLOCKS[reduce]


def _block_sums(prob, known):
    """(sums of the known cells, known cells) of each 2 x 2 block, a last odd row or column over
    the cells it has: float64 and uint8 grids. Added as (a00 + a01) + (a10 + a11), what NumPy's sum
    over the block axes does, bit for bit, a pair of columns then a pair of rows at a time
    (measured: 3-4x faster than the one-pass Taichi kernel before it, whose loops ran scalar: a
    front-end target's level 1, 372 x 209 cells, 0.32 -> 0.08 ms)."""
    h, w = prob.shape
    rows, cols = -(-h // 2), -(-w // 2)
    values = np.zeros((2 * rows, 2 * cols))
    np.copyto(values[:h, :w], prob, where=known)                  # NaN and the padding left out
    counts = np.zeros((2 * rows, 2 * cols), dtype=np.uint8)
    counts[:h, :w] = known
    columns = values[:, 0::2] + values[:, 1::2]
    pairs = (counts[0::2] + counts[1::2]).view(np.uint16)          # the block's two columns in one number
    return columns[0::2] + columns[1::2], ((pairs & 0xFF) + (pairs >> 8)).astype(np.uint8)


def _binary_blocks(reduce):
    """``coarsen``'s value, factor 2, of a block with ``occupied`` occupied and ``known`` known
    cells (of 4) at index ``occupied * 5 + known``."""
    occupied, known = np.divmod(np.arange(25), 5)
    table = _reduced(occupied.astype(np.float64), known, 2, reduce)
    table.setflags(write=False)                 # shared by every map made from ``halve_code``'s codes
    return table


_BINARY_BLOCKS = {reduce: _binary_blocks(reduce) for reduce in ("mean", "line")}
