import math

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
    libm = np.array([[math.cos(t), math.sin(t)] for t in a[:, 2]])
    if not np.array_equal(np.column_stack([np.cos(a[:, 2]), np.sin(a[:, 2])]), libm):
        pytest.skip("NumPy's cosine here is not the C library's (NumPy 1.23-1.24 with AVX-512: SVML), so a batch "
                    "differs from single poses in the last bit")
    assert np.array_equal(compose(a, b), np.array([compose(p, q) for p, q in zip(a, b)]))
    assert np.array_equal(compose(a[0], b), np.array([compose(a[0], q) for q in b]))
    assert np.array_equal(inverse(a), np.array([inverse(p) for p in a]))
    assert compose(a[0], b[:0]).shape == (0, 3)



def test_edge_cases_of_single_poses():
    """A heading just above pi wraps to pi, not -pi (the modulo rounds to 2 pi there); a heading
    that is not finite gives NaN as a batch does (math's cosine would raise); a pose without three
    components is refused."""
    above = np.nextafter(np.pi, 4.0)
    assert wrap_angle(above) == np.pi and wrap_angle(np.array([above, -np.pi]))[0] == np.pi
    assert compose((0.0, 0.0, np.pi), (0.0, 0.0, above - np.pi))[2] == np.pi
    with np.errstate(invalid="ignore"):
        assert np.isnan(compose((0.0, 0.0, np.inf), (1.0, 0.0, 0.0))).all()
        assert np.isnan(inverse((0.0, 0.0, -np.inf))).all()
    for bad in (np.zeros((3, 1)), (1.0, 2.0, 3.0, 4.0), 5.0):
        with pytest.raises(InvalidPoseError, match="three components"):
            compose(bad, (1.0, 2.0, 3.0))
    with pytest.raises(InvalidPoseError, match="three components"):
        inverse((1.0, 2.0))
