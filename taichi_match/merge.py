"""Fusing two maps into one in A's frame, given B's pose in A (unknown respected).

Two fusions. "max" (the default) keeps obstacles: where both maps know a cell, the larger
probability wins, so an obstacle either run saw stays one, as multi-robot map mergers do for
navigation (m-explore's map_merge composes its grids by the maximum). Adding the evidence in
log-odds ("log-odds") is the occupancy-grid update for independent measurements, right for two
views of a static world but it erases walls the runs disagree on: a wall one run saw and the other
saw through fuses to about 1/2, unknown in a map_server file (on the Intel pair at the matched
pose 66 % of A's occupied cells stay occupied, all of them with "max").
"""

import math

import numpy as np
import numpy.typing as npt

from ._errors import InvalidMapError, InvalidOptionError, InvalidPoseError, shown
from ._grid import GridMap
from ._se2 import as_pose, inverse, transform_points
from .io import MAX_MAP_CELLS

__all__ = ["merge_maps", "sample", "FUSIONS"]

FUSIONS = ("max", "log-odds")

_CLIP = 1e-3        # probabilities are clipped to [1e-3, 1 - 1e-3] before log-odds
# ``fusion="max"`` samples each map at least once per cell of its own within each merged cell: at
# most this many samples in all (a few seconds; a map a thousand times finer than the other took
# many minutes)
MAX_SAMPLES = 2**28


def sample(grid: GridMap, points: npt.ArrayLike) -> np.ndarray:
    """The probability of the cell each map-frame point (..., 2) falls in; NaN outside or unknown.

    Parameters
    ----------
    grid : GridMap
        The map.
    points : array_like, shape (..., 2)
        (x, y) in the map's frame, metres.

    Returns
    -------
    numpy.ndarray, shape (...)
        ``grid.prob`` at the cell each point falls in (eq. 3, floor), NaN outside the grid.

    Examples
    --------
    >>> import numpy as np
    >>> from taichi_match import GridMap
    >>> from taichi_match.merge import sample
    >>> grid = GridMap([[0.0, 1.0], [np.nan, 0.5]], 1.0)
    >>> sample(grid, [[1.5, 0.2], [0.5, 1.5], [1.9, 1.9], [-0.1, 0.5]]).tolist()
    [1.0, nan, 0.5, nan]
    """
    rows, cols = grid.cell_of(points)
    h, w = grid.shape
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    out = np.full(rows.shape, np.nan)
    out[inside] = grid.prob[rows[inside].astype(np.intp), cols[inside].astype(np.intp)]
    return out


def merge_maps(a: GridMap, b: GridMap, pose_a2b: npt.ArrayLike, *, resolution: float | None = None,
               fusion: str = "max") -> GridMap:
    """One map in A's frame covering both maps, B placed by ``pose_a2b`` (r_A2B).

    Each cell of the result is axis-aligned in A's frame, at A's resolution unless given. With
    ``fusion`` "max" it takes the largest known probability of A's and B's cells within it (a
    lattice of points over the cell, one per cell of the finer map: a wall thinner than a merged
    cell stays a wall); with "log-odds" A's and B's cells at its centre, p = sigmoid(logit(p_A) +
    logit(p_B)) where both are known, the update of an occupancy grid with independent
    measurements and a prior of 1/2 (see the module docstring). Where one map is known it is
    kept (with "log-odds", clipped to [0.001, 0.999]); where neither is, the cell stays unknown.

    Parameters
    ----------
    a, b : GridMap
        The two maps, each in its own frame.
    pose_a2b : array_like, shape (3,)
        r_A2B = (x, y, theta): B's frame in A's, metres and radians (a match's ``pose``).
    resolution : float, optional
        Cell side of the result, metres; default A's.
    fusion : {"max", "log-odds"}
        How a cell known in both maps is fused.

    Returns
    -------
    GridMap
        Axis-aligned in A's frame (yaw 0), its cell boundaries on A's where A is axis-aligned,
        covering the bounding box of both maps.

    Raises
    ------
    InvalidMapError
        If ``a`` or ``b`` is not a ``GridMap``.
    InvalidOptionError
        For an unknown ``fusion`` or a ``resolution`` that is not a finite number > 0.
    InvalidPoseError
        If ``pose_a2b`` is not three finite numbers, or puts B so far away that the result would
        exceed ``MAX_MAP_CELLS`` cells.

    Examples
    --------
    A sees free space everywhere; B, placed 1 m further along x, sees a wall across its row 10,
    also where A saw free space:

    >>> import numpy as np
    >>> from taichi_match import GridMap
    >>> from taichi_match.merge import merge_maps
    >>> a = GridMap(np.zeros((20, 20)), 0.1)
    >>> prob_b = np.zeros((20, 20))
    >>> prob_b[10, :] = 1.0
    >>> b = GridMap(prob_b, 0.1)
    >>> merged = merge_maps(a, b, (1.0, 0.0, 0.0))
    >>> merged.shape, merged.extent
    ((20, 30), (0.0, 3.0, 0.0, 2.0))
    >>> merged.prob[10, ::5].tolist()           # A only, overlap, B only: the wall is kept
    [0.0, 0.0, 1.0, 1.0, 1.0, 1.0]
    >>> merge_maps(a, b, (1.0, 0.0, 0.0), fusion="log-odds").prob[10, ::5].round(3).tolist()
    [0.001, 0.001, 0.5, 0.5, 0.999, 0.999]
    """
    if fusion not in FUSIONS:
        raise InvalidOptionError(f"fusion must be one of {FUSIONS}; got {fusion!r}")
    for name, grid in (("a", a), ("b", b)):
        if not isinstance(grid, GridMap):
            raise InvalidMapError(f"{name} must be a GridMap; got {type(grid).__name__}")
    if resolution is not None and not (isinstance(resolution, (int, float)) and math.isfinite(resolution)
                                       and resolution > 0):
        raise InvalidOptionError(f"resolution must be a finite number of metres > 0 or None; got {shown(resolution)}")
    pose = as_pose(pose_a2b, "pose_a2b")
    res = a.resolution if resolution is None else float(resolution)
    corners_b = _corners(b)
    corners = np.vstack([_corners(a), transform_points(pose, corners_b)])
    anchor = np.array(a.origin)                  # keep A's cell boundaries where A is axis-aligned
    lo = anchor + np.floor((corners.min(axis=0) - anchor) / res + 1e-9) * res
    hi = anchor + np.ceil((corners.max(axis=0) - anchor) / res - 1e-9) * res
    size = (hi - lo) / res
    if not np.all(np.isfinite(size)) or np.prod(np.maximum(np.rint(size), 1.0)) > MAX_MAP_CELLS:
        raise InvalidPoseError(f"the merged map would span {hi[0] - lo[0]:.4g} x {hi[1] - lo[1]:.4g} m, "
                               f"more than {MAX_MAP_CELLS} cells of {res} m: is the pose {tuple(pose)} right?")
    cols, rows = np.maximum(np.rint(size).astype(int), 1)
    out = GridMap(np.zeros((rows, cols)), res, (lo[0], lo[1]))
    centres = out.cell_centres()
    if fusion == "max":
        # each map's cells within a merged cell, at least one sample per cell of the finer map:
        # a wall thinner than a merged cell stays a wall
        for name, grid in (("A", a), ("B", b)):
            k = math.ceil(res / grid.resolution - 1e-9)
            if not k * k * out.prob.size <= MAX_SAMPLES:
                raise InvalidOptionError(f"map {name}'s cells ({grid.resolution:g} m) are {k:.3g} times finer than "
                                         f"the merged map's ({res:g} m): {k:.3g}^2 samples in each of "
                                         f"{out.prob.size} merged cells is more than {MAX_SAMPLES}; merge at a "
                                         f"finer resolution or coarsen map {name} first")
        fused = _max_over_cell(a, centres, res, (0.0, 0.0, 0.0))
        np.fmax(fused, _max_over_cell(b, centres, res, pose), out=fused)   # fmax: NaN only where both are
        return out.with_prob(fused)
    p_a = sample(a, centres)
    p_b = sample(b, transform_points(inverse(pose), centres))
    la = _logit(p_a)
    lb = _logit(p_b)
    fused = np.where(np.isnan(p_a), lb, np.where(np.isnan(p_b), la, la + lb))
    return out.with_prob(1.0 / (1.0 + np.exp(-fused)))


def _max_over_cell(grid, centres, res, pose):
    """The largest known probability of ``grid`` (placed by ``pose`` in the merged frame) over a
    k x k lattice of points spread over each merged cell, k enough for one per cell of ``grid``;
    NaN where none is known."""
    k = max(int(math.ceil(res / grid.resolution - 1e-9)), 1)
    back = inverse(pose)
    out = None
    for i in range(k):
        for j in range(k):
            offset = (np.array([j, i]) + 0.5) / k * res - 0.5 * res
            p = sample(grid, transform_points(back, centres + offset))
            out = p if out is None else np.fmax(out, p, out=out)
    return out


def _logit(p):
    q = np.clip(p, _CLIP, 1.0 - _CLIP)
    return np.log(q / (1.0 - q))


def _corners(grid):
    rows, cols = grid.shape
    x0, y0, yaw = grid.corner_pose
    local = np.array([[0, 0], [cols, 0], [0, rows], [cols, rows]], dtype=float) * grid.resolution
    return transform_points((x0, y0, yaw), local)
