"""The Taichi kernel against the plain-NumPy oracle of eq. (6), and the oracle against hand values."""

import numpy as np
import pytest
from conftest import random_map

from taichi_match import GridMap, InvalidMapError, InvalidPoseError, discrepancy


def test_oracle_and_kernel_on_hand_computed_cases():
    a = GridMap(np.array([[0.0, 1.0]]), 1.0)                 # x in [0, 1): 0, x in [1, 2): 1
    b = GridMap(np.array([[1.0, np.nan, 0.5]]), 1.0)         # centres x = 0.5, (unknown), 2.5
    poses = [(0, 0, 0),            # 0.5 -> A cell 0: |0 - 1| = 1;   2.5 -> outside
             (1, 0, 0),            # 1.5 -> A cell 1: |1 - 1| = 0;   3.5 -> outside
             (-2, 0, 0),           # -1.5 outside;                   0.5 -> cell 0: |0 - .5|
             (2, 1, np.pi),        # (0.5, .5) -> (1.5, .5) cell 1: 0; (2.5, .5) -> (-.5, .5) out
             (0, 5, 0)]            # everything outside A
    expected = [1.0, 0.0, 0.5, 0.0, 0.0]
    expected_overlap = [1, 1, 1, 1, 0]
    for engine in ("numpy", "taichi"):
        values, overlap = discrepancy(a, b, poses, engine=engine, return_overlap=True)
        assert np.allclose(values, expected), engine
        assert overlap.tolist() == expected_overlap, engine


CASES = [  # shape_a, res_a, origin_a, shape_b, res_b, origin_b
    ((40, 50), 0.1, (-2.0, -2.5), (40, 50), 0.1, (-2.0, -2.5)),
    ((37, 91), 0.05, (0.3, -1.0), (64, 23), 0.05, (-0.6, 0.2)),
    ((120, 80), 0.025, (-1.0, -1.5), (50, 70), 0.04, (-0.8, -0.9)),
    ((7, 300), 0.2, (-30.0, 1.0), (90, 12), 0.13, (-5.0, -4.0)),
    ((1, 1), 1.0, (0.0, 0.0), (3, 2), 0.5, (0.0, 0.0)),
    ((50, 60), 0.05, (-1.0, 0.5, 0.7), (40, 30), 0.05, (0.2, -0.3, -2.1)),       # ROS origins with yaw
    ((33, 47), 0.1, (2.0, 1.0, np.pi), (25, 25), 0.07, (0.0, 0.0, 0.0)),
]


def boundary_ties(a, b, poses, tol=1e-4):
    """Per pose, the known cells of B whose centre lands within ``tol`` cells of a cell boundary
    of A: there float32 and float64 may legitimately floor differently."""
    rows, cols = np.nonzero(b.known)
    centres = b.cell_centres(rows, cols)
    ties = []
    ca, sa = np.cos(a.yaw), np.sin(a.yaw)

    def near(w):
        return np.abs(w - np.round(w)) < tol

    for x, y, t in poses:
        px = np.cos(t) * centres[:, 0] - np.sin(t) * centres[:, 1] + x - a.origin[0]
        py = np.sin(t) * centres[:, 0] + np.cos(t) * centres[:, 1] + y - a.origin[1]
        u = (ca * px + sa * py) / a.resolution
        v = (-sa * px + ca * py) / a.resolution
        ties.append(int(np.count_nonzero(near(u) | near(v))))
    return np.array(ties)


@pytest.mark.parametrize("case", CASES)
def test_kernel_matches_numpy_oracle_on_random_maps(case, rng):
    shape_a, res_a, origin_a, shape_b, res_b, origin_b = case
    a = random_map(rng, shape_a, res_a, origin_a)
    b = random_map(rng, shape_b, res_b, origin_b, unknown=0.3)
    extent = max(shape_a) * res_a
    poses = np.column_stack([rng.uniform(-0.5, 0.5, 64) * extent, rng.uniform(-0.5, 0.5, 64) * extent,
                             rng.uniform(-np.pi, np.pi, 64)])
    poses[0] = 0.0          # commensurate grids at identity put many centres exactly on boundaries
    v_ti, n_ti = discrepancy(a, b, poses, return_overlap=True)
    v_np, n_np = discrepancy(a, b, poses, engine="numpy", return_overlap=True)
    # float32 coordinates may move a point across a cell boundary: a couple of cells per pose,
    # plus the cells that sit exactly on a boundary
    allowed = 2 + boundary_ties(a, b, poses)
    assert np.all(np.abs(n_ti - n_np) <= allowed)
    assert np.all(np.abs(v_ti - v_np) <= allowed)
    assert np.mean(np.abs(v_ti - v_np) < 1e-3) > 0.8       # and mostly identical up to float32 sums
    assert n_np.max() > 0


def test_a_grid_turned_by_its_yaw_is_the_same_map(rng):
    """The same cells stored transposed with yaw = 90 degrees give the same discrepancy."""
    prob = rng.random((30, 40))
    prob[rng.random(prob.shape) < 0.2] = np.nan
    a = GridMap(prob, 0.1, (0.0, 0.0))
    a_turned = GridMap(prob[:, ::-1].T, 0.1, (40 * 0.1, 0.0, np.pi / 2))
    def cells(g):               # (x, y, p) of every known cell, in a canonical order
        xyp = np.column_stack([g.cell_centres()[g.known], g.prob[g.known]])
        return xyp[np.lexsort(np.round(xyp[:, :2].T, 6))]

    assert np.allclose(cells(a), cells(a_turned))
    b = random_map(rng, (25, 35), 0.08, (-0.5, 0.3))
    poses = np.column_stack([rng.uniform(-1, 2, 20), rng.uniform(-1, 2, 20), rng.uniform(-3, 3, 20)])
    for engine in ("numpy", "taichi"):
        v, n = discrepancy(a, b, poses, engine=engine, return_overlap=True)
        v_t, n_t = discrepancy(a_turned, b, poses, engine=engine, return_overlap=True)
        assert np.all(np.abs(n - n_t) <= 2) and np.all(np.abs(v - v_t) <= 2.0)
        assert np.mean(np.abs(v - v_t) < 1e-3) > 0.8
        w, m = discrepancy(b, a, poses, engine=engine, return_overlap=True)
        w_t, m_t = discrepancy(b, a_turned, poses, engine=engine, return_overlap=True)
        assert np.all(np.abs(m - m_t) <= 2) and np.mean(np.abs(w - w_t) < 1e-3) > 0.8


def test_identical_maps_give_zero_at_identity(rng):
    for res, origin in ((0.05, (0.0, 0.0)), (0.1, (-3.3, 7.1)), (0.025, (-6.0, -6.0))):
        a = random_map(rng, (60, 45), res, origin, unknown=0.25)
        values, overlap = discrepancy(a, a, [(0.0, 0.0, 0.0)], return_overlap=True)
        assert values[0] == 0.0
        assert overlap[0] == a.known.sum()


def test_far_away_poses_give_zero_without_overflow(rng):
    a = random_map(rng, (40, 40), 0.05, (0.0, 0.0))
    poses = [(1e12, 0.0, 0.0), (0.0, -3e9, 1.0), (2e7, 2e7, -2.0), (2.5, 2.5, 0.0), (0.0, 0.0, 0.0)]
    for engine in ("taichi", "numpy"):
        values, overlap = discrepancy(a, a, poses, engine=engine, return_overlap=True)
        assert values[:4].tolist() == [0.0] * 4 and overlap[:4].tolist() == [0] * 4
        assert values[4] == 0.0 and overlap[4] == a.known.sum()


def test_discrepancy_is_deterministic(rng):
    a = random_map(rng, (200, 150), 0.05, (-5, -4))
    poses = rng.uniform(-1, 1, (25, 3))
    first = discrepancy(a, a, poses)
    assert all(np.array_equal(first, discrepancy(a, a, poses)) for _ in range(3))


def test_bad_arguments():
    a = GridMap(np.zeros((3, 3)), 0.1)
    with pytest.raises(InvalidMapError, match="GridMap"):
        discrepancy(np.zeros((3, 3)), a, [(0, 0, 0)])
    with pytest.raises(InvalidPoseError):
        discrepancy(a, a, [(0, 0)])
    with pytest.raises(InvalidPoseError):
        discrepancy(a, a, [(0, np.nan, 0)])
    with pytest.raises(ValueError, match="engine"):
        discrepancy(a, a, [(0, 0, 0)], engine="gpu")
