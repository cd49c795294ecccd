"""The Taichi distance transforms (``_distance``) against SciPy's exact Euclidean distance transform
and a brute-force NumPy oracle of the generalised transform."""

import numpy as np
import pytest
from scipy import ndimage

from taichi_match._distance import squared_distance, wall_distance


@pytest.mark.parametrize("share", [0.001, 0.02, 0.3, 0.9])
def test_wall_distance_equals_scipy_bit_for_bit(share, rng):
    # shapes from one cell to long thin strips; the scratch buffers grow and shrink between calls
    for shape in [(1, 1), (1, 57), (63, 1), (40, 70), (130, 9), (5, 5), (200, 180)]:
        walls = rng.random(shape) < share
        walls[rng.integers(shape[0]), rng.integers(shape[1])] = True        # at least one
        np.testing.assert_array_equal(wall_distance(walls), ndimage.distance_transform_edt(~walls))


def test_grids_beyond_the_kept_scratch_size_are_exact_too(rng, monkeypatch):
    from taichi_match import _distance

    monkeypatch.setattr(_distance._Scratch, "KEEP_CELLS", 100)     # every buffer fresh
    walls = rng.random((60, 45)) < 0.05
    np.testing.assert_array_equal(wall_distance(walls), ndimage.distance_transform_edt(~walls))


def test_no_wall_is_infinitely_far():
    assert np.all(np.isinf(wall_distance(np.zeros((4, 6), dtype=bool))))


def test_generalised_transform_equals_brute_force(rng):
    for _ in range(15):
        h, w = rng.integers(1, 30, 2)
        f = np.where(rng.random((h, w)) < 0.15, rng.random((h, w)) * 30.0, np.inf)
        f[rng.integers(h), rng.integers(w)] = rng.random() * 5.0
        rows, cols = np.indices((h, w))
        brute = np.min([(rows - a) ** 2 + (cols - b) ** 2 + f[a, b] for a, b in np.argwhere(np.isfinite(f))], axis=0)
        np.testing.assert_allclose(squared_distance(f), brute, rtol=1e-12, atol=1e-9)
