import numpy as np
import pytest

from taichi_match import GridMap
from taichi_match._blur import blur


def test_ramp_from_an_occupied_cell_into_free_cells():
    g = GridMap(np.array([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]), 0.1)
    out = blur(g, 0.5).prob[0]
    assert np.allclose(out, [1.0, 0.8, 0.6, 0.4, 0.2, 0.0, 0.0])


def test_unknown_stays_unknown_and_known_values_never_drop():
    prob = np.array([[0.9, np.nan, 0.1, 0.45, 0.0],
                     [0.0, 0.0, np.nan, 0.0, 0.3]])
    out = blur(GridMap(prob, 1.0), 2.5).prob
    assert np.array_equal(np.isnan(out), np.isnan(prob))
    known = ~np.isnan(prob)
    assert np.all(out[known] >= prob[known])
    # cell (0, 2) is 2 m from the occupied cell (0, 0) of p = 0.9: 0.9 * (1 - 2 / 2.5)
    assert out[0, 2] == pytest.approx(0.9 * (1 - 2 / 2.5))
    # cell (1, 1) is sqrt(2) m away
    assert out[1, 1] == pytest.approx(0.9 * (1 - np.sqrt(2) / 2.5))
    assert out[1, 4] == pytest.approx(0.3)      # 4.1 m away: keeps its own value


def test_zero_width_and_maps_without_obstacles_are_unchanged():
    g = GridMap(np.array([[1.0, 0.0]]), 0.1)
    assert blur(g, 0.0) is g
    free = GridMap(np.array([[0.2, np.nan]]), 0.1)
    assert np.array_equal(blur(free, 1.0).prob, free.prob, equal_nan=True)


@pytest.mark.parametrize("width", [-1.0, np.nan, np.inf])
def test_bad_width(width):
    with pytest.raises(ValueError, match="blur width"):
        blur(GridMap(np.zeros((2, 2)), 0.1), width)
