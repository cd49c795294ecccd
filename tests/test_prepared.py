"""Prepared maps' layout for the engines: rows of known cells and the known cells' moments,
against plain NumPy oracles (cell by cell)."""

import numpy as np
import pytest

from taichi_match._grid import _trusted
from taichi_match._prepared import PreparedMap


def random_map(rng, shape, unknown_share):
    prob = rng.random(shape)
    prob[rng.random(shape) < unknown_share] = np.nan
    return _trusted(prob, 0.05, (1.5, -2.0, 0.3))       # a frame turned from the map's corner


@pytest.mark.parametrize("shape, unknown_share", [((37, 53), 0.6), ((1, 70_000), 0.99), ((70_000, 1), 0.99),
                                                  ((20, 30), 1.0), ((25, 17), 0.0)])
@pytest.mark.parametrize("evidence", ["probability", "trinary"])
def test_rows_and_moments_are_those_of_the_known_cells(shape, unknown_share, evidence):
    """``rows``: each row holding a known cell with its first and last known column + 1; the
    moments: the known cells' centroid in the map frame and rms distances, from every known
    cell's centre listed one by one (also on maps wider or taller than 65535 cells)."""
    grid = random_map(np.random.default_rng(sum(shape)), shape, unknown_share)
    prepared = PreparedMap(grid, 0.1, "envelope", 2.0, evidence)
    known = prepared.known
    want = [(r, np.flatnonzero(known[r])[0], np.flatnonzero(known[r])[-1] + 1) for r in range(shape[0])
            if known[r].any()]
    np.testing.assert_array_equal(prepared.rows, np.array(want, dtype=np.int32).reshape(-1, 3))
    assert prepared.rows.dtype == np.int32
    rows, cols = np.nonzero(known)
    if len(rows) == 0:
        assert prepared.radius == prepared.spread == grid.resolution
        return
    centres = grid.cell_centres(rows, cols)
    centroid = centres.mean(axis=0)
    np.testing.assert_allclose(prepared.centroid, centroid, rtol=1e-9, atol=1e-9)
    spread = np.sqrt(((centres - centroid) ** 2).sum(axis=1).mean())
    np.testing.assert_allclose(prepared.spread, max(spread, grid.resolution), rtol=1e-9)
    radius = np.sqrt((centres ** 2).sum(axis=1).mean())
    np.testing.assert_allclose(prepared.radius, max(radius, grid.resolution), rtol=1e-9)
