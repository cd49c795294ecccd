import numpy as np
import pytest

from taichi_match._covariance import covariance_from_hessian


def test_regular_hessian_inverts_exactly():
    h = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 0.5], [0.0, 0.5, 2.0]])
    cov, degenerate = covariance_from_hessian(h, metric=2.0)
    assert np.allclose(cov, np.linalg.inv(h))
    assert degenerate.shape == (0, 3)


def test_scale_multiplies_the_covariance():
    h = np.diag([4.0, 2.0, 1.0])
    cov, _ = covariance_from_hessian(h, 1.0, scale=3.0)
    assert np.allclose(cov, 3.0 * np.diag([0.25, 0.5, 1.0]))


def test_corridor_like_singular_hessian_gives_huge_finite_variance_along_the_free_axis():
    h = np.diag([0.0, 4.0e6, 9.0e7])
    cov, degenerate = covariance_from_hessian(h, metric=3.0)
    assert np.all(np.isfinite(cov))
    assert cov[1, 1] == pytest.approx(0.25e-6) and cov[2, 2] == pytest.approx(1 / 9.0e7)
    assert cov[0, 0] > 1e6 * cov[1, 1]
    assert np.allclose(degenerate, [[1.0, 0.0, 0.0]])


def test_noisy_cross_terms_of_a_free_direction_do_not_leak_its_variance():
    # The paper's corridor as the stencil measured it (a match of the corridor on itself): x free
    # (H_xx = 0) but H_x,theta = -1461, which no positive semi-definite matrix allows. The free
    # direction must stay x, and y and theta keep the variances of their own 2 x 2 block.
    h = np.array([[0.0, -4.8e-5, -1461.0], [-4.8e-5, 1.717e5, -3.104e4], [-1461.0, -3.104e4, 2.26e6]])
    cov, degenerate = covariance_from_hessian(h, metric=2.5)
    block = np.linalg.inv(h[1:, 1:])
    assert np.allclose(cov[1:, 1:], block, rtol=1e-6)
    assert np.allclose(degenerate, [[1.0, 0.0, 0.0]])
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_cross_terms_within_the_bound_are_kept():
    # a positive definite H is inverted as it is, however strong its correlations
    h = np.array([[1.0, 0.99, 0.0], [0.99, 1.0, 0.0], [0.0, 0.0, 1.0]])
    cov, degenerate = covariance_from_hessian(h, metric=1.0)
    assert np.allclose(cov, np.linalg.inv(h)) and degenerate.shape == (0, 3)


def test_indefinite_hessian_flags_the_negative_direction_and_stays_positive_definite():
    h = np.array([[-5.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]])
    cov, degenerate = covariance_from_hessian(h, 1.0)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.allclose(np.abs(degenerate), [[1.0, 0.0, 0.0]])


def test_zero_and_nan_free_for_no_information():
    cov, degenerate = covariance_from_hessian(np.zeros((3, 3)), 1.0)
    assert np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 1e6)
    assert len(degenerate) == 3


def test_degenerate_direction_is_reported_in_pose_units():
    # information only along y; the (x, theta) plane is free: two degenerate directions
    h = np.diag([0.0, 1.0, 0.0])
    _, degenerate = covariance_from_hessian(h, 5.0)
    assert len(degenerate) == 2
    assert np.allclose(np.abs(degenerate) @ [0, 1, 0], 0.0)


def test_a_rotation_well_constrained_about_a_far_centroid_is_not_degenerate():
    # B's cells 1.5 m around a centroid 41 m from B's frame origin (a ROS map's corner): a Hessian
    # isotropic in the centroid's coordinates. Judged with theta scaled by the 41 m radius about the
    # origin, the rotation about the centroid looked some 3000 times weaker and was flagged degenerate.
    from taichi_match._covariance import centroid_metric

    m = centroid_metric((40.0, 10.0), 1.5, 0.2)
    h = m.T @ (1e4 * np.eye(3)) @ m                 # the Hessian in (x, y, theta)
    cov, degenerate = covariance_from_hessian(h, metric=m)
    assert degenerate.shape == (0, 3)
    assert np.allclose(cov, np.linalg.inv(h), rtol=1e-6)
    _, degenerate_old = covariance_from_hessian(h, metric=float(np.hypot(40.0, 10.0)))
    assert len(degenerate_old) == 1                 # what the origin-based scaling reported


def test_plateau_sd_is_the_widest_gap_of_the_walls_in_their_cells():
    from taichi_match import GridMap
    from taichi_match._covariance import plateau_sd

    grid = GridMap(np.zeros((10, 10)), 0.5)
    rng = np.random.default_rng(4)
    cells = rng.integers(0, 10, (200, 2)).astype(float)
    # every point at the same place in its cell (a map against itself): e is flat over a whole cell
    same = (cells + [0.3, 0.7]) * 0.5
    assert plateau_sd(*grid.grid_coordinates(same)) == pytest.approx(1 / np.sqrt(12))
    # fractions k / 8 along both axes: the widest gap is 1/8 of a cell
    even = (cells + (np.arange(200) % 8)[:, None] / 8.0 + 0.01) * 0.5
    assert plateau_sd(*grid.grid_coordinates(even)) == pytest.approx(0.125 / np.sqrt(12))
    # fractions 0, 0.1 and 0.6 along x (rows all at one fraction: the row axis decides)
    mixed = np.column_stack([cells[:3, 0] + [0.0, 0.1, 0.6], cells[:3, 1] + 0.5]) * 0.5
    assert plateau_sd(*grid.grid_coordinates(mixed)) == pytest.approx(1 / np.sqrt(12))
    cols_only = np.column_stack([cells[:3, 0] + [0.05, 0.15, 0.65], cells[:3, 1] + [0.05, 0.45, 0.85]]) * 0.5
    assert plateau_sd(*grid.grid_coordinates(cols_only)) == pytest.approx(0.5 / np.sqrt(12))
