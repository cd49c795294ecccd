import numpy as np
import pytest

from taichi_match import InvalidPoseError, compose, inverse, transform_points, wrap_angle
from taichi_match._se2 import as_pose, as_poses


def test_wrap_angle_interval_is_half_open_at_minus_pi():
    assert wrap_angle(np.pi) == pytest.approx(np.pi)
    assert wrap_angle(-np.pi) == pytest.approx(np.pi)
    assert wrap_angle(3 * np.pi / 2) == pytest.approx(-np.pi / 2)
    assert wrap_angle(0.0) == 0.0
    assert np.allclose(wrap_angle(np.array([7.0, -7.0])), [7.0 - 2 * np.pi, -7.0 + 2 * np.pi])


def test_transform_keeps_translation_at_zero_angle_and_rotates_about_b_origin():
    assert np.allclose(transform_points((1.0, 2.0, 0.0), [[0.0, 0.0], [1.0, 0.0]]), [[1.0, 2.0], [2.0, 2.0]])
    assert np.allclose(transform_points((0.0, 0.0, np.pi / 2), [[1.0, 0.0]]), [[0.0, 1.0]])
    assert np.allclose(transform_points((0.0, 0.0, np.pi), [[1.0, 2.0]]), [[-1.0, -2.0]])


def test_compose_and_inverse_against_homogeneous_matrices():
    def mat(p):
        c, s = np.cos(p[2]), np.sin(p[2])
        return np.array([[c, -s, p[0]], [s, c, p[1]], [0, 0, 1]])

    rng = np.random.default_rng(0)
    for _ in range(20):
        p, q = rng.uniform(-3, 3, 3), rng.uniform(-3, 3, 3)
        assert np.allclose(mat(compose(p, q)), mat(p) @ mat(q))
        assert np.allclose(mat(inverse(p)), np.linalg.inv(mat(p)))
        assert -np.pi < compose(p, q)[2] <= np.pi


@pytest.mark.parametrize("bad", [(1.0, 2.0), (1.0, np.nan, 0.0), "abc", [[1, 2, 3]], None])
def test_bad_pose(bad):
    with pytest.raises(InvalidPoseError):
        as_pose(bad)


@pytest.mark.parametrize("bad", [np.zeros((2, 2)), np.zeros((2, 3, 1)), [[0.0, 0.0, np.inf]], "x"])
def test_bad_poses(bad):
    with pytest.raises(InvalidPoseError):
        as_poses(bad)


def test_batches_compose_and_invert_each_pose_as_alone():
    """Batches of poses (broadcast against one pose or row by row) give each pose the bits of its
    own call (single calls are checked against the matrices in the test above)."""
    rng = np.random.default_rng(5)
    a, b = rng.uniform(-50.0, 50.0, (200, 3)), rng.uniform(-50.0, 50.0, (200, 3))
    a[:, 2] = rng.uniform(-10.0, 10.0, 200)
    assert np.array_equal(compose(a, b), np.array([compose(p, q) for p, q in zip(a, b)]))
    assert np.array_equal(compose(a[0], b), np.array([compose(a[0], q) for q in b]))
    assert np.array_equal(inverse(a), np.array([inverse(p) for p in a]))
    assert compose(a[0], b[:0]).shape == (0, 3)

