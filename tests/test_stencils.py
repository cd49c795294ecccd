"""Eq. (10)-(12): the stencil formulas on known functions, and on the real cost against SciPy."""

import numpy as np
import pytest
from scipy import differentiate, ndimage

from taichi_match import GridMap, Matcher, MatchOptions
from taichi_match._cost import gradient_from_stencil, gradient_stencil, hessian_from_stencil, hessian_stencil
from taichi_match._engines import make_engine


def poly(r):
    x, y, t = np.moveaxis(np.asarray(r, dtype=float), -1, 0)
    return 1.5 * x**3 - 2 * y**2 + 0.5 * t**4 + 3 * x * y - 0.7 * x * t + 1.1 * y * t + x


def poly_grad(r):
    x, y, t = r
    return np.array([4.5 * x**2 + 3 * y - 0.7 * t + 1, -4 * y + 3 * x + 1.1 * t, 2 * t**3 - 0.7 * x + 1.1 * y])


def poly_hess(r):
    x, y, t = r
    return np.array([[9 * x, 3, -0.7], [3, -4, 1.1], [-0.7, 1.1, 6 * t**2]])


def test_stencil_formulas_are_exact_on_low_order_polynomials():
    rng = np.random.default_rng(3)
    for _ in range(10):
        r = rng.uniform(-2, 2, 3)
        steps = rng.uniform(0.01, 0.2, 3)
        g = gradient_from_stencil(poly(gradient_stencil(r, steps)), steps)
        h = hessian_from_stencil(poly(hessian_stencil(r, steps)), steps)
        assert np.allclose(g, poly_grad(r), rtol=1e-9, atol=1e-9)
        # the 4-point mixed difference has an O(eps^2) error on t^4-free terms only: exact here
        assert np.allclose(h, poly_hess(r), rtol=1e-7, atol=1e-6)


def test_stencil_layout():
    s = hessian_stencil(np.zeros(3), (0.1, 0.2, 0.3))
    assert s.shape == (25, 3)
    assert np.array_equal(s[:13], gradient_stencil(np.zeros(3), (0.1, 0.2, 0.3)))
    assert len({tuple(p) for p in s}) == 25                        # 25 distinct poses


@pytest.fixture(scope="module")
def smooth_cost():
    """A smooth random occupancy field, so that e is smooth at the scale of the stencil."""
    rng = np.random.default_rng(7)
    field = ndimage.gaussian_filter(rng.standard_normal((240, 300)), 12.0)
    prob = (field - field.min()) / (field.max() - field.min())
    prob[:10, :30] = np.nan
    grid = GridMap(prob, 0.04, (-6.0, -4.8))
    prepared = Matcher(MatchOptions.paper()).prepare(grid, blur=0.0)
    return make_engine("taichi", prepared, prepared), make_engine("numpy", prepared, prepared)


@pytest.mark.parametrize("pose", [(0.2, 0.3, 0.05), (-0.4, -0.6, -0.1), (0.0, 0.9, 0.2)])
def test_kernel_stencil_gradient_and_hessian_against_scipy_on_the_numpy_oracle(smooth_cost, pose):
    taichi_engine, numpy_engine = smooth_cost
    steps = np.array([0.08, 0.08, 0.02])
    g = gradient_from_stencil(taichi_engine(gradient_stencil(pose, steps))[0], steps)
    h = hessian_from_stencil(taichi_engine(hessian_stencil(pose, steps))[0], steps)

    def e(u):        # u in units of the steps, shape (3, ...) as SciPy passes it
        poses = np.moveaxis(np.asarray(u), 0, -1) * steps + pose
        return numpy_engine(poses.reshape(-1, 3))[0].reshape(poses.shape[:-1])

    ref_g = differentiate.jacobian(e, np.zeros(3), initial_step=1.0, order=4, maxiter=1).df / steps
    ref_h = differentiate.hessian(e, np.zeros(3), initial_step=1.0, order=4, maxiter=1).ddf / np.outer(steps, steps)
    assert np.allclose(g, ref_g, rtol=0.05, atol=0.02 * np.abs(ref_g).max())
    assert np.allclose(h, ref_h, rtol=0.1, atol=0.05 * np.abs(ref_h).max())


@pytest.mark.parametrize("a_yaw", [0.0, 0.3])
def test_the_stencil_launch_equals_the_numpy_oracle_at_the_25_poses(rng, a_yaw):
    # A large B with unknown cells and a yawed origin, A yawed or not, poses partly off A
    from conftest import random_map

    from taichi_match._prepared import PreparedMap

    a = random_map(rng, (260, 300), 0.05, (-7.0, -6.0, a_yaw))
    b = random_map(rng, (250, 280), 0.05, (-6.5, -6.0, 0.2))
    pa, pb = PreparedMap(a, 0.0), PreparedMap(b, 0.0)
    taichi_engine, numpy_engine = make_engine("taichi", pa, pb), make_engine("numpy", pa, pb)
    for pose in [(0.1, -0.2, 0.05), (3.0, 2.5, -0.4), (0.0, 0.0, 0.0)]:
        steps = np.array([a.resolution, a.resolution, 0.01])
        values, counts = taichi_engine(hessian_stencil(pose, steps), "first")
        ref_values, ref_counts = numpy_engine(hessian_stencil(pose, steps))
        # float32 row sums against float64, and fast-math rounding that moves a few of B's cells
        # across a cell boundary of A (each changes e by at most 1 on these maps; ~40k cells)
        assert np.allclose(values, ref_values, rtol=1e-5, atol=3.0), np.abs(values - ref_values).max()
        assert abs(counts[0] - ref_counts[0]) <= 3
