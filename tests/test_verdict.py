"""The verdict (``_verdict``): true pairs accepted, wrong poses and unrelated maps refused, the
evidence independent of how the pose was found, and hand values of the evidence."""

import numpy as np
import pytest
from conftest import rasterize, room_scene

import taichi_match as tm
from taichi_match import GridMap, Matcher, MatchOptions
from taichi_match._verdict import (
    AGREE_CELLS,
    CONFLICT_CELLS,
    Evidence,
    WallDistance,
    compare_walls,
    evidence,
    placed_walls,
)

TRUTH = (0.15, -0.1, 0.05)
RES = 0.05
# The verdict's thresholds as the README documents them ("accepted: can this pose go into a pose
# graph?"): at least 50 walls compared, agreement >= 0.5, conflict <= 0.14, uncertainty <= 0.05 m.
# Written out here, not imported from _verdict, so that the tests hold the code to the documented rule.
MIN_WALLS, MIN_AGREEMENT, MAX_CONFLICT, MAX_UNCERTAINTY_M = 50, 0.5, 0.14, 0.05


@pytest.fixture(scope="module")
def room_pair():
    """The pair of tests/test_cli.py: B sampled from the room at r_A2B = TRUTH."""
    a = rasterize(room_scene, (130, 170), RES, (-4.1, -3.1))
    b = rasterize(room_scene, (120, 160), RES, (-4.0, -3.0), pose_a2b=TRUTH)
    return a, b


def pose_error(pose):
    """(metres, degrees) from TRUTH."""
    return float(np.hypot(pose[0] - TRUTH[0], pose[1] - TRUTH[1])), \
        float(abs(np.degrees(tm.wrap_angle(pose[2] - TRUTH[2]))))


def random_walls(seed, shape=(120, 160), resolution=RES, origin=(-4.0, -3.0), segments=12, frame=True):
    """A free map of the room's size with one-cell wall segments at random (and, with ``frame``,
    walls all around, as the room has): a structure unrelated to the room."""
    rng = np.random.default_rng(seed)
    p = np.zeros(shape)
    for _ in range(segments):
        length = rng.integers(10, 60)
        if rng.random() < 0.5:
            r, c = rng.integers(0, shape[0]), rng.integers(0, shape[1] - 20)
            p[r, c:c + length] = 1.0
        else:
            r, c = rng.integers(0, shape[0] - 20), rng.integers(0, shape[1])
            p[r:r + length, c] = 1.0
    if frame:
        p[0, :] = p[-1, :] = p[:, 0] = p[:, -1] = 1.0
    return GridMap(p, resolution, origin)


def accepted_by_thresholds(ev):
    """The README's rule with the README's numbers: what ``Evidence.accepts(True)`` must say."""
    return (ev.walls_compared >= MIN_WALLS and ev.wall_agreement >= MIN_AGREEMENT
            and ev.wall_conflict <= MAX_CONFLICT and ev.uncertainty <= MAX_UNCERTAINTY_M)


def wall_evidence(walls_a, walls_b, pose, covariance=None, degenerate=None, centroid=(0.0, 0.0), spread=1.0):
    """``_verdict.evidence`` at ``pose``; by default with a covariance of zero (uncertainty 0), so
    that only the walls decide."""
    covariance = np.zeros((3, 3)) if covariance is None else covariance
    degenerate = np.zeros((0, 3)) if degenerate is None else degenerate
    pose = np.asarray(pose, dtype=np.float64)
    return evidence(compare_walls(walls_a, walls_b, placed_walls(walls_a, walls_b, pose)), pose, covariance,
                    degenerate, centroid, spread)


# ---------------------------------------------------------------------------------------------
# 1. A true pair


@pytest.mark.parametrize("guess", [(0.0, 0.0, 0.0), (0.35, -0.25, 0.1), TRUTH])
def test_a_true_pair_is_accepted(room_pair, guess):
    a, b = room_pair
    res = tm.match(a, b, guess)
    metres, degrees = pose_error(res.pose)
    assert metres <= 2 * RES and degrees <= 0.5, res
    assert res.converged and res.accepted, (res, res.evidence)
    ev = res.evidence
    assert isinstance(ev, Evidence)
    assert ev.wall_agreement >= 0.8 and ev.wall_conflict <= 0.05 and ev.walls_compared > 50, ev
    assert 0.0 < ev.uncertainty <= MAX_UNCERTAINTY_M
    assert res.accepted == ev.accepts(res.converged) == accepted_by_thresholds(ev)


def test_the_verdict_follows_the_match_the_other_way_round(room_pair):
    a, b = room_pair
    res = tm.match(b, a, tm.inverse(TRUTH) + np.array([0.1, 0.1, -0.05]))
    assert res.accepted and np.allclose(res.pose, tm.inverse(TRUTH), atol=[2 * RES, 2 * RES, np.radians(0.5)])


# ---------------------------------------------------------------------------------------------
# 2. False pairs


BAD_GUESSES = [(2.0, 0.0, np.radians(30)), (-2.0, 1.0, -np.radians(30)), (0.0, 2.0, np.radians(30)),
               (2.15, -0.1, 0.05), (0.15, 1.9, 0.05), (0.15, -0.1, 0.05 + np.radians(30)),
               (-1.85, -2.1, np.radians(-25))]


def test_wrong_poses_from_far_guesses_are_refused(room_pair):
    a, b = room_pair
    wrong = 0
    for guess in BAD_GUESSES:
        res = tm.match(a, b, guess)
        metres, degrees = pose_error(res.pose)
        if metres > 0.1 or degrees > 1.0:
            wrong += 1
            assert not res.accepted, (guess, res, res.evidence)
        assert res.accepted == (res.converged and accepted_by_thresholds(res.evidence))
    assert wrong >= 3, "the far guesses should lead the matcher astray, or this test proves nothing"


@pytest.mark.parametrize("frame", [True, False])
@pytest.mark.parametrize("seed", range(3))
def test_unrelated_maps_are_refused(room_pair, seed, frame):
    a, b = room_pair
    other = random_walls(seed, frame=frame)
    for first, second in ((a, other), (other, b)):
        for guess in ((0.0, 0.0, 0.0), TRUTH):
            res = tm.match(first, second, guess)
            assert not res.accepted, (seed, guess, res, res.evidence)


def test_a_map_without_walls_is_refused(room_pair):
    a, b = room_pair
    free = GridMap(np.zeros((120, 160)), RES, (-4.0, -3.0))
    for first, second in ((a, free), (free, b)):
        for guess in ((0.0, 0.0, 0.0), TRUTH):
            res = tm.match(first, second, guess)
            assert not res.accepted, (guess, res)
            # no wall of the free map to meet: any wall compared is a conflict
            assert res.evidence.wall_agreement == 0.0 and res.evidence.wall_conflict == 1.0, res.evidence
            if second is free:      # the room as A: B (free) is pushed off its walls, nothing compared
                assert res.evidence.walls_compared < MIN_WALLS, (res, res.evidence)
    # at the identity, where the free map covers the room, every wall of the room meets free space
    room_walls = np.count_nonzero(np.nan_to_num(a.prob) >= 0.5)
    ev = wall_evidence(WallDistance(a), WallDistance(free), (0.0, 0.0, 0.0))
    assert ev.wall_conflict == 1.0 and ev.wall_agreement == 0.0 and 1000 < ev.walls_compared <= room_walls
    assert not ev.accepts(True)


def test_a_map_with_no_known_cells_of_the_other_in_reach_is_refused(room_pair):
    a, b = room_pair
    res = tm.match(a, b, (1e6, 0.0, 0.0))
    assert res.status == tm.Status.NO_OVERLAP and not res.converged and not res.accepted
    assert res.evidence.walls_compared == 0 and res.evidence.wall_conflict == 1.0


@pytest.mark.parametrize("options", [dict(max_iterations=0), dict(max_iterations=0, levels=1),
                                     dict(max_iterations=1, xtol=0.01)])
def test_results_that_did_not_converge_are_refused(room_pair, options):
    a, b = room_pair
    guess = np.array(TRUTH) + np.array([0.15, 0.1, 0.05])
    res = tm.match(a, b, guess, **options)
    assert not res.converged and res.status == tm.Status.MAX_ITERATIONS
    assert not res.accepted and res.evidence.accepts(False) is False
    assert res.evidence.accepts(True) == accepted_by_thresholds(res.evidence)
    if options == dict(max_iterations=1, xtol=0.01):
        # one Newton step on the coarsest level cannot meet its tolerance, the finer levels reach
        # the truth, and what the maps say there passes: only the missing convergence refuses the
        # result
        metres, degrees = pose_error(res.pose)
        assert metres <= 2 * RES and degrees <= 0.5
        assert res.evidence.wall_agreement >= 0.95 and res.evidence.accepts(True), res.evidence


def test_the_paper_optimiser_out_of_iterations_is_refused(room_pair):
    a, b = room_pair
    res = Matcher(MatchOptions.paper(max_iterations=0, levels=1)).match(a, b, np.array(TRUTH) + [0.3, 0.0, 0.1])
    assert not res.converged and not res.accepted


# ---------------------------------------------------------------------------------------------
# 3. The evidence does not depend on how the pose was found


def test_the_evidence_is_the_same_whatever_discrepancy_was_optimised(room_pair):
    a, b = room_pair
    default = Matcher().match(a, b, TRUTH)
    paper = Matcher(MatchOptions.paper()).match(a, b, TRUTH)
    bfgs = Matcher(optimizer="bfgs", levels=1).match(a, b, TRUTH)
    for res in (default, paper, bfgs):
        assert res.accepted, res
    for res in (paper, bfgs):
        compared = default.evidence.walls_compared
        assert abs(res.evidence.walls_compared - compared) <= 0.02 * compared
        assert res.evidence.wall_agreement == pytest.approx(default.evidence.wall_agreement, abs=0.02)
        assert res.evidence.wall_conflict == pytest.approx(default.evidence.wall_conflict, abs=0.02)
    # at one and the same pose the wall evidence is identical, from either matcher's prepared maps
    pose = np.array(TRUTH) + [0.2, -0.1, 0.02]
    cov = np.eye(3) * 1e-6
    found = []
    for matcher in (Matcher(), Matcher(MatchOptions.paper())):
        walls_a, walls_b = matcher.prepare(a).wall_distance, matcher.prepare(b).wall_distance
        found.append(wall_evidence(walls_a, walls_b, pose, cov))
    assert found[0] == found[1]


def test_agreement_drops_and_conflict_rises_away_from_the_truth(room_pair):
    a, b = room_pair
    walls_a, walls_b = WallDistance(a), WallDistance(b)
    at_truth = wall_evidence(walls_a, walls_b, TRUTH)
    assert at_truth.wall_agreement >= 0.95 and at_truth.wall_conflict <= 0.01 and at_truth.accepts(True)
    previous = at_truth
    for dx in (0.15, 0.3, 0.6):              # 3, 6, 12 cells off
        ev = wall_evidence(walls_a, walls_b, np.array(TRUTH) + [dx, 0.0, 0.0])
        assert ev.wall_agreement < previous.wall_agreement and ev.wall_conflict >= previous.wall_conflict, ev
        previous = ev
    assert previous.wall_agreement < at_truth.wall_agreement - 0.3 and previous.wall_conflict > 0.3, previous
    assert not previous.accepts(True)
    previous = at_truth
    for degrees in (5, 10, 20):
        ev = wall_evidence(walls_a, walls_b, np.array(TRUTH) + [0.0, 0.0, np.radians(degrees)])
        assert ev.wall_agreement < previous.wall_agreement and ev.wall_conflict > previous.wall_conflict, ev
        previous = ev
    assert previous.wall_agreement < 0.4 and previous.wall_conflict > 0.5 and not previous.accepts(True)


# ---------------------------------------------------------------------------------------------
# 4. Hand values


def one_wall_map(unknown_rows=0):
    """1 m cells, 21 rows x 30 columns, free but for a one-cell wall along row 10 (30 walls);
    the first ``unknown_rows`` rows unknown."""
    p = np.zeros((21, 30))
    p[10, :] = 1.0
    p[:unknown_rows, :] = np.nan
    return GridMap(p, 1.0)


@pytest.mark.parametrize("dy, compared, agreement, conflict", [
    (0, 60, 1.0, 0.0),          # walls exactly onto walls
    (1, 60, 1.0, 0.0),          # 1 cell off: within AGREE_CELLS
    (2, 60, 1.0, 0.0),
    (3, 60, 0.0, 0.0),          # 3 cells: neither agreeing nor conflicting
    (4, 60, 0.0, 0.0),          # CONFLICT_CELLS is "farther than"
    (5, 60, 0.0, 1.0),          # 5 cells into the other's free space: all conflict
    (-7, 60, 0.0, 1.0),
    (11, 0, 0.0, 1.0),          # B's wall lands off A's grid, A's off B's: nothing compared
])
def test_hand_values_of_the_evidence(dy, compared, agreement, conflict):
    grid = one_wall_map()
    walls = WallDistance(grid)
    ev = wall_evidence(walls, walls, (0.0, float(dy), 0.0))
    assert (ev.walls_compared, ev.wall_agreement, ev.wall_conflict, ev.uncertainty) == \
        (compared, agreement, conflict, 0.0)
    assert ev.accepts(True) == (dy in (0, 1, 2))          # 60 walls >= MIN_WALLS
    assert not ev.accepts(False)
    assert AGREE_CELLS == 2.0 and CONFLICT_CELLS == 4.0


@pytest.mark.parametrize("walls, agreement, conflict, uncertainty, accepted", [
    (50, 0.5, 0.14, 0.05, True),             # every threshold met exactly: accepted
    (49, 0.5, 0.14, 0.05, False),            # one wall too few
    (50, 0.499, 0.14, 0.05, False),          # agreement just short
    (50, 0.5, 0.141, 0.05, False),           # conflict just over
    (50, 0.5, 0.14, 0.0501, False),          # uncertainty just over
    (5000, 1.0, 0.0, 0.0, True),
    (5000, 1.0, 0.0, np.inf, False),
])
def test_the_documented_thresholds_at_their_edges(walls, agreement, conflict, uncertainty, accepted):
    ev = Evidence(walls, agreement, conflict, uncertainty)
    assert ev.accepts(True) is accepted and ev.accepts(False) is False


def test_walls_on_unknown_cells_are_not_compared():
    a = WallDistance(one_wall_map(unknown_rows=3))        # A's rows 0-2 unknown
    b = WallDistance(one_wall_map())
    # B's wall (row 10) lands on A's row 1 (unknown): not compared; A's wall on B's row 19: free,
    # 9 cells from B's wall
    ev = wall_evidence(a, b, (0.0, -9.0, 0.0))
    assert (ev.walls_compared, ev.wall_agreement, ev.wall_conflict) == (30, 0.0, 1.0)
    assert not ev.accepts(True)                           # and 30 < MIN_WALLS
    # a map without walls: its cells are infinitely far from a wall
    free = WallDistance(GridMap(np.zeros((5, 5)), 1.0))
    assert len(free.centres) == 0 and np.all(np.isinf(free.distance))
    ev = wall_evidence(WallDistance(one_wall_map()), free, (0.0, 8.0, 0.0))
    assert (ev.walls_compared, ev.wall_conflict) == (5, 1.0)


def test_a_rotated_pair_and_a_grid_with_yaw():
    grid = one_wall_map()
    # the same cells stored turned by a quarter turn: as a map, the same wall
    turned = GridMap(np.rot90(grid.prob, k=-1), 1.0, (0.0, 21.0, -np.pi / 2))
    np.testing.assert_allclose(np.sort(turned.cell_centres(*np.nonzero(turned.prob == 1.0)), axis=0),
                               np.sort(grid.cell_centres(*np.nonzero(grid.prob == 1.0)), axis=0), atol=1e-9)
    ev = wall_evidence(WallDistance(grid), WallDistance(turned), (0.0, 0.0, 0.0))
    assert (ev.walls_compared, ev.wall_agreement, ev.wall_conflict) == (60, 1.0, 0.0)
    # a half turn about the wall's middle (15, 10.5) maps the wall onto itself
    ev = wall_evidence(WallDistance(grid), WallDistance(grid), (30.0, 21.0, np.pi))
    assert (ev.walls_compared, ev.wall_agreement, ev.wall_conflict) == (60, 1.0, 0.0)


def test_the_uncertainty_leaves_out_degenerate_directions():
    walls = WallDistance(one_wall_map())
    cov = np.diag([0.01**2, 3.0**2, 0.004**2])            # y badly determined, theta 0.004 rad
    spread = 5.0                                          # theta as metres: 0.004 * 5 = 0.02
    ev = wall_evidence(walls, walls, (0.0, 0.0, 0.0), cov, spread=spread)
    assert ev.uncertainty == pytest.approx(3.0) and not ev.accepts(True)
    ev = wall_evidence(walls, walls, (0.0, 0.0, 0.0), cov, np.array([[0.0, 1.0, 0.0]]), spread=spread)
    assert ev.uncertainty == pytest.approx(0.02) and ev.accepts(True)
    ev = wall_evidence(walls, walls, (0.0, 0.0, 0.0), cov, np.eye(3), spread=spread)
    assert ev.uncertainty == np.inf and not ev.accepts(True)


def test_a_rotation_moves_the_centroid_of_b():
    # theta known to 1 mrad; B's cells centred 10 m out along B's x axis, spread 2 m about that:
    # the centroid moves by 10 mrad-metres along y, a typical cell by 2 more, together
    # sd^2 = (1e-3)^2 (10^2 + 2^2)
    walls = WallDistance(one_wall_map())
    cov = np.diag([0.0, 0.0, 1e-3**2])
    ev = wall_evidence(walls, walls, (0.0, 0.0, 0.0), cov, centroid=(10.0, 0.0), spread=2.0)
    assert ev.uncertainty == pytest.approx(1e-3 * np.sqrt(104.0))
    # the same with the pose turned a quarter turn: the centroid's motion turns with it
    ev = wall_evidence(walls, walls, (0.0, 0.0, np.pi / 2), cov, centroid=(10.0, 0.0), spread=2.0)
    assert ev.uncertainty == pytest.approx(1e-3 * np.sqrt(104.0))
    # a centroid at B's origin: only the spread counts
    ev = wall_evidence(walls, walls, (0.0, 0.0, 0.0), cov, centroid=(0.0, 0.0), spread=2.0)
    assert ev.uncertainty == pytest.approx(2e-3)
