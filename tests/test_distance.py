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


def test_small_grids_column_pass_on_the_transpose_gives_the_same_bits(rng, monkeypatch):
    # grids up to SMALL_CELLS run their column pass as rows of the transposed grid (one kernel
    # variant fewer to load): the same floats as the column kernel, on grey walls and on walls at 0
    from taichi_match import _distance

    grids = []
    for h, w in [(1, 1), (1, 40), (37, 1), (23, 61), (130, 90)]:
        grids.append(np.where(rng.random((h, w)) < 0.1, -np.log(rng.random((h, w)) + 1e-3) * 7.0, np.inf))
        grids.append(np.where(rng.random((h, w)) < 0.05, 0.0, np.inf))
    small = [squared_distance(f) for f in grids]
    monkeypatch.setattr(_distance, "SMALL_CELLS", 0)
    for f, got in zip(grids, small):
        assert got.tobytes() == squared_distance(f).tobytes()


@pytest.mark.parametrize("reach", [0, 1, 4, 13, 20])
def test_near_squared_distance_is_exact_within_reach(reach, rng):
    from taichi_match._distance import far, near_squared_distance

    for shape, share in [((1, 1), 1.0), ((1, 40), 0.1), ((37, 1), 0.1), ((60, 75), 0.01), ((90, 50), 0.2)]:
        walls = rng.random(shape) < share
        got = near_squared_distance(*np.nonzero(walls), shape, reach)
        exact = np.rint(ndimage.distance_transform_edt(~walls) ** 2) if walls.any() else np.full(shape, np.inf)
        assert np.iinfo(got.dtype).max > reach * reach
        np.testing.assert_array_equal(got, np.where(exact <= reach * reach, exact, far(got)))
        rows, cols = np.nonzero(walls)
        shuffled = rng.permutation(len(rows))                # the walls in any order
        np.testing.assert_array_equal(near_squared_distance(rows[shuffled], cols[shuffled], shape, reach), got)


def test_near_weighted_envelope_is_the_largest_weighted_profile_within_reach(rng):
    from taichi_match._distance import near_weighted_envelope

    reach = 5
    profile = np.exp(-0.5 * np.arange(reach * reach + 1) / 4.0)
    for shape in [(1, 1), (23, 31), (40, 12)]:
        rows, cols = rng.integers(0, shape[0], 12), rng.integers(0, shape[1], 12)
        weights = rng.uniform(0.5, 1.0, 12)
        got = near_weighted_envelope(rows, cols, weights, shape, reach, profile)
        np.testing.assert_array_equal(got, brute_envelope(rows, cols, weights, shape, reach, profile))


def brute_envelope(rows, cols, weights, shape, reach, profile):
    r, c = np.indices(shape)
    brute = np.zeros(shape)
    for a, b, w in zip(rows, cols, weights):
        q = (r - a) ** 2 + (c - b) ** 2
        brute = np.maximum(brute, np.where(q <= reach * reach, w * profile[np.minimum(q, reach * reach)], 0.0))
    return brute


@pytest.mark.parametrize("increasing", [False, True])
def test_walls_in_runs_along_rows_stamp_as_each_wall_alone(increasing, rng):
    """Walls next to each other on a row (of one weight, or of several) stamp the same envelope
    as one by one, also with a profile that rises somewhere (where a run's nearest wall need not
    give the largest value), and the same squared distances as the exact transform."""
    from taichi_match._distance import far, near_squared_distance, near_weighted_envelope

    reach, shape = 6, (30, 41)
    profile = np.exp(-0.5 * np.arange(reach * reach + 1) / 4.0)
    if increasing:
        profile[10] = 0.9                          # above its neighbours
    rows, cols, weights = [], [], []
    for row, start, length, weight in [(3, 0, 41, 1.0), (9, 5, 7, 0.5), (9, 12, 4, 1.0), (15, 30, 2, 0.75),
                                       (22, 10, 1, 1.0), (29, 20, 15, 0.5)]:
        rows += [row] * length
        cols += list(range(start, start + length))
        weights += [weight] * length
    rows, cols, weights = np.array(rows), np.array(cols), np.array(weights)
    weights[len(weights) // 3] = 0.6               # one wall of a run of another weight
    order = rng.permutation(len(rows))             # in any order
    got = near_weighted_envelope(rows[order], cols[order], weights[order], shape, reach, profile)
    np.testing.assert_array_equal(got, brute_envelope(rows, cols, weights, shape, reach, profile))
    walls = np.zeros(shape, dtype=bool)
    walls[rows, cols] = True
    exact = np.rint(ndimage.distance_transform_edt(~walls) ** 2)
    squared = near_squared_distance(rows[order], cols[order], shape, reach)
    np.testing.assert_array_equal(squared, np.where(exact <= reach * reach, exact, far(squared)))
