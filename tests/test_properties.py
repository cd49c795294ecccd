"""Property-based tests over the public API (Hypothesis, derandomised: the same examples every run)."""

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import taichi_match as tm
from taichi_match import compose, inverse

PROFILE = settings(derandomize=True, max_examples=40, deadline=None,
                   suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

finite = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)
angles = st.floats(-np.pi, np.pi, allow_nan=False)


@st.composite
def grids(draw, max_side=24):
    rows = draw(st.integers(1, max_side))
    cols = draw(st.integers(1, max_side))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    prob = rng.random((rows, cols))
    prob[rng.random((rows, cols)) < draw(st.floats(0.0, 0.9))] = np.nan
    resolution = draw(st.sampled_from([0.05, 0.1, 0.25]))
    origin = (draw(finite), draw(finite), draw(angles))
    return tm.GridMap(prob, resolution, origin)


poses = st.tuples(finite, finite, angles)


@PROFILE
@given(grids(), grids(), st.lists(poses, min_size=1, max_size=6))
def test_discrepancy_is_finite_non_negative_and_bounded_by_the_overlap(a, b, batch):
    values, overlap = tm.discrepancy(a, b, batch, return_overlap=True)
    assert np.all(np.isfinite(values)) and np.all(values >= 0.0)
    assert np.all(values <= overlap + 1e-6) and np.all(overlap <= b.known.sum())


@PROFILE
@given(grids())
def test_a_map_against_itself_at_identity_is_zero(a):
    values, overlap = tm.discrepancy(a, a, [(0.0, 0.0, 0.0)], return_overlap=True)
    assert values[0] == 0.0 and overlap[0] == a.known.sum()


@PROFILE
@given(grids(), grids(), poses, poses)
def test_moving_both_maps_together_changes_nothing(a, b, pose, motion):
    """Move both grids by the same rigid motion T: e(T A, T B, T r T^-1) = e(A, B, r), up to cells
    that sit on a cell boundary (float32 coordinates)."""
    moved_a = tm.GridMap(a.prob, a.resolution, tuple(compose(motion, a.corner_pose)))
    moved_b = tm.GridMap(b.prob, b.resolution, tuple(compose(motion, b.corner_pose)))
    moved_pose = compose(compose(motion, pose), inverse(motion))
    for engine in ("numpy", "taichi"):
        v, n = tm.discrepancy(a, b, [pose], engine=engine, return_overlap=True)
        w, m = tm.discrepancy(moved_a, moved_b, [moved_pose], engine=engine, return_overlap=True)
        assert abs(int(n[0]) - int(m[0])) <= 2 and abs(v[0] - w[0]) <= 2.0


@PROFILE
@given(grids(max_side=30), grids(max_side=30), poses)
def test_match_never_raises_on_valid_input_and_reports_a_finite_result(a, b, pose):
    res = tm.match(a, b, pose, max_iterations=20)
    assert np.all(np.isfinite(res.pose)) and np.all(np.isfinite(res.covariance))
    assert -np.pi < res.pose[2] <= np.pi
    assert isinstance(res.status, tm.Status)
    assert res.converged == res.status.converged
    if res.status == tm.Status.NO_OVERLAP:
        assert np.allclose(res.pose[:2], pose[:2])
