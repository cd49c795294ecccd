"""End-to-end matches against synthetic ground truth."""

import numpy as np
import pytest
from conftest import rasterize, room_scene

from taichi_match import (
    GridMap,
    InvalidMapError,
    InvalidOptionError,
    InvalidPoseError,
    Matcher,
    MatchOptions,
    Status,
    match,
)
from taichi_match.scenes import corridor


@pytest.fixture(scope="module")
def corridor_map():
    return corridor()


@pytest.fixture(scope="module")
def matcher():
    return Matcher()


def test_corridor_builder_geometry(corridor_map):
    prob = corridor_map.prob
    assert prob.shape == (480, 480) and corridor_map.resolution == 0.025
    column = prob[:, 17]
    assert np.array_equal(prob, np.repeat(prob[:, :1], 480, axis=1), equal_nan=True)   # along x
    free = np.flatnonzero(column == 0.0)
    walls = np.flatnonzero(column == 1.0)
    assert len(free) * 0.025 == pytest.approx(6.0)               # 6 m of free corridor
    assert len(walls) == 4                                        # two 2-cell walls
    centres_y = corridor_map.cell_centres(walls, np.zeros_like(walls))[:, 1]
    assert np.all(np.abs(np.abs(centres_y) - 3.0) < 0.05)


@pytest.mark.parametrize("ranges, required", [((0.5, 0.5, 0.5), 99), ((1.5, 1.5, 0.38), 98)])
def test_paper_table_1_on_the_corridor(corridor_map, matcher, ranges, required):
    """The paper's protocol: 100 seeded initial poses; success is |y| < 0.025 m, |theta| < 0.045."""
    rng = np.random.default_rng(2010)
    ok = closest = 0
    for _ in range(100):
        r0 = rng.uniform(-1.0, 1.0, 3) * ranges
        res = matcher.match(corridor_map, corridor_map, r0)
        ok += abs(res.pose[1]) < 0.025 and abs(res.pose[2]) < 0.045
        # the paper: the closest pose along the corridor; the envelope discrepancy's coarse levels
        # (0.1 m cells) move x by a cell or so on the given map (measured on these trials: 98 / 99 within
        # one cell; the test allows two)
        closest += abs(res.pose[0] - r0[0]) < 0.05
    assert ok >= required
    assert closest >= required


def test_corridor_covariance_is_long_along_the_corridor(corridor_map, matcher):
    res = matcher.match(corridor_map, corridor_map, (0.3, 0.2, 0.1))
    assert res.converged
    cov = res.covariance
    assert np.all(np.isfinite(cov))
    assert cov[0, 0] >= 100 * cov[1, 1]
    assert len(res.degenerate) == 1 and abs(res.degenerate[0, 0]) > 0.99
    assert abs(res.pose[0] - 0.3) < 0.05          # along the corridor the prior keeps x near x0


@pytest.mark.parametrize("start", [(0.3, 0.2, 0.05), (0.0, 0.1, -0.03), (1.0, -0.2, 0.1)])
def test_the_free_direction_does_not_leak_into_theta_on_the_corridor(corridor_map, matcher, start):
    # The corridor on itself: theta is pinned by 12 m of walls (the errors are below 1e-3 rad).
    # The stencil's Hessian had H_xx = 0 but H_x,theta = +-1461, which tilted the free direction
    # and gave theta a standard deviation of 0.016-0.029 rad.
    res = matcher.match(corridor_map, corridor_map, start)
    assert res.accepted and abs(res.pose[2]) < 1e-3
    sd = np.sqrt(np.diag(res.calibrated_covariance))
    assert sd[0] > 10.0 and sd[1] < 0.02 and sd[2] < 0.005
    assert np.allclose(res.degenerate, [[1.0, 0.0, 0.0]], atol=1e-9)


@pytest.mark.parametrize("truth, res_b, shape_b, origin_b", [
    ((0.3, -0.2, 0.15), 0.025, (260, 340), (-4.2, -3.2)),
    ((-0.5, 0.4, -0.3), 0.025, (250, 330), (-4.0, -3.0)),
    ((0.2, 0.1, 0.05), 0.05, (130, 170), (-4.2, -3.2)),      # B coarser than A
])
def test_recovers_a_known_pose_of_a_resampled_copy(truth, res_b, shape_b, origin_b):
    a = rasterize(room_scene, (250, 330), 0.025, (-4.1, -3.1))
    b = rasterize(room_scene, shape_b, res_b, origin_b, pose_a2b=truth)
    rng = np.random.default_rng(5)
    for _ in range(4):
        r0 = np.array(truth) + rng.uniform(-1, 1, 3) * (0.2, 0.2, 0.08)
        res = match(a, b, r0)
        assert res.converged, res.message
        err = res.pose - truth
        assert np.hypot(err[0], err[1]) < 2 * 0.025 and abs(err[2]) < np.radians(1.0), (r0, res.pose)
        assert len(res.degenerate) == 0
        assert np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_result_fields(corridor_map, matcher):
    res = matcher.match(corridor_map, corridor_map, (0.1, 0.1, 0.02))
    assert res.pose.shape == (3,) and res.covariance.shape == (3, 3) and res.information.shape == (3, 3)
    assert res.x is res.pose and res.fun == res.cost and res.nit == res.iterations
    assert res.success == res.converged is True and isinstance(res.status, Status)
    assert res.cost >= res.discrepancy >= 0.0
    assert 0 < res.overlap <= np.count_nonzero(corridor_map.known)
    # the default Newton path over 3 levels: launches = 3 level-entry stencils + a trial stencil per
    # step tried (every accepted step one of them) + 1 launch counting the overlap at the pose found;
    # 25 poses per stencil launch and 1 for the overlap. The counts are deterministic on a machine
    # but follow the kernel's last bits, which Taichi compiles for the host processor: measured
    # (6, 10), every trial accepted, until 2026-12-07, and (3, 9) on the AVX-512 host of 2026-12-08
    assert 3 + res.iterations + 1 <= res.launches <= 10, (res.iterations, res.launches)
    assert res.evaluations == 25 * (res.launches - 1) + 1
    assert res.seconds > 0 and "converged" in res.message
    assert -np.pi < res.pose[2] <= np.pi


def test_match_is_deterministic(corridor_map):
    results = [Matcher().match(corridor_map, corridor_map, (0.4, -0.3, 0.2)) for _ in range(3)]
    for res in results[1:]:
        assert np.array_equal(res.pose, results[0].pose)
        assert np.array_equal(res.covariance, results[0].covariance)


def test_no_overlap_is_reported_not_raised():
    a = GridMap(np.zeros((20, 20)), 0.1)
    res = match(a, a, (100.0, 0.0, 0.0))
    assert res.status == Status.NO_OVERLAP and not res.converged
    assert np.array_equal(res.pose, [100.0, 0.0, 0.0]) and res.overlap == 0
    assert np.all(np.isfinite(res.covariance)) and len(res.degenerate) == 3
    assert "overlap" in res.message


@pytest.mark.parametrize("levels", [1, 3])
def test_iteration_budget_is_reported_not_raised(corridor_map, matcher, levels):
    res = matcher.match(corridor_map, corridor_map, (0.0, 0.8, 0.3), max_iterations=1, levels=levels)
    assert res.status == Status.MAX_ITERATIONS and not res.converged
    # one step per level, each level's single trial accepted (measured). Launches: levels=1: the
    # entry stencil, its overlap count (the first level is also the last: a separate launch, as
    # the envelope kernel does not count it), 1 trial, 1 overlap count at the end = 4;
    # levels=3: 3 entry stencils + 3 trials + 1 overlap count = 7
    assert res.iterations == levels
    assert res.launches == {1: 4, 3: 7}[levels], res.launches
    assert res.evaluations == 25 * 2 * levels + 1               # 25 per stencil, the counts' poses once
    assert np.all(np.isfinite(res.pose))


def test_all_unknown_map_gives_no_overlap():
    a = GridMap(np.zeros((10, 10)), 0.1)
    b = GridMap(np.full((10, 10), np.nan), 0.1)
    assert match(a, b, (0.0, 0.0, 0.0)).status == Status.NO_OVERLAP


def test_the_numpy_engine_runs_the_same_algorithm(corridor_map):
    r0 = (0.2, 0.3, 0.1)
    fast = Matcher().match(corridor_map, corridor_map, r0)
    slow = Matcher(engine="numpy").match(corridor_map, corridor_map, r0)
    assert abs(fast.pose[1] - slow.pose[1]) < 0.01 and abs(fast.pose[2] - slow.pose[2]) < 0.005


@pytest.mark.parametrize("pose", [(0.0, np.nan, 0.0), (0.0, 0.0), "abc", (0.0, np.inf, 0.0)])
def test_bad_initial_pose(pose):
    a = GridMap(np.zeros((5, 5)), 0.1)
    with pytest.raises(InvalidPoseError):
        match(a, a, pose)


def test_bad_maps_and_options():
    a = GridMap(np.zeros((5, 5)), 0.1)
    with pytest.raises(InvalidMapError):
        match(np.zeros((5, 5)), a, (0, 0, 0))
    with pytest.raises(InvalidOptionError, match="no_such_option"):
        match(a, a, (0, 0, 0), no_such_option=1)
    for bad in (dict(blur=-1.0), dict(prior_weight=np.nan), dict(rotation_scale=0.0),
                dict(max_iterations=-1), dict(step=0.0), dict(engine="cuda"), dict(max_iterations=2.5),
                dict(levels=0), dict(levels=9), dict(refine_iterations=-1), dict(blur_kind="box"),
                dict(optimizer="lbfgs"), dict(xtol=-1.0), dict(interpolation="cubic")):
        with pytest.raises(InvalidOptionError):
            match(a, a, (0, 0, 0), **bad)


def test_evaluation_counts_stay_small_on_a_fixed_problem(corridor_map, matcher):
    """A regression pin on a fixed start; along the corridor the answer is the closest pose to r0."""
    res = matcher.match(corridor_map, corridor_map, (0.9, -1.2, 0.3))
    assert res.converged
    assert abs(res.pose[0] - 0.9) < 0.01
    # measured, and deterministic on a machine: until 2026-12-07 the default Newton path over 3
    # levels took 9 + 5 + 2 accepted steps (coarse to fine; the finest stops with NO_DESCENT after
    # one rejected trial); launches = 3 level-entry stencils + 9 + 5 + 3 trial stencils + 1 launch
    # counting the overlap at the pose found = 21; 25 poses per stencil launch, 1 for the overlap.
    # On the AVX-512 host of 2026-12-08 (Taichi compiles for the host processor, and along the
    # corridor the path follows the kernel's last bits) 11 steps and 15 launches. More than either
    # is a change of the algorithm's path: re-measure and say why.
    assert res.iterations <= 16, res.iterations
    assert res.launches <= 3 + (9 + 5 + 3) + 1, res.launches
    assert res.evaluations == 25 * (res.launches - 1) + 1, res.evaluations


def test_calibrated_covariance_uses_the_published_model(corridor_map, matcher):
    res = matcher.match(corridor_map, corridor_map, (0.1, 0.2, 0.05), covariance_scale=4.0)
    # the README's model with the README's numbers (not the code's constants): q is e per wall
    # compared, and the covariance is 4.25 * max(q, 0.01)**0.55 * H(e)^-1 + plateau, H(e)^-1 being
    # the covariance without its scale
    assert res.residual == pytest.approx(res.discrepancy / res.evidence.walls_compared)
    assert np.allclose(res.calibrated_covariance,
                       4.25 * max(res.residual, 0.01) ** 0.55 * res.covariance / 4.0 + res.covariance_floor)
    # and H(e)^-1 is the inverse of the information where it has any: given x (the corridor's
    # direction, floored), the covariance of (y, theta) is the inverse of the information's
    # (y, theta) block (the Schur complement; the marginal is not, as the degenerate direction
    # carries a little theta: information[0, 2] != 0)
    cov = res.covariance / 4.0
    given_x = cov[1:, 1:] - np.outer(cov[1:, 0], cov[0, 1:]) / cov[0, 0]
    assert np.allclose(given_x, np.linalg.inv(res.information[1:, 1:]), rtol=1e-6, atol=0)
    # a map against itself: every wall sits at the same place in its cell, e is flat over a whole
    # cell, and the floor is an error spread evenly over it (sd 1/sqrt(12) cell) at B's centroid
    floor = res.covariance_floor
    for axis in (0, 1):
        sd = np.sqrt(floor[axis, axis])
        assert 0.2 * corridor_map.resolution < sd <= corridor_map.resolution / np.sqrt(12) + 1e-12
    # the corridor's direction keeps its huge variance
    assert len(res.degenerate) == 1 and res.calibrated_covariance[0, 0] > 1.0


def test_calibrated_covariance_of_the_bilinear_lookup_uses_its_published_model(corridor_map, matcher):
    # the README's model for interpolation="bilinear" (the README's numbers, not the code's
    # constants): 3.0 * max(q, 0.01)**0.9 * H(e)^-1 + plateau
    res = matcher.match(corridor_map, corridor_map, (0.1, 0.2, 0.05), interpolation="bilinear")
    assert res.options.interpolation == "bilinear" and res.options.blur_kind == "envelope"
    assert np.allclose(res.calibrated_covariance,
                       3.0 * max(res.residual, 0.01) ** 0.9 * res.covariance + res.covariance_floor)


def test_coarse_to_fine_levels_reach_the_same_answer(corridor_map):
    from taichi_match._pyramid import coarsen

    g = coarsen(corridor_map)
    assert g.shape == (240, 240) and g.resolution == 0.05 and g.corner_pose == corridor_map.corner_pose
    block = corridor_map.prob[118:120, 10:12]                     # a block with a wall row and free/unknown
    expected = np.nanmean(block) if np.any(~np.isnan(block)) else np.nan
    assert np.allclose(g.prob[59, 5], expected, equal_nan=True)
    rng = np.random.default_rng(8)
    # the paper's e reaches the answer from a single level; the envelope discrepancy's narrow bowl
    # (0.1 m) needs the pyramid, with either optimizer
    for options in (MatchOptions(levels=3), MatchOptions(levels=3, optimizer="bfgs"), MatchOptions.paper(levels=3),
                    MatchOptions.paper(levels=1), MatchOptions.paper(levels=1, optimizer="bfgs")):
        matcher = Matcher(options)
        for _ in range(4):
            r0 = rng.uniform(-1, 1, 3) * (1.5, 1.5, 0.38)
            res = matcher.match(corridor_map, corridor_map, r0)
            assert res.converged and abs(res.pose[1]) < 0.025 and abs(res.pose[2]) < 0.045, (options, r0, res)


def test_a_minimum_without_overlap_is_reported_as_separated():
    rng = np.random.default_rng(21)
    strip = GridMap(rng.random((1, 500)), 0.05)                 # one row: any shift in y separates
    statuses = []
    for r0 in ((0.0, 0.0, 0.0), (0.05, 0.01, 0.0), (-0.1, -0.01, 0.0), (0.0, -0.03, 0.0), (0.1, 0.03, 0.01)):
        res = match(strip, strip, r0)
        assert res.overlap > 0 or (res.status == Status.SEPARATED and not res.converged)
        statuses.append(res.status)
        # without the overlap counted, whether there is any still decides SEPARATED
        uncounted = match(strip, strip, r0, count_overlap=False)
        assert uncounted.overlap is None and uncounted.status == res.status
        assert np.array_equal(uncounted.pose, res.pose)
    assert Status.SEPARATED in statuses


@pytest.mark.parametrize("options", [MatchOptions(), MatchOptions(levels=2, interpolation="bilinear"),
                                     MatchOptions(optimizer="bfgs"), MatchOptions.paper(levels=2)])
def test_a_match_without_the_overlap_counted_is_the_same_match(options, rng):
    a = corridor()
    for _ in range(3):
        r0 = rng.uniform(-1, 1, 3) * (0.3, 0.3, 0.05)
        counted = Matcher(options).match(a, a, r0)
        uncounted = Matcher(options.replace(count_overlap=False)).match(a, a, r0)
        # the envelope's count takes a launch of its own and is left out; the paper's e counts it free
        assert counted.overlap > 0
        assert uncounted.overlap == (None if options.blur_kind == "envelope" else counted.overlap)
        for name in ("pose", "covariance", "calibrated_covariance"):
            assert np.array_equal(getattr(counted, name), getattr(uncounted, name)), name
        assert (counted.accepted, counted.status) == (uncounted.accepted, uncounted.status)


@pytest.mark.parametrize("value", [1, "yes", None, np.float64(1.0)])
def test_count_overlap_must_be_a_bool(value):
    with pytest.raises(InvalidOptionError, match="count_overlap must be True or False"):
        MatchOptions(count_overlap=value)


def test_maps_without_structure_are_reported_as_giving_no_information():
    free = GridMap(np.zeros((60, 60)), 0.05)
    res = match(free, free, (0.1, -0.05, 0.02))
    assert res.status == Status.NO_INFORMATION and not res.converged
    assert len(res.degenerate) == 3 and np.all(np.isfinite(res.covariance))
    assert np.allclose(res.pose, (0.1, -0.05, 0.02))


@pytest.mark.parametrize("far", [1.5e5, 1e7])
def test_maps_far_from_their_frames_origin_are_refused(far):
    """Cells 1e7 m from their frame's origin gave an accepted pose 5 cm off with a zero covariance:
    beyond ``MAX_FRAME_DISTANCE`` a map is refused, by the search too, with what to do."""
    from taichi_match import InvalidMapError, Matcher
    from taichi_match.scenes import room

    near = room()
    moved = GridMap(near.prob, near.resolution, (far, 0.0, 0.0))
    for a, b in ((moved, near), (near, moved)):
        with pytest.raises(InvalidMapError, match="origin"):
            Matcher().match(a, b, (0.0, 0.0, 0.0))
        with pytest.raises(InvalidMapError, match="origin"):
            Matcher().match(a, b)
    assert Matcher().match(GridMap(near.prob, near.resolution, (5e4, 0.0, 0.0)),
                           GridMap(near.prob, near.resolution, (5e4, 0.0, 0.0)), (0.05, 0.0, 0.0)).accepted
