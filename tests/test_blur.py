import numpy as np
import pytest

from taichi_match import GridMap
from taichi_match._blur import blur


def brute_force_normalised_gaussian(prob, sigma_cells, truncate=3.0):
    """Normalised convolution over known cells, written out cell by cell."""
    radius = int(truncate * sigma_cells + 0.5)
    rows, cols = prob.shape
    out = np.full(prob.shape, np.nan)
    for i in range(rows):
        for j in range(cols):
            if np.isnan(prob[i, j]):
                continue
            num = den = 0.0
            for di in range(-radius, radius + 1):
                for dj in range(-radius, radius + 1):
                    k, m = i + di, j + dj
                    if 0 <= k < rows and 0 <= m < cols and not np.isnan(prob[k, m]):
                        w = np.exp(-(di * di + dj * dj) / (2 * sigma_cells**2))
                        num += w * prob[k, m]
                        den += w
            out[i, j] = num / den
    return out


def test_gaussian_is_a_normalised_convolution_over_known_cells():
    rng = np.random.default_rng(0)
    prob = rng.random((14, 17))
    prob[rng.random(prob.shape) < 0.3] = np.nan
    out = blur(GridMap(prob, 0.1), 0.2, kind="gaussian").prob         # sigma = 2 cells
    assert np.allclose(out, brute_force_normalised_gaussian(prob, 2.0), equal_nan=True, atol=1e-12)


def test_gaussian_turns_a_stray_occupied_cell_into_a_faint_smudge():
    prob = np.zeros((41, 41))
    prob[20, 20] = 1.0
    out = blur(GridMap(prob, 0.05), 0.2, kind="gaussian").prob         # sigma = 4 cells
    assert out.max() == pytest.approx(1 / (2 * np.pi * 16), rel=0.05)
    wall = np.zeros((41, 41))
    wall[:, 20] = 1.0                                                   # a wall keeps more
    assert blur(GridMap(wall, 0.05), 0.2, kind="gaussian").prob.max() > 5 * out.max()


def test_ramp_from_an_occupied_cell_into_free_cells():
    g = GridMap(np.array([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]), 0.1)
    out = blur(g, 0.5, kind="ramp").prob[0]
    assert np.allclose(out, [1.0, 0.8, 0.6, 0.4, 0.2, 0.0, 0.0])


def test_ramp_unknown_stays_unknown_and_known_values_never_drop():
    prob = np.array([[0.9, np.nan, 0.1, 0.45, 0.0],
                     [0.0, 0.0, np.nan, 0.0, 0.3]])
    out = blur(GridMap(prob, 1.0), 2.5, kind="ramp").prob
    assert np.array_equal(np.isnan(out), np.isnan(prob))
    known = ~np.isnan(prob)
    assert np.all(out[known] >= prob[known])
    # cell (0, 2) is 2 m from the occupied cell (0, 0) of p = 0.9: 0.9 * (1 - 2 / 2.5)
    assert out[0, 2] == pytest.approx(0.9 * (1 - 2 / 2.5))
    # cell (1, 1) is sqrt(2) m away
    assert out[1, 1] == pytest.approx(0.9 * (1 - np.sqrt(2) / 2.5))
    assert out[1, 4] == pytest.approx(0.3)      # 4.1 m away: keeps its own value


@pytest.mark.parametrize("kind", ["gaussian", "ramp"])
def test_zero_width_and_unknown_cells(kind):
    g = GridMap(np.array([[1.0, 0.0], [np.nan, 0.2]]), 0.1)
    assert blur(g, 0.0, kind=kind) is g
    out = blur(g, 0.3, kind=kind).prob
    assert np.isnan(out[1, 0]) and np.all(np.isfinite(out[[0, 0, 1], [0, 1, 1]]))
    assert np.all((out[~np.isnan(out)] >= 0) & (out[~np.isnan(out)] <= 1))


@pytest.mark.parametrize("width", [-1.0, np.nan, np.inf])
def test_bad_width(width):
    with pytest.raises(ValueError, match="blur width"):
        blur(GridMap(np.zeros((2, 2)), 0.1), width)


def test_bad_kind():
    with pytest.raises(ValueError, match="blur kind"):
        blur(GridMap(np.zeros((2, 2)), 0.1), 0.1, kind="box")


@pytest.mark.parametrize("shape, sigma", [((480, 480), 20.0), ((37, 501), 7.3), ((5, 3), 20.0), ((60, 60), 2.0)])
def test_the_fft_gaussian_equals_scipys(rng, shape, sigma):
    from scipy import ndimage

    from taichi_match._blur import gaussian_filter

    stack = rng.random((2,) + shape)
    expected = np.stack([ndimage.gaussian_filter(a, sigma, mode="constant", truncate=3.0) for a in stack])
    assert np.allclose(gaussian_filter(stack, sigma), expected, rtol=0, atol=1e-12)
