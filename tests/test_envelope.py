"""The envelope discrepancy (``_envelope``): the Taichi kernel against the NumPy oracle, both
against hand values, its symmetry and its minimum at the truth; the line-reduced pyramid, the
trinary evidence and the options that go with it."""

import dataclasses
import warnings

import numpy as np
import pytest
from conftest import rasterize, room_scene

import taichi_match as tm
from taichi_match import (
    GridMap,
    InvalidOptionError,
    Matcher,
    MatchOptions,
    PreparedMap,
    inverse,
    make_engine,
    transform_points,
)
from taichi_match._envelope import SERIAL_BELOW, EnvelopeEngine, NumpyEnvelope
from taichi_match._grid import trinary, trinary_code
from taichi_match._pyramid import coarsen, halve_code

TRUTH = (0.15, -0.1, 0.05)


@pytest.fixture(scope="module")
def room_pair():
    """The pair of tests/test_cli.py: B sampled from the room at r_A2B = TRUTH."""
    a = rasterize(room_scene, (130, 170), 0.05, (-4.1, -3.1))
    b = rasterize(room_scene, (120, 160), 0.05, (-4.0, -3.0), pose_a2b=TRUTH)
    return a, b


def sparse_walls_map(rng, shape, resolution, origin, walls=0.08, unknown=0.2):
    """Grey probabilities: a fraction ``walls`` of the cells occupied (p in [0.5, 1]), the rest
    in [0, 0.5), a fraction ``unknown`` NaN."""
    prob = np.where(rng.random(shape) < walls, rng.uniform(0.5, 1.0, shape), rng.uniform(0.0, 0.5, shape))
    prob[rng.random(shape) < unknown] = np.nan
    return GridMap(prob, resolution, origin)


def boundary_ties(dst, src, pose, cells, tol=2e-4):
    """How many of ``src``'s ``cells`` (rows, cols), moved into ``dst``'s frame by ``pose``
    (r_dst2src, which maps src's points into dst's frame), land within ``tol`` cells of one of
    ``dst``'s cell boundaries, on or next to the grid: there the kernel's float32 and the
    oracle's float64 may floor differently."""
    rows, cols = cells
    if len(rows) == 0:
        return 0
    r, c = dst.grid_coordinates(transform_points(pose, src.cell_centres(rows, cols)))
    h, w = dst.shape
    near_grid = (r > -1) & (r < h + 1) & (c > -1) & (c < w + 1)
    near = lambda x: np.abs(x - np.round(x)) < tol       # noqa: E731
    return int(np.count_nonzero(near_grid & (near(r) | near(c))))


def walls_of(grid):
    return np.nonzero(np.nan_to_num(grid.prob, nan=0.0) >= 0.5)


# ---------------------------------------------------------------------------------------------
# 1. The kernel equals the oracle

CASES = {  # shape_a, res_a, origin_a, shape_b, res_b, origin_b
    "same-grid": ((40, 50), 0.1, (-2.0, -2.5), (40, 50), 0.1, (-2.0, -2.5)),
    "other-resolution-and-origin": ((45, 60), 0.1, (-2.0, -3.0), (50, 38), 0.07, (-1.2, -0.9)),
    "turned-a": ((40, 56), 0.05, (-2.0, -1.0, 0.3), (36, 44), 0.05, (-0.8, -0.6)),
    "both-turned": ((30, 42), 0.08, (0.5, -1.5, -1.1), (44, 28), 0.06, (-1.0, 0.4, 2.4)),
}
FAR_POSES = [(1e9, 0.0, 0.0), (-1e9, 3.0, 1.0), (0.0, 1e9, -2.0), (1e5, -1e5, 0.3), (3e7, 3e7, np.pi)]


def oracle_case(case, rng, n=48):
    """(a, b, prepared a, prepared b, n poses spread over A) for one of ``CASES``."""
    shape_a, res_a, origin_a, shape_b, res_b, origin_b = CASES[case]
    a = sparse_walls_map(rng, shape_a, res_a, origin_a)
    b = sparse_walls_map(rng, shape_b, res_b, origin_b, unknown=0.3)
    extent = max(shape_a) * res_a
    poses = np.column_stack([rng.uniform(-0.5, 0.5, n) * extent, rng.uniform(-0.5, 0.5, n) * extent,
                             rng.uniform(-np.pi, np.pi, n)])
    return a, b, PreparedMap(a, 0.1, "envelope"), PreparedMap(b, 0.1, "envelope"), poses


@pytest.mark.parametrize("unknown_cost", [0.0, 0.3, 1.0])
@pytest.mark.parametrize("case", list(CASES))
def test_kernel_equals_numpy_oracle(case, unknown_cost, rng):
    a, b, pa, pb, poses = oracle_case(case, rng)
    v_ti, n_ti = make_engine("taichi", pa, pb, unknown_cost)(poses)
    v_np, n_np = make_engine("numpy", pa, pb, unknown_cost)(poses)
    # the envelope kernel's own count: walls landing on known cells of the other map
    w_ti = EnvelopeEngine(pa, pb, unknown_cost)(poses)[1]
    w_np = NumpyEnvelope(a, b, 0.1, 0.1, unknown_cost)(poses)[1]

    wall_ties = np.array([boundary_ties(a, b, p, walls_of(b)) + boundary_ties(b, a, inverse(p), walls_of(a))
                          for p in poses])
    known_ties = np.array([boundary_ties(a, b, p, np.nonzero(b.known)) for p in poses])
    clean = wall_ties == 0
    assert clean.mean() >= 0.7, "too few poses free of float32 boundary ties to compare exactly"
    # tie-free poses: the same value up to float32 rounding of the sums, the same counts
    np.testing.assert_allclose(v_ti[clean], v_np[clean], rtol=1e-5, atol=1e-4)
    np.testing.assert_array_equal(w_ti[clean], w_np[clean])
    np.testing.assert_array_equal(n_ti[known_ties == 0], n_np[known_ties == 0])
    # the others: each point on a boundary may cost at most 1 more or less (weights, costs <= 1)
    assert np.all(np.abs(v_ti - v_np) <= 1e-5 * np.abs(v_np) + 1e-4 + wall_ties)
    assert np.all(np.abs(w_ti - w_np) <= wall_ties)
    assert np.all(np.abs(n_ti - n_np) <= known_ties)
    # the comparison is not vacuous: walls land on known cells and cost something
    assert w_np.max() > 20 and v_np.max() > 1.0
    if unknown_cost > 0:            # walls on unknown cells were charged somewhere
        free_of_unknown = make_engine("numpy", pa, pb, 0.0)(poses)[0]
        assert np.any(v_np > free_of_unknown + 0.5 * unknown_cost)

    # poses that put B (and A in B) millions of cells away: nothing lands, nothing is charged
    for name in ("taichi", "numpy"):
        values, counts = make_engine(name, pa, pb, unknown_cost)(FAR_POSES)
        assert values.tolist() == [0.0] * len(FAR_POSES), name
        assert counts.tolist() == [0] * len(FAR_POSES), name
    assert EnvelopeEngine(pa, pb, unknown_cost)(FAR_POSES)[1].tolist() == [0] * len(FAR_POSES)


def off_grid_weight(dst, src, pose):
    """The summed weight of ``src``'s walls (p >= 0.5) whose centres, moved into ``dst``'s frame by
    ``pose`` (r_dst2src), land off ``dst``'s grid; walls within 1e-4 cells of its edge are counted
    as ties (second value)."""
    rows, cols = walls_of(src)
    r, c = dst.grid_coordinates(transform_points(pose, src.cell_centres(rows, cols)))
    h, w = dst.shape
    off = (r < 0) | (r >= h) | (c < 0) | (c >= w)
    tie = (np.abs(r) < 1e-4) | (np.abs(r - h) < 1e-4) | (np.abs(c) < 1e-4) | (np.abs(c - w) < 1e-4)
    return float(src.prob[rows, cols][off].sum()), int(np.count_nonzero(tie))


@pytest.mark.parametrize("case", list(CASES))
def test_an_unknown_grid_edge_charges_each_wall_off_the_grid_the_unknown_cost(case, rng):
    """``grid_edge="unknown"``: a wall landing off the other map's grid pays unknown_cost times its
    weight instead of nothing, both ways, in the kernel and the oracle alike (nearest and
    bilinear); everything else is unchanged, so the two settings differ by exactly that sum."""
    a, b, pa, pb, poses = oracle_case(case, rng)
    cost = 0.3
    edge = {name: make_engine(name, pa, pb, cost, grid_edge="unknown")(poses)[0] for name in ("taichi", "numpy")}
    free = make_engine("numpy", pa, pb, cost)(poses)[0]
    expected, ties = np.zeros(len(poses)), np.zeros(len(poses), dtype=int)
    for k, pose in enumerate(poses):
        (b_off, b_ties), (a_off, a_ties) = off_grid_weight(a, b, pose), off_grid_weight(b, a, inverse(pose))
        expected[k], ties[k] = cost * (b_off + a_off), b_ties + a_ties
    clean = ties == 0
    np.testing.assert_allclose((edge["numpy"] - free)[clean], expected[clean], rtol=1e-9, atol=1e-9)
    assert expected.max() > 1.0                      # walls did land off the grids
    walls = len(walls_of(a)[0]) + len(walls_of(b)[0])
    wall_ties = np.array([boundary_ties(a, b, p, walls_of(b)) + boundary_ties(b, a, inverse(p), walls_of(a))
                          for p in poses])
    np.testing.assert_allclose(edge["taichi"][wall_ties == 0], edge["numpy"][wall_ties == 0], rtol=1e-5, atol=1e-4)
    bilinear = [make_engine(name, pa, pb, cost, "bilinear", "unknown")(poses)[0] for name in ("taichi", "numpy")]
    np.testing.assert_allclose(bilinear[0], bilinear[1], rtol=1e-5, atol=1e-5 * walls)
    # millions of cells away every wall of both maps is off the other's grid
    everything = cost * (a.prob[walls_of(a)].sum() + b.prob[walls_of(b)].sum())
    for name in ("taichi", "numpy"):
        for interpolation in ("nearest", "bilinear"):
            far = make_engine(name, pa, pb, cost, interpolation, "unknown")(FAR_POSES)[0]
            np.testing.assert_allclose(far, everything, rtol=1e-5)


def test_both_grid_edges_interleaved_each_keep_their_own_values(rng):
    """The grid edge is read by the kernel at run time (one compiled variant for both): engines of
    either setting on the same maps, launched in turn, each give their own oracle's values."""
    a, b, pa, pb, poses = oracle_case(next(iter(CASES)), rng)
    engines = {edge: make_engine("taichi", pa, pb, 0.3, "bilinear", edge) for edge in ("free", "unknown")}
    oracle = {edge: make_engine("numpy", pa, pb, 0.3, "bilinear", edge)(poses)[0] for edge in ("free", "unknown")}
    walls = len(walls_of(a)[0]) + len(walls_of(b)[0])
    for _ in range(2):
        for edge in ("unknown", "free"):
            np.testing.assert_allclose(engines[edge](poses)[0], oracle[edge], rtol=1e-5, atol=1e-5 * walls)
    assert np.max(oracle["unknown"] - oracle["free"]) > 1.0


def test_the_grid_edge_option_reaches_the_match(room_pair):
    """A matcher with ``grid_edge="unknown"`` evaluates the discrepancy so: at the truth, with B's
    grid larger than what A covers, its walls off A's grid add to e."""
    a, b = room_pair
    free = Matcher(levels=1, max_iterations=0, refine_iterations=0).match(a, b, TRUTH)
    edge = Matcher(levels=1, max_iterations=0, refine_iterations=0, grid_edge="unknown").match(a, b, TRUTH)
    pa, pb = PreparedMap(a, 0.1, "envelope", evidence="trinary"), PreparedMap(b, 0.1, "envelope", evidence="trinary")
    expected = make_engine("numpy", pa, pb, 0.3, grid_edge="unknown")([TRUTH])[0][0]
    assert edge.discrepancy == pytest.approx(expected, rel=1e-4)
    assert edge.discrepancy > free.discrepancy + 100.0        # the room's walls off A: 0.3 each


def test_far_poses_mixed_into_a_batch_do_not_disturb_the_others(rng):
    a = sparse_walls_map(rng, (40, 50), 0.1, (-2.0, -2.5))
    b = sparse_walls_map(rng, (30, 30), 0.1, (-1.5, -1.5))
    engine = make_engine("taichi", PreparedMap(a, 0.1, "envelope"), PreparedMap(b, 0.1, "envelope"), 0.3)
    near = np.array([(0.013, -0.021, 0.1), (0.31, 0.2, -0.4)])
    alone, counts_alone = engine(near)
    mixed, counts_mixed = engine(np.vstack([near[:1], FAR_POSES, near[1:]]))
    assert mixed[[0, -1]].tolist() == alone.tolist() and counts_mixed[[0, -1]].tolist() == counts_alone.tolist()
    assert np.all(mixed[1:-1] == 0.0) and alone.min() > 0.0


def test_count_any_spares_the_dense_launch_only_when_walls_show_the_overlap(room_pair):
    a, b = room_pair
    pa, pb = PreparedMap(a, 0.1, "envelope"), PreparedMap(b, 0.1, "envelope")
    engine = make_engine("taichi", pa, pb, 0.3)
    near = np.array([TRUTH, (0.3, 0.1, 0.2)])
    values, counts = engine(near, "any")
    exact = engine(near, "first")[1]
    assert engine.dense_launches == 0 and counts[0] > 0 and exact[0] > 0
    assert values.tolist() == engine(near, "none")[0].tolist()
    # B's walls all off A: the dense count decides, exactly
    far = np.array([(0.0, 1e4, 0.0)])
    assert engine(far, "any")[1].tolist() == [0] and engine.dense_launches == 1
    # A's edge: B shifted until a few of its walls are left on A, the dense count decides too
    edge = np.array([(0.0, 5.94, 0.02)])
    walls = engine._evaluate(edge, "b_walls")[1][0]
    assert 0 < walls < 10 and engine(edge, "any")[1][0] == engine(edge, "first")[1][0] > 0
    assert engine.dense_launches == 2


def test_relaunches_and_one_thread_give_the_same_sums(rng):
    """An engine relaunches one launch context per batch shape with new poses copied in; batches
    under ``SERIAL_BELOW`` lookups run on one thread. Neither may change a bit: the same poses
    give the same values alone (one thread) as in a large batch (all threads), and a batch seen
    before gives its first values again after others were launched."""
    a = sparse_walls_map(rng, (220, 200), 0.05, (-5.0, -5.5), walls=0.3, unknown=0.1)
    b = sparse_walls_map(rng, (200, 210), 0.05, (-5.2, -5.0), walls=0.3, unknown=0.1)
    pa, pb = PreparedMap(a, 0.1, "envelope"), PreparedMap(b, 0.1, "envelope")
    engine = EnvelopeEngine(pa, pb, 0.3)
    lookups = pa.walls[0].size + pb.walls[0].size
    assert lookups < SERIAL_BELOW < 40 * lookups            # one pose on one thread, 40 on all
    first = rng.normal(0.0, [0.3, 0.3, 0.2], (40, 3))
    second = rng.normal(0.0, [0.3, 0.3, 0.2], (40, 3))
    v1, n1 = engine(first)
    v2, _ = engine(second)
    assert not np.array_equal(v1, v2)
    again = engine(first)
    assert again[0].tolist() == v1.tolist() and again[1].tolist() == n1.tolist()
    alone = [engine(pose[None, :]) for pose in first]
    assert [v[0] for v, _ in alone] == v1.tolist() and [n[0] for _, n in alone] == n1.tolist()
    fresh = EnvelopeEngine(pa, pb, 0.3)(second)[0]
    assert fresh.tolist() == v2.tolist()


# ---------------------------------------------------------------------------------------------
# 2. Hand values


def test_hand_computed_values_on_one_row_maps():
    # resolution 1 m, blur 1 m: the envelope at d cells from a wall is exp(-d^2 / 2)
    a = GridMap(np.array([[1.0, 0.0, 0.0, np.nan, 0.0, 0.0, 0.0, 0.0]]), 1.0)   # wall centre (0.5, 0.5)
    b = GridMap(np.array([[1.0, 0.0, np.nan]]), 1.0)                            # wall centre (0.5, 0.5)
    pa, pb = PreparedMap(a, 1.0, "envelope"), PreparedMap(b, 1.0, "envelope")
    bowl = lambda d: 1.0 - np.exp(-0.5 * d * d)       # noqa: E731
    u = 0.3
    cases = [  # pose, e, walls landing on known cells
        ((0, 0, 0), 0.0, 2),                      # each wall on the other's wall
        ((1, 0, 0), bowl(1), 1),                  # B's wall on A's free cell 1; A's wall off B
        ((2, 0, 0), bowl(2), 1),
        ((3, 0, 0), u, 0),                        # B's wall on A's unknown cell 3
        ((7, 0, 0), bowl(7), 1),                  # free, far from A's wall: ~1
        ((8, 0, 0), 0.0, 0),                      # off A's grid: nothing
        ((-1, 0, 0), bowl(1), 1),                 # A's wall on B's free cell 1; B's wall off A
        ((-2, 0, 0), u, 0),                       # A's wall on B's unknown cell 2
        ((-3, 0, 0), 0.0, 0),
        ((0, 1, 0), 0.0, 0),                      # a row above both grids
        ((1, 1, np.pi), 0.0, 2),                  # turned half a turn about (0.5, 0.5)
        ((8, 1, np.pi), bowl(7), 1),              # B's wall at x = 7.5; A's at 7.5 in B: off
        ((1, 0, np.pi / 2), 0.0, 2),              # a quarter turn about (0.5, 0.5)
        ((3, 0, np.pi / 2), bowl(2), 1),          # B's wall at (2.5, 0.5); A's at (0.5, 2.5) in B: off
        ((1e9, 0, 0), 0.0, 0),
    ]
    poses = [p for p, _, _ in cases]
    expected = [e for _, e, _ in cases]
    expected_walls = [n for _, _, n in cases]
    assert bowl(7) == pytest.approx(1.0, abs=1e-10)
    for name in ("taichi", "numpy"):
        values, _ = make_engine(name, pa, pb, u)(poses)
        np.testing.assert_allclose(values, expected, rtol=1e-6, atol=1e-7, err_msg=name)
    assert EnvelopeEngine(pa, pb, u)(poses)[1].tolist() == expected_walls
    assert NumpyEnvelope(a, b, 0.1, 0.1, u)(poses)[1].tolist() == expected_walls
    # the overlap make_engine reports is eq. (6)'s: known cells of B on known cells of A
    assert make_engine("taichi", pa, pb, u)([(0, 0, 0), (3, 0, 0), (-1, 0, 0)])[1].tolist() == [2, 1, 1]
    # unknown_cost 0: unknown cells are not compared, as in the paper
    assert make_engine("taichi", pa, pb, 0.0)([(3, 0, 0), (-2, 0, 0)])[0].tolist() == [0.0, 0.0]


def test_grey_walls_are_weighted_by_their_occupancy():
    a = GridMap(np.array([[0.8, 0.0, 0.0]]), 1.0)
    b = GridMap(np.array([[0.6]]), 1.0)
    pa, pb = PreparedMap(a, 1.0, "envelope"), PreparedMap(b, 1.0, "envelope")
    # pose 0: B's wall (w 0.6) on A's wall (hi 0.8), A's (w 0.8) on B's (hi 0.6)
    # pose 1: B's wall on A's cell 1 (hi 0.8 exp(-1/2)); A's wall off B
    expected = [0.6 * 0.2 + 0.8 * 0.4, 0.6 * (1.0 - 0.8 * np.exp(-0.5))]
    for name in ("taichi", "numpy"):
        np.testing.assert_allclose(make_engine(name, pa, pb)([(0, 0, 0), (1, 0, 0)])[0], expected, rtol=1e-6)
    # cells below 0.5 are not walls: a map of them costs nothing
    faint = GridMap(np.array([[0.49, 0.3]]), 1.0)
    assert make_engine("taichi", PreparedMap(faint, 1.0, "envelope"), PreparedMap(faint, 1.0, "envelope"))(
        [(0, 0, 0), (1, 0, 0)])[0].tolist() == [0.0, 0.0]


# ---------------------------------------------------------------------------------------------
# 3. Symmetry, 4. the minimum at the truth


def test_swapping_the_maps_and_inverting_the_pose_gives_the_same_value(room_pair, rng):
    a, b = room_pair
    pa, pb = PreparedMap(a, 0.1, "envelope"), PreparedMap(b, 0.1, "envelope")
    poses = np.vstack([TRUTH, np.array(TRUTH) + np.column_stack([rng.uniform(-0.5, 0.5, (20, 2)),
                                                                   rng.uniform(-0.2, 0.2, 20)])])
    for unknown_cost in (0.0, 0.3):
        e_ab = make_engine("taichi", pa, pb, unknown_cost)(poses)[0]
        e_ba = make_engine("taichi", pb, pa, unknown_cost)([inverse(p) for p in poses])[0]
        np.testing.assert_allclose(e_ba, e_ab, rtol=0.02, atol=1e-3)
        e_ba_np = make_engine("numpy", pb, pa, unknown_cost)([inverse(p) for p in poses])[0]
        np.testing.assert_allclose(e_ba_np, e_ab, rtol=0.02, atol=1e-3)
        assert e_ab.max() > 20 * e_ab[0]


def test_the_discrepancy_is_lowest_at_the_truth(room_pair):
    a, b = room_pair
    engine = make_engine("taichi", PreparedMap(a, 0.1, "envelope"), PreparedMap(b, 0.1, "envelope"), 0.3)
    deg = np.radians(1.0)
    offsets = np.array([(0.1, 0, 0), (-0.1, 0, 0), (0, 0.1, 0), (0, -0.1, 0), (0, 0, deg), (0, 0, -deg),
                        (0.07, 0.07, 0), (-0.07, 0.07, deg)])
    values = engine(np.vstack([TRUTH, np.array(TRUTH) + offsets]))[0]
    assert np.all(values[1:] > values[0] + 10.0), values


def test_match_recovers_the_truth_from_nearby_guesses(room_pair):
    a, b = room_pair
    rng = np.random.default_rng(7)
    for _ in range(5):
        direction = rng.normal(size=2)
        offset = rng.uniform(0.05, 0.3) * direction / np.linalg.norm(direction)
        guess = np.array(TRUTH) + np.array([offset[0], offset[1], rng.uniform(-0.1, 0.1)])
        res = tm.match(a, b, guess)
        assert res.converged, (guess, res)
        assert np.hypot(*(res.pose[:2] - TRUTH[:2])) <= 2 * 0.05, (guess, res)
        assert abs(np.degrees(res.pose[2] - TRUTH[2])) <= 0.5, (guess, res)


# ---------------------------------------------------------------------------------------------
# 5. The line-reduced pyramid


def one_cell_walls():
    """16 x 16 free maps holding one one-cell wall each, along either axis, at even and odd rows
    and columns."""
    maps = []
    for k in (0, 5, 6, 15):
        row = np.zeros((16, 16))
        row[k, :] = 1.0
        maps.append((row, np.s_[k // 4, :]))
        col = np.zeros((16, 16))
        col[:, k] = 1.0
        maps.append((col, np.s_[:, k // 4]))
    return maps


@pytest.mark.parametrize("index", range(8))
def test_line_reduction_keeps_a_one_cell_wall(index):
    prob, wall_at_level_2 = one_cell_walls()[index]
    grid = GridMap(prob, 0.05, (-0.4, -0.4))
    once = coarsen(grid, reduce="line")
    twice = coarsen(once, reduce="line")
    assert once.shape == (8, 8) and twice.shape == (4, 4)
    assert once.resolution == 0.1 and twice.resolution == 0.2 and twice.corner_pose == grid.corner_pose
    assert np.count_nonzero(once.prob == 1.0) == 8 and np.count_nonzero(once.prob == 0.0) == 56
    assert np.all(twice.prob[wall_at_level_2] == 1.0)
    assert np.count_nonzero(twice.prob == 1.0) == 4 and np.count_nonzero(twice.prob == 0.0) == 12


@pytest.mark.parametrize("shape", [(40, 60), (41, 60), (40, 61), (7, 3)])
@pytest.mark.parametrize("reduce", ["mean", "line", "max"])
@pytest.mark.parametrize("factor", [2, 3])
def test_coarsening_equals_a_plain_numpy_block_reduction(shape, reduce, factor, rng):
    """Any factor, odd shapes: against the blocks reduced with nansum / nanmax over a NaN-padded copy."""
    prob = rng.random(shape)
    prob[rng.random(shape) < 0.4] = np.nan
    prob[:factor, :factor] = np.nan                       # a block with nothing known
    r2, c2 = -(-shape[0] // factor), -(-shape[1] // factor)
    padded = np.full((r2 * factor, c2 * factor), np.nan)
    padded[:shape[0], :shape[1]] = prob
    blocks = padded.reshape(r2, factor, c2, factor).transpose(0, 2, 1, 3).reshape(r2, c2, -1)
    known = np.sum(~np.isnan(blocks), axis=2)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)       # all-NaN blocks
        expected = {"mean": np.nansum(blocks, axis=2) / np.maximum(known, 1),
                    "line": np.minimum(factor * np.nansum(blocks, axis=2) / np.maximum(known, 1), 1.0),
                    "max": np.nanmax(blocks, axis=2)}[reduce]
    expected[known == 0] = np.nan
    out = coarsen(GridMap(prob, 0.05, (1.0, -2.0, 0.3)), factor, reduce)
    assert out.shape == (r2, c2) and out.resolution == pytest.approx(0.05 * factor)
    assert out.corner_pose == (1.0, -2.0, 0.3)
    np.testing.assert_array_equal(np.isnan(out.prob), known == 0)
    np.testing.assert_allclose(out.prob, expected, rtol=1e-14, atol=0.0)


@pytest.mark.parametrize("shape", [(40, 60), (41, 60), (40, 61), (7, 3), (1, 1), (1, 2), (2, 1)])
@pytest.mark.parametrize("reduce", ["mean", "line"])
def test_halving_trinary_codes_is_coarsening_their_map_bit_for_bit(shape, reduce, rng):
    """``halve_code`` (counts and a table) gives the general reduction's numbers exactly, odd shapes too,
    and both give the plain NumPy block reduction's (sums as NumPy adds them over the block axes)."""
    prob = (rng.random(shape) < 0.3).astype(np.float64)
    prob[rng.random(shape) < 0.4] = np.nan
    grid = GridMap(prob, 0.05, (1.0, -2.0, 0.3))
    general = coarsen(grid, reduce=reduce)
    blocks, table = halve_code(trinary_code(prob), reduce)
    assert blocks.dtype == np.uint8 and np.all((blocks == 0) == np.isnan(general.prob))     # 0: unknown
    np.testing.assert_array_equal(table[blocks], general.prob)
    grey = GridMap(np.where(np.isnan(prob), np.nan, rng.random(shape)), 0.05)
    padded = np.full((-(-shape[0] // 2) * 2, -(-shape[1] // 2) * 2), np.nan)
    padded[:shape[0], :shape[1]] = grey.prob
    blocks = padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2)
    known = (~np.isnan(blocks)).sum(axis=(1, 3))
    total = np.where(np.isnan(blocks), 0.0, blocks).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        expected = total / known if reduce == "mean" else np.minimum(2 * total / known, 1.0)
    np.testing.assert_array_equal(coarsen(grey, reduce=reduce).prob, np.where(known > 0, expected, np.nan))


def test_line_reduction_fades_a_lone_cell_and_mean_and_max_do_as_documented():
    prob = np.zeros((8, 8))
    prob[3, 2] = 1.0
    grid = GridMap(prob, 0.05)
    once = coarsen(grid, reduce="line")
    twice = coarsen(once, reduce="line")
    assert once.prob[1, 1] == 0.5 and np.count_nonzero(once.prob) == 1
    assert twice.prob[0, 0] == 0.25 and np.count_nonzero(twice.prob) == 1
    # mean: a 2 x 2 block holding one wall cell has mean 1/4; a one-cell wall fades to 1/2
    assert coarsen(grid).prob[1, 1] == 0.25 and coarsen(grid, reduce="mean").prob[1, 1] == 0.25
    assert coarsen(coarsen(grid)).prob[0, 0] == pytest.approx(1 / 16)
    wall = np.zeros((8, 8))
    wall[5, :] = 1.0
    assert np.all(coarsen(GridMap(wall, 0.05)).prob[2] == 0.5)
    # max: the lone cell and the wall both stay 1 at every level
    assert coarsen(coarsen(grid, reduce="max"), reduce="max").prob[0, 0] == 1.0
    assert np.all(coarsen(GridMap(wall, 0.05), reduce="max").prob[2] == 1.0)
    # grey cells: the line reduction doubles the mean and caps it at 1
    grey = GridMap(np.array([[0.2, 0.1], [0.0, 0.1]]), 1.0)
    assert coarsen(grey, reduce="line").prob[0, 0] == pytest.approx(0.2)
    assert coarsen(grey, reduce="mean").prob[0, 0] == pytest.approx(0.1)
    assert coarsen(grey, reduce="max").prob[0, 0] == pytest.approx(0.2)


@pytest.mark.parametrize("reduce", ["line", "mean", "max"])
def test_coarsening_keeps_unknown_unknown(reduce):
    prob = np.zeros((6, 5))
    prob[:2, :2] = np.nan                 # a whole block unknown -> unknown
    prob[2, 2] = np.nan                   # a block with one unknown cell: reduced over the known ones
    prob[3, 3] = 1.0
    prob[4:, :] = np.nan                  # the last block row unknown
    out = coarsen(GridMap(prob, 0.1), reduce=reduce).prob
    assert out.shape == (3, 3)
    assert np.isnan(out[0, 0]) and np.all(np.isnan(out[2]))
    assert np.count_nonzero(np.isnan(out)) == 4
    expected = {"line": 2.0 / 3.0, "mean": 1.0 / 3.0, "max": 1.0}[reduce]
    assert out[1, 1] == pytest.approx(expected)
    assert out[1, 2] == 0.0 and out[0, 1] == 0.0


def test_the_envelope_pyramid_uses_the_line_reduction(room_pair):
    a, _ = room_pair
    base = PreparedMap(a, 0.1, "envelope")        # holds the coarser levels' grids
    level = base.level(2)
    assert np.array_equal(level.grid.prob, coarsen(coarsen(a, reduce="line"), reduce="line").prob, equal_nan=True)
    assert level.blur_width == 0.1                        # blur_growth 1 by default on PreparedMap
    growing = PreparedMap(a, 0.1, "envelope", blur_growth=2.0)
    assert growing.level(2).blur_width == pytest.approx(0.4)
    gaussian_base = PreparedMap(a, 0.1, "gaussian")
    gaussian = gaussian_base.coarser()
    assert np.array_equal(gaussian.grid.prob, coarsen(a).prob, equal_nan=True)


# ---------------------------------------------------------------------------------------------
# 6. Trinary evidence


def test_trinary_thresholds_are_map_savers():
    p = np.array([[0.0, 0.1, 0.195, 0.196, 0.3, 0.5, 0.65, 0.651, 0.9, 1.0, np.nan]])
    out = trinary(GridMap(p, 0.05, (1.0, 2.0, 0.5))).prob
    expected = [0.0, 0.0, 0.0, np.nan, np.nan, np.nan, np.nan, 1.0, 1.0, 1.0, np.nan]
    np.testing.assert_array_equal(out[0], expected)
    custom = trinary(GridMap(p, 0.05), occupied=0.5, free=0.3).prob[0]
    np.testing.assert_array_equal(custom, [0.0, 0.0, 0.0, 0.0, np.nan, np.nan, 1.0, 1.0, 1.0, 1.0, np.nan])
    already = GridMap(np.array([[0.0, 1.0, np.nan]]), 0.1)
    np.testing.assert_array_equal(trinary(already).prob, already.prob)


def test_trinary_evidence_is_the_default_and_changes_the_prepared_map(rng):
    grid = GridMap(rng.random((30, 40)), 0.05)
    assert MatchOptions().evidence == "trinary"
    matcher = Matcher()
    default = matcher.prepare(grid)
    probability = Matcher(MatchOptions(evidence="probability")).prepare(grid)
    values = default.lower.prob
    assert set(np.unique(values[~np.isnan(values)]).tolist()) == {0.0, 1.0}
    assert np.isnan(values).any()
    assert np.array_equal(probability.lower.prob, grid.prob)
    assert not np.array_equal(default.lower.prob, probability.lower.prob, equal_nan=True)
    # trinary: walls are the cells above 0.65; probability: those at 0.5 or more
    assert len(default.walls[0]) == np.count_nonzero(grid.prob > 0.65)
    assert len(probability.walls[0]) == np.count_nonzero(grid.prob >= 0.5)
    assert np.array_equal(default.grid.prob, trinary(grid).prob, equal_nan=True)
    with pytest.raises(InvalidOptionError):
        PreparedMap(grid, 0.1, "envelope", evidence="binary")


# ---------------------------------------------------------------------------------------------
# 7. Options


@pytest.mark.parametrize("unknown_cost", [0.0, 0.3])
@pytest.mark.parametrize("case", list(CASES))
def test_the_bilinear_kernel_equals_the_numpy_oracle(case, unknown_cost, rng):
    """Each wall's cost interpolated between the four cell centres around it: the kernel (float32
    coordinates) against the oracle (float64, from the maps alone), at every pose: the value is
    continuous across cell boundaries, so there are no ties to set aside."""
    a, b, pa, pb, poses = oracle_case(case, rng)
    v_ti = make_engine("taichi", pa, pb, unknown_cost, "bilinear")(poses)[0]
    v_np = make_engine("numpy", pa, pb, unknown_cost, "bilinear")(poses)[0]
    walls = len(walls_of(a)[0]) + len(walls_of(b)[0])
    np.testing.assert_allclose(v_ti, v_np, rtol=1e-5, atol=1e-5 * walls)
    # not the nearest cell's value: the interpolation changed the sums
    nearest = make_engine("numpy", pa, pb, unknown_cost)(poses)[0]
    assert np.abs(v_np - nearest).max() > 0.2
    for name in ("taichi", "numpy"):
        assert make_engine(name, pa, pb, unknown_cost, "bilinear")(FAR_POSES)[0].tolist() == [0.0] * len(FAR_POSES)


def test_bilinear_costs_a_lone_wall_between_the_cell_centres():
    """Hand values: B a lone wall; A a known row with its wall at column 5 and free cells at
    columns 4 and 6 (envelope 0 there: blur 0). B's wall a quarter cell right of A's wall's centre
    costs 0 (3/4) + 1 (1/4) = 1/4 with "bilinear", 0 with "nearest"."""
    prob = np.full((3, 11), np.nan)
    prob[1, :] = 0.0
    prob[1, 5] = 1.0
    a = GridMap(prob, 0.1)
    lone = np.full((1, 1), 1.0)
    b = GridMap(lone, 0.1)
    pa, pb = PreparedMap(a, 0.0, "envelope"), PreparedMap(b, 0.0, "envelope")
    pose = [(0.5 + 0.025, 0.1, 0.0)]           # B's cell centre (0.05, 0.05) onto (0.575, 0.15)
    for name in ("taichi", "numpy"):
        # the other way, A's wall lands a quarter cell left of B's lone (known) cell's centre,
        # between it (cost 0) and the ring off B (cost 0)
        nearest = make_engine(name, pa, pb, 0.0)(pose)[0][0]
        bilinear = make_engine(name, pa, pb, 0.0, "bilinear")(pose)[0][0]
        assert nearest == pytest.approx(0.0, abs=1e-6), name
        assert bilinear == pytest.approx(0.25, abs=1e-6), name


def test_bilinear_smooths_the_discrepancy_along_a_path(room_pair):
    """Along a straight path of poses a tenth of a cell apart, the interpolated envelope changes
    by far less from pose to pose than the nearest cell's, which steps as walls cross cells."""
    a, b = room_pair
    pa, pb = PreparedMap(a, 0.1, "envelope"), PreparedMap(b, 0.1, "envelope")
    t = np.linspace(-0.15, 0.15, 61)[:, None]
    poses = np.asarray(TRUTH) + t * np.array([1.0, 0.5, 0.2])
    nearest = make_engine("taichi", pa, pb, 0.3)(poses)[0]
    bilinear = make_engine("taichi", pa, pb, 0.3, "bilinear")(poses)[0]
    second = lambda v: np.abs(np.diff(v, 2)).max()          # noqa: E731
    assert second(bilinear) < 0.25 * second(nearest)


def test_bilinear_envelope_matches_with_the_newton_driver(room_pair):
    a, b = room_pair
    options = MatchOptions(interpolation="bilinear")
    assert options.blur_kind == "envelope" and options.method == "newton"
    res = tm.match(a, b, (0.1, -0.05, 0.0), interpolation="bilinear")
    assert res.accepted
    np.testing.assert_allclose(res.pose, TRUTH, atol=0.02)
    assert MatchOptions.paper(interpolation="bilinear").method == "bfgs"
    engine = make_engine("taichi", PreparedMap(a, 0.1, "envelope"), PreparedMap(b, 0.1, "envelope"))
    with pytest.raises(InvalidOptionError, match="analytic gradient"):
        engine.bilinear(np.array([TRUTH]))
    with pytest.raises(InvalidOptionError, match="same kind of blur"):
        make_engine("taichi", PreparedMap(a, 0.1, "envelope"), PreparedMap(b, 0.1, "gaussian"))


@pytest.mark.parametrize("field, value", [
    ("unknown_cost", -0.1), ("unknown_cost", 1.5), ("unknown_cost", float("nan")), ("unknown_cost", "0.3"),
    ("unknown_cost", True), ("unknown_cost", None),
    ("blur_growth", 0.5), ("blur_growth", 17.0), ("blur_growth", float("inf")), ("blur_growth", "2"),
    ("evidence", "binary"), ("evidence", None), ("evidence", "Trinary"),
    ("grid_edge", "Unknown"), ("grid_edge", None), ("grid_edge", True), ("grid_edge", ["free"]),
    ("grid_edge", np.array(["free", "unknown"])),
])
def test_bad_envelope_options_are_refused(field, value):
    with pytest.raises(InvalidOptionError, match=field):
        MatchOptions(**{field: value})


@pytest.mark.parametrize("field, value", [("unknown_cost", 0.0), ("unknown_cost", 1.0), ("unknown_cost", 0),
                                          ("blur_growth", 1.0), ("blur_growth", 16), ("evidence", "probability"),
                                          ("grid_edge", "free"), ("grid_edge", "unknown")])
def test_edge_values_of_envelope_options_are_accepted(field, value):
    assert getattr(MatchOptions(**{field: value}), field) == value


def test_the_defaults_and_the_paper_preset():
    default, paper = MatchOptions(), MatchOptions.paper()
    assert (default.blur_kind, default.blur, default.blur_growth, default.unknown_cost, default.evidence) == \
        ("envelope", 0.1, 2.0, 0.3, "trinary")
    assert (paper.blur_kind, paper.blur, paper.blur_growth, paper.unknown_cost, paper.evidence) == \
        ("gaussian", 0.5, 1.0, 0.0, "probability")
    assert dataclasses.replace(paper, blur_kind="envelope").blur_kind == "envelope"


# ---------------------------------------------------------------------------------------------
# 8. Determinism


def test_the_same_match_twice_gives_bit_identical_poses(room_pair):
    a, b = room_pair
    guess = (0.3, -0.2, 0.1)
    first = tm.match(a, b, guess)
    again = tm.match(a, b, guess)
    fresh = Matcher().match(a, b, guess)
    for other in (again, fresh):
        assert first.pose.tobytes() == other.pose.tobytes()
        assert first.discrepancy == other.discrepancy and first.cost == other.cost
        assert first.information.tobytes() == other.information.tobytes()
    engine = make_engine("taichi", PreparedMap(a, 0.1, "envelope"), PreparedMap(b, 0.1, "envelope"), 0.3)
    poses = np.array(TRUTH) + np.random.default_rng(1).normal(scale=0.1, size=(50, 3))
    assert engine(poses)[0].tobytes() == engine(poses)[0].tobytes()


def test_a_wall_on_unknown_cells_next_to_a_wall_pays_its_distance():
    # what a laser cannot see behind a wall is unknown: a wall there, within the envelope of the
    # other map's wall, is explained by it and pays min(unknown_cost, 1 - hi), not the full
    # unknown_cost (resolution 1 m, blur 1 m: 1 - hi = 1 - exp(-d^2 / 2) at d cells)
    a = GridMap(np.array([[0.0, 0.0, 1.0, np.nan, np.nan, np.nan]]), 1.0)      # wall centre (2.5, 0.5)
    b = GridMap(np.array([[1.0]]), 1.0)                                        # wall centre (0.5, 0.5)
    pa, pb = PreparedMap(a, 1.0, "envelope"), PreparedMap(b, 1.0, "envelope")
    bowl = lambda d: 1.0 - np.exp(-0.5 * d * d)       # noqa: E731
    u = 0.5
    poses = [(2, 0, 0), (1, 0, 0), (3, 0, 0), (4, 0, 0), (0, 0, 0), (6, 0, 0)]
    expected = [0.0, bowl(1), bowl(1), u, bowl(2), 0.0]      # on, before, just behind, far behind, free, off
    assert bowl(1) < u < bowl(2)
    for name in ("taichi", "numpy"):
        np.testing.assert_allclose(make_engine(name, pa, pb, u)(poses)[0], expected, rtol=1e-6, atol=1e-7, err_msg=name)


def test_the_conflict_grid_from_stamped_distances_equals_the_exact_transforms(rng):
    # laser-like trinary maps (few walls, unknown areas): the stamped path of PreparedMap against
    # the exact transform over every cell and the blur, bit for bit, unknown cells included
    from taichi_match._blur import blur_everywhere, wall_transform
    from taichi_match._envelope import conflict_grid

    for shape in [(60, 200), (120, 160), (150, 90)]:
        prob = np.where(rng.random(shape) < 0.004, 1.0, 0.0)
        prob[rng.random(shape) < 0.4] = np.nan
        prob[rng.integers(shape[0]), rng.integers(shape[1])] = 1.0
        grid = GridMap(prob, 0.05)
        for width in (0.01, 0.05, 0.1):
            prepared = PreparedMap(grid, width, "envelope")
            assert prepared._squared is not None, "the stamped path was not taken"
            exact = conflict_grid(blur_everywhere(grid, width, kind="envelope", transform=wall_transform(grid)),
                                  np.isnan(prob))
            assert prepared.conflict.tobytes() == exact.tobytes()
            # the verdict's distances agree with the exact transform where its thresholds look
            d = prepared.wall_distance.lookup(*np.indices(shape).reshape(2, -1) + 0.5)
            ref = wall_transform(grid)[0].ravel().copy()
            ref[np.isnan(prob.ravel())] = np.nan
            near = ~np.isnan(ref) & (ref <= 5)                   # within the reach, and beyond CONFLICT_CELLS
            np.testing.assert_array_equal(d[near], ref[near])
            assert np.all(d[~np.isnan(ref) & (ref > 5)] > 5) and np.all(np.isnan(d[np.isnan(ref)]))


@pytest.mark.parametrize("shape", [(1, 1), (1, 300), (300, 1), (3, 2000), (40, 33)])
def test_the_stamped_conflict_grid_equals_the_exact_transforms_on_thin_maps(shape, rng):
    # thin maps, whose rows spread over many work items (``_launch.row_spread``) and whose walls'
    # discs reach past the map's edges; stamped walls at 1 and grey ones against the exact
    # transforms, bit for bit
    from taichi_match._blur import blur_everywhere, wall_transform
    from taichi_match._envelope import conflict_grid, envelope_profile, near_conflict_grid

    for grey in (False, True):
        prob = np.where(rng.random(shape) < 0.03, rng.uniform(0.5, 1.0, shape) if grey else 1.0, 0.0)
        prob[rng.random(shape) < 0.3] = np.nan
        prob[0, 0] = 1.0
        grid = GridMap(prob, 0.05)
        unknown = np.isnan(prob)
        reach = 13
        exact = conflict_grid(blur_everywhere(grid, 0.1, kind="envelope",
                                              transform=None if grey else wall_transform(grid)), unknown)
        if grey:
            rows, cols = np.nonzero(prob >= 0.5)
            got, squared = near_conflict_grid(~unknown, prob, reach, 0.5, (rows, cols, prob[rows, cols]))
            assert squared is None
            np.testing.assert_allclose(got, exact, rtol=0, atol=1e-6)       # the envelope's two arithmetics
            assert np.array_equal(got < -0.5, exact < -0.5)                   # the same cells unknown
        else:
            prepared = PreparedMap(grid, 0.1, "envelope")
            assert (prepared._squared is not None) == (shape != (1, 1))     # the stamped path (one cell: too few)
            assert prepared.conflict.tobytes() == exact.tobytes()
    assert len(envelope_profile(reach, 0.5)) == reach * reach + 2


@pytest.mark.parametrize("reach, ratio", [(13, 0.5), (20, 0.3)])
@pytest.mark.parametrize("grey, trinary", [(False, True), (False, False), (True, False)])
def test_the_stamped_conflict_grid_equals_numpy_from_scipy_distances(grey, trinary, reach, ratio, rng):
    # one launch stamps the walls' squared distances (or grey envelope) and the conflict values:
    # against SciPy's exact distance transform and conflict_grid's NumPy arithmetic, bit for bit
    # (walls at 1 on a trinary or a probability map; grey walls on a probability map); reach 20
    # keeps the squared distances in uint16
    shape = (90, 130)
    walls = rng.random(shape) < 0.02
    prob = np.where(walls, rng.uniform(0.5, 1.0, shape) if grey else 1.0,
                    0.0 if trinary else rng.uniform(0.0, 0.45, shape))
    prob[rng.random(shape) < 0.3] = np.nan
    _check_stamped_conflict_grid(prob, walls & ~np.isnan(prob), grey, trinary, reach, ratio)


@pytest.mark.parametrize("grey, trinary", [(False, True), (False, False), (True, False)])
def test_the_stamped_conflict_grid_on_a_laser_like_canvas(grey, trinary, rng):
    # a laser's fan in a mostly unknown canvas (front-end submaps know 4-16 % of their cells, and
    # the kernel writes only each row's span from its first known cell to its last): rows wholly
    # unknown, rows known only at their first or last cell, unknown holes inside the fan, walls at
    # its edge whose envelope reaches into the unknown around it
    shape = (80, 150)
    ii, jj = np.indices(shape)
    d = np.hypot(ii - 40.0, jj - 75.0)
    angle = np.arctan2(ii - 40.0, jj - 75.0)
    fan = (d < 30) & (np.abs(angle) < 1.2)
    edge = fan & (d >= 29)
    walls = edge | (fan & (rng.random(shape) < 0.01))
    prob = np.where(walls, rng.uniform(0.5, 1.0, shape) if grey else 1.0,
                    0.0 if trinary else rng.uniform(0.0, 0.45, shape))
    prob[~fan] = np.nan
    prob[fan & (rng.random(shape) < 0.1) & ~walls] = np.nan
    prob[5, 0] = prob[6, -1] = 1.0                     # rows known at one end only, walls there
    walls[5, 0] = walls[6, -1] = True
    prob[7, 0] = prob[8, -1] = 0.0
    assert np.isnan(prob[0]).all() and np.isnan(prob).mean() > 0.8
    _check_stamped_conflict_grid(prob, walls, grey, trinary, 13, 0.5)


def _check_stamped_conflict_grid(prob, walls, grey, trinary, reach, ratio):
    from scipy.ndimage import distance_transform_edt

    from taichi_match._envelope import conflict_grid, envelope_profile, near_conflict_grid

    shape = prob.shape
    unknown = np.isnan(prob)
    rows, cols = np.nonzero(walls)
    profile = envelope_profile(reach, ratio)
    got, squared = near_conflict_grid(~unknown, None if trinary else prob, reach, ratio,
                                      (rows, cols, prob[rows, cols]), squared=not grey)
    if grey:
        # the grey envelope by brute force: the brightest wall's weight * profile within reach
        envelope = np.zeros(shape)
        ii, jj = np.indices(shape)
        for r, c in zip(rows, cols):
            q = (ii - r) ** 2 + (jj - c) ** 2
            near = prob[r, c] * profile[np.minimum(q, reach * reach)]
            envelope = np.maximum(envelope, np.where(q <= reach * reach, near, 0.0))
        hi = envelope
    else:
        exact = np.rint(distance_transform_edt(~walls) ** 2).astype(np.int64)
        assert squared.dtype == (np.uint8 if reach * reach < 255 else np.uint16)
        want = np.where(exact <= reach * reach, exact, np.iinfo(squared.dtype).max)
        np.testing.assert_array_equal(squared, want)
        hi = profile[np.minimum(exact, reach * reach + 1)]
    hi = np.where(unknown, hi, np.fmax(np.nan_to_num(prob), hi))
    assert got.tobytes() == conflict_grid(hi, unknown).tobytes()


def test_the_stamped_conflict_grid_without_walls_is_the_maps_own():
    # no wall: 1 - p on known cells, -2 on unknown ones, -4 on the ring; squared distances all far
    from taichi_match._envelope import conflict_grid, near_conflict_grid

    prob = np.array([[0.0, np.nan, 0.2], [np.nan, 0.4, 0.0]])
    unknown = np.isnan(prob)
    none = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0))
    got, squared = near_conflict_grid(~unknown, None, 13, 0.5, none, squared=True)
    assert got.tobytes() == conflict_grid(np.zeros(prob.shape), unknown).tobytes() and np.all(squared == 255)
    got, squared = near_conflict_grid(~unknown, prob, 13, 0.5, none)
    assert got.tobytes() == conflict_grid(np.nan_to_num(prob), unknown).tobytes() and squared is None


def test_known_cells_moments_equal_the_listed_cells(rng):
    for shape, origin in [((40, 70), (-1.0, 2.0)), ((100, 33), (3.0, -4.0, 0.7)), ((1, 1), (0.0, 0.0))]:
        prob = rng.random(shape)
        prob[rng.random(shape) < 0.4] = np.nan
        prob.flat[0] = 0.2
        grid = GridMap(prob, 0.05, origin)
        prepared = PreparedMap(grid, 0.1, "envelope")
        centres = grid.cell_centres(*np.nonzero(grid.known))
        centroid = centres.mean(axis=0)
        np.testing.assert_allclose(prepared.centroid, centroid, rtol=1e-12, atol=1e-12)
        rms = np.sqrt(np.mean(np.sum((centres - centroid) ** 2, 1)))
        assert prepared.spread == pytest.approx(max(rms, 0.05), rel=1e-12)
        assert prepared.radius == pytest.approx(max(np.sqrt(np.mean(np.sum(centres**2, 1))), 0.05), rel=1e-12)


# ---------------------------------------------------------------------------------------------
# 6. Coarse levels taken from an earlier version of the map (the mapping loop's target)


def test_a_map_can_take_its_coarse_levels_from_an_earlier_version(room_pair):
    a, b = room_pair
    prob = a.prob.copy()
    prob[:, 120:] = np.nan                         # the earlier version: the right part not yet seen
    older = GridMap(prob, a.resolution, a.origin)
    matcher = tm.Matcher()
    old = matcher.prepare(older)
    new = matcher.prepare(a, coarse_from=old)
    assert new.level(1) is old.level(1) and new.level(2) is old.level(2)
    fresh = tm.Matcher().prepare(a)
    assert np.array_equal(new.conflict, fresh.conflict)          # the given level is its own
    assert not np.array_equal(new.level(1).conflict, fresh.level(1).conflict)
    res = matcher.match(a, b, np.array(TRUTH) + (0.2, -0.15, 0.08))
    assert res.accepted
    assert np.hypot(*(res.pose[:2] - TRUTH[:2])) <= 2 * 0.05 and abs(np.degrees(res.pose[2] - TRUTH[2])) <= 0.5


def test_coarse_levels_must_come_from_the_same_blur(room_pair):
    a, _ = room_pair
    other = tm.Matcher(blur=0.2).prepare(a)
    with pytest.raises(ValueError, match="same blur"):
        tm.Matcher().prepare(GridMap(a.prob.copy(), a.resolution, a.origin), coarse_from=other)


@pytest.mark.parametrize("reduce", ["mean", "line"])
@pytest.mark.parametrize("shape", [(90, 130), (7, 300), (41, 1)])
def test_a_map_of_codes_and_their_probabilities_prepares_as_its_probabilities(reduce, shape, rng):
    # a coarse level of a trinary map is kept as its block codes and their table (``halve_code``,
    # ``_grid._from_code``): its walls, known cells and stamped conflict grid are those of the same
    # map given as probabilities, bit for bit (walls at 1 only, and grey ones)
    from taichi_match._envelope import near_conflict_grid
    from taichi_match._grid import _from_code

    for walls_at_one in (False, True):
        fine = np.where(rng.random((2 * shape[0], 2 * shape[1])) < 0.004, 1.0, 0.0)   # few: stamped
        fine[0, 0] = 1.0
        fine[rng.random(fine.shape) < 0.5] = np.nan
        blocks, table = halve_code(trinary_code(fine), reduce)
        if walls_at_one:                               # only blocks full of walls, or none
            table = np.where(table >= 0.5, 1.0, table)
        coded = PreparedMap(_from_code(blocks, 0.1, (1.0, 2.0, 0.0), table), 0.2, "envelope")
        plain = PreparedMap(GridMap(table[blocks], 0.1, (1.0, 2.0, 0.0)), 0.2, "envelope")
        assert coded._stamp == plain._stamp and coded.n_known == plain.n_known
        assert coded._stamp or shape == (41, 1)                # the stamped path, on the larger maps
        assert all(np.array_equal(a, b) for a, b in zip(coded.walls, plain.walls))
        assert coded.conflict.tobytes() == plain.conflict.tobytes()
        # codes go by the grey stamps (one kernel variant fewer), keeping no squared distances;
        # the verdict's wall distances are the same where the plain map's stamps reach
        assert coded._squared is None
        assert (plain._squared is not None) == (walls_at_one and plain._stamp)
        if plain._squared is not None:
            r, c = (a.ravel() + 0.5 for a in np.indices(blocks.shape))
            want, got = plain.wall_distance.lookup(r, c), coded.wall_distance.lookup(r, c)
            near = np.isfinite(want)
            assert near.sum() > 100 and np.array_equal(got[near], want[near])
            assert np.array_equal(np.isnan(got), np.isnan(want)) and np.all(got[np.isinf(want)] > 13)
        rows, cols = np.nonzero(table[blocks] >= 0.5)
        got, _ = near_conflict_grid(blocks, table, 13, 0.5, (rows, cols, table[blocks][rows, cols]))
        want, _ = near_conflict_grid(blocks != 0, table[blocks], 13, 0.5, (rows, cols, table[blocks][rows, cols]))
        assert got.tobytes() == want.tobytes()
        if walls_at_one:                               # codes go by the grey stamps: no squared distances
            stamped, distances = near_conflict_grid(blocks, table, 13, 0.5, (rows, cols, table[blocks][rows, cols]),
                                                    squared=True)
            assert distances is None and stamped.tobytes() == want.tobytes()
