import numpy as np
import pytest

from taichi_match import GridMap, InvalidMapError, TaichiMatchError
from taichi_match._grid import cells


def test_cell_geometry_follows_the_stated_convention():
    g = GridMap(np.zeros((3, 4)), 0.5, (-1.0, 2.0))
    # cell (i=2, j=1) covers x in [-0.5, 0), y in [3, 3.5): its centre is (-0.25, 3.25)
    assert np.allclose(g.cell_centres([2], [1]), [[-0.25, 3.25]])
    rows, cols = g.cell_of([[-0.25, 3.25], [-1.0, 2.0], [-1.0001, 1.9999], [0.999, 3.499]])
    assert rows.tolist() == [2, 0, -1, 2] and cols.tolist() == [1, 0, -1, 3]
    assert g.extent == (-1.0, 1.0, 2.0, 3.5)


def test_prob_is_an_immutable_float_copy():
    src = np.zeros((2, 2), dtype=np.float32)
    g = GridMap(src, 1.0)
    src[0, 0] = 1.0
    assert g.prob[0, 0] == 0.0 and g.prob.dtype == np.float64
    with pytest.raises(ValueError):
        g.prob[0, 0] = 1.0


@pytest.mark.parametrize("prob, match", [
    (np.zeros(5), "2-D"),
    (np.zeros((2, 2, 2)), "2-D"),
    (np.zeros((0, 3)), "at least one"),
    (np.array([[0.5, np.inf]]), "infinite"),
    (np.array([[0.5, 1.5]]), r"\[0, 1\]"),
    (np.array([[-0.1, 0.5]]), r"\[0, 1\]"),
    (np.array([["a", "b"]]), "real numbers"),
    (np.array([[1 + 1j]]), "real numbers"),
    ([[0.1, None]], "real numbers"),
])
def test_bad_probabilities_raise_clear_errors(prob, match):
    with pytest.raises(InvalidMapError, match=match):
        GridMap(prob, 0.1)


@pytest.mark.parametrize("res", [0, -0.1, np.nan, np.inf, "0.1", True, None])
def test_bad_resolution(res):
    with pytest.raises(InvalidMapError, match="resolution"):
        GridMap(np.zeros((2, 2)), res)


@pytest.mark.parametrize("origin", [(0.0,), (0.0, 1.0, 2.0, 3.0), (np.nan, 0.0), (0.0, np.inf), (0.0, 0.0, np.nan),
                                    "ab", None])
def test_bad_origin(origin):
    with pytest.raises(InvalidMapError, match="origin"):
        GridMap(np.zeros((2, 2)), 0.1, origin)


def test_errors_share_the_library_root_and_are_value_errors():
    with pytest.raises(TaichiMatchError):
        GridMap(np.zeros(3), 0.1)
    with pytest.raises(ValueError):
        GridMap(np.zeros(3), 0.1)


def test_nan_is_unknown_and_bool_maps_are_accepted():
    g = GridMap(np.array([[np.nan, 1.0], [0.0, 0.25]]), 0.1)
    assert g.known.tolist() == [[False, True], [True, True]]
    assert GridMap(np.array([[True, False]]), 0.1).prob.tolist() == [[1.0, 0.0]]


def test_yaw_turns_the_grid_about_its_corner():
    g = GridMap(np.zeros((3, 4)), 0.5, (1.0, 2.0, np.pi / 2))
    assert g.origin == (1.0, 2.0) and g.yaw == np.pi / 2
    # cell (i=2, j=1): local centre (0.75, 1.25); turned by 90 degrees: (-1.25, 0.75); plus the corner
    assert np.allclose(g.cell_centres([2], [1]), [[1.0 - 1.25, 2.0 + 0.75]])
    rows, cols = g.cell_of([[1.0 - 1.25, 2.0 + 0.75]])
    assert rows.tolist() == [2] and cols.tolist() == [1]
    assert np.allclose(g.extent, (1.0 - 1.5, 1.0, 2.0, 2.0 + 2.0))
    assert GridMap(np.zeros((2, 2)), 0.1, (0.0, 0.0)).yaw == 0.0


def test_cell_of_inverts_cell_centres_for_any_yaw():
    rng = np.random.default_rng(1)
    for yaw in (0.0, 0.3, -2.0, np.pi):
        g = GridMap(np.zeros((7, 9)), 0.2, (rng.normal(), rng.normal(), yaw))
        rows, cols = np.indices(g.shape)
        r, c = g.cell_of(g.cell_centres(rows, cols))
        assert np.array_equal(r, rows) and np.array_equal(c, cols)


def test_maps_too_large_are_refused_before_allocating():
    from taichi_match._grid import MAX_CELLS

    huge = np.lib.stride_tricks.as_strided(np.zeros(1), shape=(65536, MAX_CELLS // 65536 + 1), strides=(0, 0))
    with pytest.raises(InvalidMapError, match="too large"):
        GridMap(huge, 0.05)


@pytest.mark.parametrize("shape", [(1, 1), (3, 7), (0, 5), (5, 0), (100, 37)])
def test_cells_lists_a_masks_true_cells_as_numpy_nonzero(shape):
    mask = np.random.default_rng(sum(shape)).random(shape) < 0.3
    rows, cols = cells(mask)
    expected = np.nonzero(mask)
    assert np.array_equal(rows, expected[0]) and np.array_equal(cols, expected[1])
