"""Fusing two maps into one in A's frame, given B's pose in A (unknown respected).

Two fusions. "max" (the default) keeps obstacles: where both maps know a cell, the larger
probability wins, so an obstacle either run saw stays one, as multi-robot map mergers do for
navigation (m-explore's map_merge composes its grids by the maximum). Adding the evidence in
log-odds ("log-odds") is the occupancy-grid update for independent measurements, right for two
views of a static world but it erases walls the runs disagree on: a wall one run saw and the other
saw through fuses to about 1/2, unknown in a map_server file (on the Intel pair at the matched
pose 66 % of A's occupied cells stay occupied, all of them with "max").
"""

import numpy as np

from ._errors import InvalidOptionError, InvalidPoseError
from ._grid import GridMap
from ._se2 import as_pose, inverse, transform_points
from .io import MAX_MAP_CELLS

__all__ = ["merge_maps", "sample", "FUSIONS"]

FUSIONS = ("max", "log-odds")

_CLIP = 1e-3        # probabilities are clipped to [1e-3, 1 - 1e-3] before log-odds


def sample(grid: GridMap, points):
    """The probability of the cell each map-frame point (..., 2) falls in; NaN outside or unknown."""
    rows, cols = grid.cell_of(points)
    h, w = grid.shape
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    out = np.full(rows.shape, np.nan)
    out[inside] = grid.prob[rows[inside].astype(np.intp), cols[inside].astype(np.intp)]
    return out


def merge_maps(a: GridMap, b: GridMap, pose_a2b, *, resolution=None, fusion: str = "max") -> GridMap:
    """One map in A's frame covering both maps, B placed by ``pose_a2b`` (r_A2B).

    Each cell of the result (axis-aligned in A's frame, A's resolution unless given) takes A's and
    B's cells at its centre (nearest cell). Where both are known they are fused (``fusion``:
    "max", p = max(p_A, p_B); "log-odds", p = sigmoid(logit(p_A) + logit(p_B)), the update of an
    occupancy grid with independent measurements and a prior of 1/2; see the module docstring);
    where one is known it is kept; where neither is, the cell stays unknown.
    """
    if fusion not in FUSIONS:
        raise InvalidOptionError(f"fusion must be one of {FUSIONS}; got {fusion!r}")
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
    p_a = sample(a, centres)
    p_b = sample(b, transform_points(inverse(pose), centres))
    if fusion == "max":
        return out.with_prob(np.fmax(p_a, p_b))            # fmax: NaN (unknown) only where both are
    la = _logit(p_a)
    lb = _logit(p_b)
    fused = np.where(np.isnan(p_a), lb, np.where(np.isnan(p_b), la, la + lb))
    return out.with_prob(1.0 / (1.0 + np.exp(-fused)))


def _logit(p):
    q = np.clip(p, _CLIP, 1.0 - _CLIP)
    return np.log(q / (1.0 - q))


def _corners(grid):
    rows, cols = grid.shape
    x0, y0, yaw = grid.corner_pose
    local = np.array([[0, 0], [cols, 0], [0, rows], [cols, rows]], dtype=float) * grid.resolution
    return transform_points((x0, y0, yaw), local)
