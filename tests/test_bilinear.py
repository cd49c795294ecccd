"""The bilinear option (beyond the paper): kernel against the NumPy oracle, the oracle's analytic
gradient against SciPy's finite differences, and matches with it."""

import numpy as np
import pytest
from scipy import differentiate, ndimage

from taichi_match import GridMap, Matcher, MatchOptions
from taichi_match._engines import make_engine
from taichi_match._prepared import PreparedMap
from taichi_match.scenes import corridor


@pytest.fixture(scope="module")
def corridor_map():
    return corridor()


def smooth_map(rng, shape, resolution, origin, unknown_block=True):
    field = ndimage.gaussian_filter(rng.standard_normal(shape), 12.0)
    prob = (field - field.min()) / (field.max() - field.min())
    if unknown_block:
        prob[:10, :30] = np.nan
    return GridMap(prob, resolution, origin)


def test_the_bilinear_kernel_equals_the_numpy_oracle(rng):
    a = smooth_map(rng, (240, 300), 0.04, (-6.0, -4.8, 0.2))
    b = smooth_map(rng, (160, 180), 0.05, (-3.0, -3.0, -0.3))
    pa, pb = PreparedMap(a, 0.0), PreparedMap(b, 0.0)
    poses = np.array([(0.1, 0.2, 0.05), (-0.3, 0.1, -0.2), (5.0, 0.0, 1.0), (60.0, 0.0, 0.0)])
    e, n, g = make_engine("taichi", pa, pb).bilinear(poses)
    e_ref, n_ref, g_ref = make_engine("numpy", pa, pb).bilinear(poses)
    assert np.allclose(e, e_ref, rtol=1e-5, atol=1e-3)
    assert np.abs(n - n_ref).max() <= 2 and n[-1] == 0
    assert np.allclose(g, g_ref, rtol=1e-4, atol=1e-3 * np.abs(g_ref).max())


def test_the_analytic_gradient_is_the_derivative_of_the_value(rng):
    # B well inside a fully known A: e is continuous (kinks only), so finite differences apply
    a = smooth_map(rng, (200, 200), 0.05, (-5.0, -5.0, 0.1), unknown_block=False)
    b = smooth_map(rng, (60, 70), 0.05, (-1.5, -1.75, -0.2), unknown_block=False)
    oracle = make_engine("numpy", PreparedMap(a, 0.0), PreparedMap(b, 0.0))
    for pose in [(0.1, 0.2, 0.05), (-0.3, 0.1, -0.2)]:
        _, _, grad = oracle.bilinear(np.array([pose]))

        def e(u):                                      # (3, ...) as SciPy passes it
            u = np.asarray(u)
            return oracle.bilinear(np.moveaxis(u, 0, -1).reshape(-1, 3))[0].reshape(u.shape[1:])

        ref = differentiate.jacobian(e, np.array(pose), initial_step=1e-5, order=2, maxiter=1).df
        assert np.allclose(grad[0], ref, rtol=1e-3, atol=1e-3 * np.abs(ref).max())


@pytest.mark.parametrize("optimizer", ["newton", "bfgs"])
def test_bilinear_matches_find_the_corridor(corridor_map, optimizer):
    matcher = Matcher(MatchOptions.paper(interpolation="bilinear", optimizer=optimizer))
    rng = np.random.default_rng(4)
    for _ in range(4):
        r0 = rng.uniform(-1, 1, 3) * (0.5, 0.5, 0.3)
        res = matcher.match(corridor_map, corridor_map, r0)
        assert abs(res.pose[1]) < 0.025 and abs(res.pose[2]) < 0.045, (r0, res)
        assert res.overlap > 0 and np.all(np.isfinite(res.covariance))
        assert res.degenerate.shape[0] >= 1 and abs(res.degenerate[0][0]) > 0.99     # x, along the corridor
