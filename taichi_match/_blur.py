"""Blurring a map once before matching (sec. 3.2 of the paper).

The paper applies "a standard blurring algorithm that introduces a gradient of grey from black
(occupied) to white (free) cells". We use a linear ramp in the Euclidean distance to the nearest
occupied cell::

    p'(c) = max(p(c), p(o) * max(0, 1 - d(c, o) / width))      for known c,
    p'(c) = NaN                                                 for unknown c,

where o is the occupied cell (p >= ``occupied``) nearest to c and d the distance between cell
centres in metres. Occupied cells keep their value, free cells within ``width`` of an obstacle turn
grey, unknown cells stay unknown.

Why a linear ramp: the discrepancy (eq. 6) is an L1 distance, and the L1 distance between a
monotone profile and its copy shifted by d is |d| times the profile's total variation. A ramp
keeps the slope of e against a misalignment constant up to ``width`` (the basin of convergence)
instead of the few cells of the raw map, and keeps it steep at the minimum, so the prior
K * ||r - r0|| (eq. 8) cannot drag the answer off the true alignment. A Gaussian blur of thin
walls lowers their peak and flattens the slope near the minimum. The default width is measured
in ``bench/tune_defaults.py`` (see the README).
"""

import numpy as np
from scipy import ndimage

from ._grid import GridMap

__all__ = ["blur"]


def blur(grid: GridMap, width: float, *, occupied: float = 0.5) -> GridMap:
    """Return ``grid`` with a grey ramp of ``width`` metres spread from occupied into known cells."""
    width = float(width)
    if not np.isfinite(width) or width < 0.0:
        raise ValueError(f"blur width must be a finite number of metres >= 0; got {width}")
    prob = grid.prob
    occ = np.nan_to_num(prob, nan=0.0) >= occupied
    if width == 0.0 or not occ.any():
        return grid
    dist, (ri, ci) = ndimage.distance_transform_edt(~occ, return_indices=True)
    ramp = prob[ri, ci] * np.clip(1.0 - dist * grid.resolution / width, 0.0, None)
    out = np.fmax(prob, ramp)          # fmax keeps a finite ramp over NaN, so restore unknowns:
    out[np.isnan(prob)] = np.nan
    return grid.with_prob(out)
