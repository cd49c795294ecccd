"""Property-based tests over the public API (Hypothesis, derandomised: the same examples every run)."""

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import taichi_match as tm
from taichi_match import compose, inverse

PROFILE = settings(derandomize=True, max_examples=40, deadline=None,
                   suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

finite = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)
angles = st.floats(-np.pi, np.pi, allow_nan=False)


@st.composite
def grids(draw, max_side=24, min_side=1, max_unknown=0.9):
    rows = draw(st.integers(min_side, max_side))
    cols = draw(st.integers(min_side, max_side))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    prob = rng.random((rows, cols))
    prob[rng.random((rows, cols)) < draw(st.floats(0.0, max_unknown))] = np.nan
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


def _rotation(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def _plain_eq6(a, b, pose, tie=1e-4):
    """Eq. (6) in plain float64 NumPy, independent of the package: (e, overlap, ties), ties being
    B's known cells whose centre lands within ``tie`` cells of a cell boundary of A (grid edges
    included), the only cells whose lookup float rounding may change."""
    rows, cols = np.nonzero(b.known)
    bx, by, b_yaw = b.corner_pose
    in_b = np.column_stack([(cols + 0.5) * b.resolution, (rows + 0.5) * b.resolution])
    in_b = in_b @ _rotation(b_yaw).T + [bx, by]                         # B's frame
    in_a = in_b @ _rotation(pose[2]).T + [pose[0], pose[1]]             # A's frame
    ax, ay, a_yaw = a.corner_pose
    uv = (in_a - [ax, ay]) @ _rotation(a_yaw) / a.resolution            # A's (column, row), continuous
    ties = int(np.count_nonzero(np.any(np.abs(uv - np.round(uv)) < tie, axis=1)))
    j, i = np.floor(uv).astype(np.int64).T
    inside = (i >= 0) & (i < a.shape[0]) & (j >= 0) & (j < a.shape[1])
    p_a = np.full(len(i), np.nan)
    p_a[inside] = a.prob[i[inside], j[inside]]
    on_known = ~np.isnan(p_a)
    return float(np.abs(p_a[on_known] - b.prob[rows, cols][on_known]).sum()), int(on_known.sum()), ties


MIN_OVERLAP = 8


@st.composite
def overlapping_pairs(draw):
    """Two grids and a pose r_A2B that puts a known cell of B (its centre) inside a known cell of
    A, away from that cell's edges: the maps overlap by construction."""
    a = draw(grids(min_side=4, max_unknown=0.5))
    b = draw(grids(min_side=4, max_unknown=0.5))
    rows_a, cols_a = np.nonzero(a.known)
    rows_b, cols_b = np.nonzero(b.known)
    assume(len(rows_a) > 0 and len(rows_b) > 0)
    ka = draw(st.integers(0, len(rows_a) - 1))
    kb = draw(st.integers(0, len(rows_b) - 1))
    inside = np.array([draw(st.floats(0.1, 0.9)), draw(st.floats(0.1, 0.9))])
    theta = draw(angles)
    ax, ay, a_yaw = a.corner_pose
    target = ((np.array([cols_a[ka], rows_a[ka]]) + inside) * a.resolution) @ _rotation(a_yaw).T + [ax, ay]
    bx, by, b_yaw = b.corner_pose
    anchor = ((np.array([cols_b[kb], rows_b[kb]]) + 0.5) * b.resolution) @ _rotation(b_yaw).T + [bx, by]
    t = target - _rotation(theta) @ anchor
    return a, b, (float(t[0]), float(t[1]), float(theta))


@PROFILE
@given(overlapping_pairs(), poses)
def test_moving_both_maps_together_changes_nothing(pair, motion):
    """Move both grids by the same rigid motion T: e(T A, T B, T r T^-1) = e(A, B, r) exactly, for
    pairs that overlap (by construction, and at least MIN_OVERLAP cells: the 40 examples overlap by 8
    to 163 cells, median 24; 12 of 52 generated are filtered out). Measured: both engines give
    bit-identical e and overlap before and after the motion on every example. What the tolerance
    still allows: a cell of B whose centre lies within 1e-4 cells of a cell boundary of A may floor
    either way (float32 cell coordinates in the kernel have errors of ~1e-5 cells for coordinates
    of a few hundred cells), changing the overlap by 1 and e by at most 1; plus float32 rounding of
    the sum (1e-6 per cell compared)."""
    a, b, pose = pair
    expected_e, expected_overlap, ties = _plain_eq6(a, b, pose)
    assume(expected_overlap >= MIN_OVERLAP)
    moved_a = tm.GridMap(a.prob, a.resolution, tuple(compose(motion, a.corner_pose)))
    moved_b = tm.GridMap(b.prob, b.resolution, tuple(compose(motion, b.corner_pose)))
    moved_pose = compose(compose(motion, pose), inverse(motion))
    rounding = 1e-6 * expected_overlap
    for engine in ("numpy", "taichi"):
        v, n = tm.discrepancy(a, b, [pose], engine=engine, return_overlap=True)
        w, m = tm.discrepancy(moved_a, moved_b, [moved_pose], engine=engine, return_overlap=True)
        assert abs(int(n[0]) - int(m[0])) <= ties, (engine, n, m, ties)
        assert abs(v[0] - w[0]) <= ties + rounding, (engine, v, w, ties)
        # and both are eq. (6) as plain NumPy computes it
        assert abs(int(n[0]) - expected_overlap) <= ties, (engine, n, expected_overlap, ties)
        assert abs(v[0] - expected_e) <= ties + rounding, (engine, v, expected_e, ties)


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
