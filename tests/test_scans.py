"""Occupancy grids from laser scans: the cell traversal (reference against an exact oracle, Taichi
against the reference) and ``scans_to_grid`` on a simulated robot in a rectangular room."""

import os
import subprocess
import sys
import textwrap
from fractions import Fraction

import numpy as np
import pytest

from taichi_match import GridMap
from taichi_match._errors import InvalidOptionError, InvalidPoseError
from taichi_match._raycast import count_traversals_taichi
from taichi_match.logs import Scan
from taichi_match.scans import BeamCounts, SensorModel, _cells_of_segment, count_traversals, scans_to_grid, trinary

# --- the cell traversal ----------------------------------------------------------------------------

def exact_cells(u0, v0, u1, v1):
    """The oracle: the cells (row, col) of the segment in exact rational arithmetic on the given
    floats. It crosses grid line k of an axis at t = (k - a0) / (a1 - a0); between consecutive
    parameters the segment lies in one cell, the one holding the piece's midpoint."""
    u0, v0, u1, v1 = (Fraction(float(c)) for c in (u0, v0, u1, v1))
    ts = {Fraction(0), Fraction(1)}
    for a0, a1 in ((u0, u1), (v0, v1)):
        if a1 != a0:
            lo, hi = min(a0, a1), max(a0, a1)
            for k in range(int(np.ceil(lo)), int(np.floor(hi)) + 1):
                ts.add((k - a0) / (a1 - a0))
    ts = sorted(ts)
    cells = []
    for ta, tb in zip(ts[:-1], ts[1:]):
        mid = (ta + tb) / 2
        cells.append((int(np.floor(v0 + mid * (v1 - v0))), int(np.floor(u0 + mid * (u1 - u0)))))
    return cells


def reference_cells(segment):
    rows, cols = _cells_of_segment(*segment)
    return list(zip(rows.tolist(), cols.tolist()))


def counts(segments, hit, shape, engine):
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    return count_traversals(segments[:, :2], segments[:, 2:], np.asarray(hit, dtype=bool), (0, 0), 1.0,
                            shape, engine)


def hand_counts(shape, hit_cells=(), miss_cells=()):
    hits = np.zeros(shape, dtype=np.int32)
    misses = np.zeros(shape, dtype=np.int32)
    for cell in hit_cells:
        hits[cell] += 1
    for cell in miss_cells:
        misses[cell] += 1
    return hits, misses


ENGINES = ["numpy", "taichi"]


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("segment, hit, hit_cells, miss_cells", [
    # horizontal, from the middle of cell (2, 1) to the middle of cell (2, 5)
    ((1.5, 2.5, 5.5, 2.5), True, [(2, 5)], [(2, 1), (2, 2), (2, 3), (2, 4)]),
    ((1.5, 2.5, 5.5, 2.5), False, [], [(2, 1), (2, 2), (2, 3), (2, 4), (2, 5)]),
    # the same backwards, and vertical
    ((5.5, 2.5, 1.5, 2.5), True, [(2, 1)], [(2, 5), (2, 4), (2, 3), (2, 2)]),
    ((3.5, 6.5, 3.5, 0.5), True, [(0, 3)], [(r, 3) for r in range(1, 7)]),
    # 45 degrees through the corners (1, 1), (2, 2), (3, 3): the diagonal neighbours are not touched
    ((0.5, 0.5, 3.5, 3.5), False, [], [(0, 0), (1, 1), (2, 2), (3, 3)]),
    ((4.0, 0.0, 0.0, 4.0), True, [(4, 0)], [(0, 3), (1, 2), (2, 1), (3, 0)]),
    # starting on a grid line: the first cell is the one it moves into
    ((3.0, 0.5, 0.5, 0.5), False, [], [(0, 2), (0, 1), (0, 0)]),
    ((3.0, 0.5, 4.5, 0.5), False, [], [(0, 3), (0, 4)]),
    # ending on a grid line: the hit is in the cell holding the endpoint, past the last one crossed
    ((0.5, 0.5, 3.0, 0.5), True, [(0, 3)], [(0, 0), (0, 1), (0, 2)]),
    ((0.5, 3.0, 0.5, 0.5), True, [(0, 0)], [(2, 0), (1, 0)]),
    # along a grid line: the cells on its upper side (floor)
    ((1.0, 2.0, 1.0, 4.5), False, [], [(2, 1), (3, 1), (4, 1)]),
    # zero length: its one cell
    ((2.5, 1.5, 2.5, 1.5), True, [(1, 2)], []),
    ((2.5, 1.5, 2.5, 1.5), False, [], [(1, 2)]),
    ((2.0, 1.0, 2.0, 1.0), False, [], [(1, 2)]),
    # slope 1/2 from a corner: through the corner (2, 4), touching (1, 2) and (1, 3) on the way
    # (and ending on the corner (2, 4): its cell holds no piece of the segment, no miss there)
    ((0.0, 0.0, 4.0, 2.0), False, [], [(0, 0), (0, 1), (1, 2), (1, 3)]),
])
def test_traversal_of_hand_computed_segments(engine, segment, hit, hit_cells, miss_cells):
    shape = (8, 8)
    end_cell = (int(np.floor(segment[3])), int(np.floor(segment[2])))
    assert set(exact_cells(*segment)) - ({end_cell} if hit else set()) == set(miss_cells)
    assert hit_cells == ([end_cell] if hit else [])
    got = counts(segment, [hit], shape, engine)
    want = hand_counts(shape, hit_cells, miss_cells)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_a_segment_moving_less_than_a_rounding_error_along_an_axis_stays_in_its_column():
    # u goes from 20 to the float just below it: every point after the start is in column 19.
    # (Found from the piece's midpoint, u rounded back onto 20 for half of the segment.)
    segment = (20.0, 10.3, np.nextafter(20.0, 0.0), 20.7)
    assert reference_cells(segment) == [(r, 19) for r in range(10, 21)] == exact_cells(*segment)
    for engine in ENGINES:
        hits, misses = counts(segment, [False], (32, 32), engine)
        assert hits.sum() == 0 and misses[10:21, 19].tolist() == [1] * 11 and misses.sum() == 11


def random_segments(rng, shape, n):
    """Segments with both endpoints in the grid: general ones, long and short ones, axis-parallel
    ones, ones starting or ending on grid lines or grid corners, and zero-length ones."""
    rows, cols = shape
    top = np.array([cols, rows], dtype=np.float64) * (1.0 - 1e-9)
    p = rng.uniform(0.0, top, (n, 2))
    q = rng.uniform(0.0, top, (n, 2))
    kind = rng.integers(0, 9, n)
    short = kind == 1
    q[short] = np.clip(p[short] + rng.normal(0.0, 0.7, (short.sum(), 2)), 0.0, top)
    q[kind == 2, 0] = p[kind == 2, 0]                                   # vertical
    q[kind == 3, 1] = p[kind == 3, 1]                                   # horizontal
    p[kind == 4] = np.floor(p[kind == 4])                               # from a grid corner
    q[kind == 5] = np.floor(q[kind == 5])                               # to a grid corner
    p[kind == 6, 0] = np.round(p[kind == 6, 0])                         # from / to a grid line
    q[kind == 6, 1] = np.round(q[kind == 6, 1])
    p[kind == 6] = np.minimum(p[kind == 6], top)
    q[kind == 6] = np.minimum(q[kind == 6], top)
    q[kind == 7] = p[kind == 7]                                         # zero length
    half = kind == 8                                                    # half cells: many corners
    p[half] = np.minimum(np.round(p[half] * 2.0) / 2.0, top)
    q[half] = np.minimum(np.round(q[half] * 2.0) / 2.0, top)
    return np.column_stack([p, q])


@pytest.mark.parametrize("seed", range(3))
def test_reference_traversal_matches_exact_arithmetic(seed):
    rng = np.random.default_rng(seed)
    for segment in random_segments(rng, (20, 30), 150):
        assert reference_cells(segment) == exact_cells(*segment), segment


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("shape", [(30, 40), (7, 5), (1, 60)])
def test_taichi_traversal_equals_the_reference(seed, shape):
    rng = np.random.default_rng(100 + seed)
    segments = random_segments(rng, shape, 800)
    hit = rng.random(len(segments)) < 0.5
    want = counts(segments, hit, shape, "numpy")
    got = counts(segments, hit, shape, "taichi")
    assert got[0].dtype == got[1].dtype == np.int32 and got[0].shape == got[1].shape == shape
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert want[0].sum() == np.count_nonzero(hit)


def test_taichi_traversal_equals_the_reference_on_rays_through_grid_corners():
    # rays from cell corners and half cells at 0, 45, 90 ... degrees and slopes 1/2 and 2, some
    # nudged by a rounding error: the two axes cross at the same t, or a rounding error apart
    rng = np.random.default_rng(7)
    n = 3000
    start = rng.integers(20, 44, (n, 2)) + rng.choice([0.0, 0.5, 0.25], (n, 2))
    angle = (rng.choice(np.r_[np.arange(-3, 5) * np.pi / 4, np.arctan2(1, 2), np.arctan2(2, -1)], n)
             + rng.choice([0.0, 0.0, 1e-16, -1e-16], n))
    length = rng.choice([1.0, 2.0, 5.0, 10.5, 7 * np.sqrt(2), 15.3], n)
    end = start + length[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    segments = np.column_stack([start, end])
    hit = rng.random(n) < 0.5
    want = counts(segments, hit, (64, 64), "numpy")
    got = counts(segments, hit, (64, 64), "taichi")
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


@pytest.mark.parametrize("engine", ["numpy", "taichi"])
def test_a_beam_does_not_clear_a_return_of_its_own_scan(engine):
    # a grazing pair on a 1-cell grid row: beam 0 ends in cell (0, 2); beam 1 passes through it
    # to end in (0, 4). In one scan the return's cell stays a pure hit; in two scans (or with
    # no scans given) beam 1 clears it once
    segments = np.array([[0.5, 0.5, 2.5, 0.5], [0.5, 0.5, 4.5, 0.5]])
    hit = np.array([True, True])
    for scan, missed in (([0, 0], 0), ([0, 1], 1), (None, 1)):
        hits, misses = count_traversals(segments[:, :2], segments[:, 2:], hit, (0, 0), 1.0, (1, 6), engine,
                                        None if scan is None else np.array(scan))
        assert hits[0].tolist() == [0, 0, 1, 0, 1, 0]
        assert misses[0].tolist() == [2, 2, missed, 1, 0, 0], scan
    # a beam without a return spares its scan's returns too, and misses its own endpoint's cell
    hits, misses = count_traversals(segments[:, :2], segments[:, 2:], np.array([True, False]), (0, 0), 1.0,
                                    (1, 6), engine, np.array([0, 0]))
    assert misses[0].tolist() == [2, 2, 0, 1, 1, 0]


def test_taichi_own_scan_rule_equals_the_reference():
    # 40 scans of 60 beams from nearby origins: many beams cross the returns of their own scan
    rng = np.random.default_rng(11)
    scans, beams = 40, 60
    origin = np.repeat(rng.uniform(20.0, 40.0, (scans, 2)), beams, axis=0)
    angle = rng.uniform(-np.pi, np.pi, scans * beams)
    end = origin + rng.uniform(1.0, 18.0, scans * beams)[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    hit = rng.random(scans * beams) < 0.8
    scan = np.repeat(np.arange(scans), beams)
    want = count_traversals(origin, end, hit, (0, 0), 1.0, (60, 64), "numpy", scan)
    got = count_traversals(origin, end, hit, (0, 0), 1.0, (60, 64), "taichi", scan)
    plain = count_traversals(origin, end, hit, (0, 0), 1.0, (60, 64), "taichi")
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert np.array_equal(got[0], plain[0]) and plain[1].sum() > got[1].sum()    # the rule did skip misses
    with pytest.raises(InvalidOptionError, match="non-decreasing"):
        count_traversals(origin, end, hit, (0, 0), 1.0, (60, 64), "taichi", scan[::-1])


def test_taichi_skips_cells_outside_the_grid():
    # segments leaving, crossing, or missing an 12 x 16 grid: the counts are those of the
    # reference on a grid 40 cells larger on each side, cut back to the grid
    rng = np.random.default_rng(3)
    shape, pad = (12, 16), 40
    segments = rng.uniform(-30.0, 45.0, (600, 4))
    hit = rng.random(600) < 0.5
    big = count_traversals(segments[:, :2], segments[:, 2:], hit, (-pad, -pad), 1.0,
                           (shape[0] + 2 * pad, shape[1] + 2 * pad), "numpy")
    got = count_traversals_taichi(segments, hit.astype(np.int32), shape)
    for g, b in zip(got, big):
        np.testing.assert_array_equal(g, b[pad:pad + shape[0], pad:pad + shape[1]])
    # far away, moving away or passing by: nothing counted, nothing written out of bounds
    far = np.array([[-1e6, 5.0, -2e6, 5.0], [3.0, 1e5, 3.0, -1e5 + 7.0], [-5.0, -5.0, -1.0, -1.0],
                    [20.0, 13.0, 40.0, 30.0]])
    hits, misses = count_traversals_taichi(far[[0, 2, 3]], np.ones(3, dtype=np.int32), shape)
    assert hits.sum() == 0 and misses.sum() == 0
    hits, misses = count_traversals_taichi(far[1:2], np.zeros(1, dtype=np.int32), shape)
    assert hits.sum() == 0 and misses[:, 3].tolist() == [1] * shape[0] and misses.sum() == shape[0]


def test_taichi_traversal_of_no_segment_or_bad_segments():
    hits, misses = count_traversals_taichi(np.zeros((0, 4)), np.zeros(0, dtype=np.int32), (3, 4))
    assert hits.shape == misses.shape == (3, 4) and hits.dtype == misses.dtype == np.int32
    assert not hits.any() and not misses.any()
    for bad in (np.nan, np.inf, 1e300):
        with pytest.raises(InvalidOptionError, match="finite"):
            count_traversals_taichi(np.array([[0.5, 0.5, bad, 1.0]]), np.ones(1, dtype=np.int32), (3, 4))
    with pytest.raises(InvalidOptionError):
        count_traversals_taichi(np.zeros((2, 3)), np.ones(2, dtype=np.int32), (3, 4))
    with pytest.raises(InvalidOptionError, match="engine"):
        counts((0.5, 0.5, 1.5, 1.5), [True], (3, 4), "cuda")


def test_taichi_traversal_goes_on_after_taichi_is_initialised_or_reset_again():
    env = {k: v for k, v in os.environ.items() if not k.startswith(("TI_", "ENABLE_TAICHI"))}
    code = """
        import contextlib, io, sys
        import numpy as np
        from taichi_match._raycast import count_traversals_taichi
        assert "taichi" not in sys.modules, "taichi imported eagerly"
        seg = np.array([[0.5, 0.5, 6.5, 3.2], [2.0, 5.5, 2.0, 0.5]])
        hit = np.array([1, 0], dtype=np.int32)
        first = count_traversals_taichi(seg, hit, (8, 8))
        import taichi as ti
        with contextlib.redirect_stdout(io.StringIO()):
            ti.init(arch=ti.cpu)
        again = count_traversals_taichi(seg, hit, (8, 8))
        ti.reset()
        third = count_traversals_taichi(seg, hit, (8, 8))
        for other in (again, third):
            assert all(np.array_equal(a, b) for a, b in zip(first, other))
        assert first[0][3, 6] == 1 and first[1].sum() == 9 + 6, first
    """
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                         timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout == "" and out.stderr == ""


# --- scans_to_grid on a simulated robot in a rectangular room ----------------------------------------

HALF = (3.02, 2.02)              # the room's walls: x = +-3.02, y = +-2.02 (inside cells of 0.05 m)
ANGLES = np.linspace(-np.pi / 2, np.pi / 2, 181)
POSES = np.array([[0.0, 0.0, 0.0], [1.1, 0.4, 0.6], [-1.7, -0.9, 2.5], [0.3, 1.2, -1.9]])


def ranges_in_room(pose, angles=ANGLES):
    """The distance from the laser at ``pose`` along each beam to the walls of the room."""
    x, y, theta = pose
    c, s = np.cos(theta + angles), np.sin(theta + angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (HALF[0] - x) / c, np.where(c < 0, (-HALF[0] - x) / c, np.inf))
        ty = np.where(s > 0, (HALF[1] - y) / s, np.where(s < 0, (-HALF[1] - y) / s, np.inf))
    return np.minimum(tx, ty)


def room_scans(poses=POSES, max_range=30.0):
    return [Scan(float(i), ranges_in_room(p), ANGLES, np.asarray(p, dtype=np.float64), max_range)
            for i, p in enumerate(poses)]


def cell_centres(grid):
    rows, cols = grid.shape
    x = grid.origin[0] + (np.arange(cols) + 0.5) * grid.resolution
    y = grid.origin[1] + (np.arange(rows) + 0.5) * grid.resolution
    return np.meshgrid(x, y)


def same_grid(a, b):
    return (a.shape == b.shape and a.resolution == b.resolution and a.origin == b.origin
            and a.prob.tobytes() == b.prob.tobytes())


def wall_cells(grid):
    """The cells the wall lines run through (the walls lie 0.02 m inside cells of 0.05 m), corners
    left out; and the cell centres (x, y)."""
    res = grid.resolution
    x, y = cell_centres(grid)
    on_wall = (((np.abs(np.abs(x) - HALF[0]) < res / 2) & (np.abs(y) < HALF[1] - res))
               | ((np.abs(np.abs(y) - HALF[1]) < res / 2) & (np.abs(x) < HALF[0] - res)))
    return on_wall, x, y


def test_room_walls_are_occupied_inside_free_outside_unknown():
    grid = scans_to_grid(room_scans(), POSES, resolution=0.05)
    res = grid.resolution
    on_wall, x, y = wall_cells(grid)
    p = grid.prob
    assert on_wall.sum() > 300
    seen = on_wall & np.isfinite(p)
    assert seen.sum() > 0.9 * on_wall.sum()
    # most wall cells are occupied; a few seen only at grazing angles are not: a beam running
    # through the wall's cell for a few centimetres before it ends in the next one misses it
    assert np.mean(p[seen] > 0.5) > 0.9
    for px, py, _ in POSES:
        # inside, within 0.7 m of the robot (all walls are farther): free where seen
        near = np.hypot(x - px, y - py) < 0.7
        assert np.isfinite(p[near]).mean() > 0.4 and np.all(p[near & np.isfinite(p)] < 0.5)
    # the interior away from the walls is free where seen, and mostly seen
    interior = (np.abs(x) < HALF[0] - 2 * res) & (np.abs(y) < HALF[1] - 2 * res)
    assert np.isfinite(p[interior]).mean() > 0.9 and np.all(p[interior & np.isfinite(p)] < 0.5)
    # no cell wholly outside the walls is known
    outside = (np.abs(x) - res / 2 > HALF[0]) | (np.abs(y) - res / 2 > HALF[1])
    assert outside.sum() > 0 and np.all(np.isnan(p[outside]))
    # the grid's cell boundaries lie on multiples of the resolution, with 2 cells of margin
    assert np.allclose(np.array(grid.origin) / res, np.round(np.array(grid.origin) / res))
    assert grid.origin[0] < -HALF[0] - 1.9 * res and np.all(np.isnan(p[:2])) and np.all(np.isnan(p[:, -2:]))


@pytest.mark.parametrize("pose", POSES[:3])        # the fourth's only wall that near is behind it
def test_one_scan_sees_the_walls_ahead_as_occupied(pose):
    # on each wall less than 2.5 m away, within 0.5 m of the foot of the perpendicular from the
    # robot, beams (1 degree apart) end less than 0.05 m apart and meet the wall steeply: every
    # cell seen there holds a hit and is occupied
    grid = scans_to_grid(room_scans([pose]), [pose], resolution=0.05)
    on_wall, x, y = wall_cells(grid)
    p = grid.prob
    px, py, _ = pose
    side = (np.abs(x) > HALF[0] - 0.05) & (np.abs(y - py) < 0.5) & (np.abs(np.sign(x) * HALF[0] - px) < 2.5)
    end = (np.abs(y) > HALF[1] - 0.05) & (np.abs(x - px) < 0.5) & (np.abs(np.sign(y) * HALF[1] - py) < 2.5)
    near_foot = on_wall & (side | end)
    seen = near_foot & np.isfinite(p)
    assert seen.sum() >= 15 and np.all(p[seen] > 0.5)


def test_taichi_and_numpy_grids_are_identical_and_deterministic():
    scans = room_scans()
    first = scans_to_grid(scans, POSES, engine="taichi")
    assert same_grid(first, scans_to_grid(scans, POSES, engine="taichi"))
    assert same_grid(first, scans_to_grid(scans, POSES, engine="numpy"))
    # at other resolutions too, and from poses on cell corners (beams along grid lines)
    poses = np.array([[0.0, 0.0, 0.0], [1.0, -0.5, np.pi / 2], [-1.0, 0.5, np.pi / 4]])
    for resolution in (0.1, 0.25):
        scans = room_scans(poses)
        assert same_grid(scans_to_grid(scans, poses, resolution=resolution, engine="taichi"),
                         scans_to_grid(scans, poses, resolution=resolution, engine="numpy"))


@pytest.mark.parametrize("engine", ["taichi", "numpy"])
def test_counts_do_not_depend_on_the_arrays_extent(engine):
    """A beam's cells are found on the lattice: counted into a larger array at another offset,
    the same counts sit at the same lattice cells (scans of beams from far off the origin, ends
    on cell corners and lines)."""
    rng = np.random.default_rng(5)
    n = 200 if engine == "taichi" else 60
    start = np.repeat(rng.uniform(100.0, 110.0, (4, 2)), n // 4, axis=0)
    end = start + rng.uniform(-9.0, 9.0, (n, 2))
    end[::7] = np.round(end[::7] * 4) / 4                        # on cell corners and lines
    hit = rng.random(n) < 0.7
    scan = np.repeat(np.arange(4), n // 4)
    # lattice cells 182-238 on both axes: the big array holds them all, the small one a part
    small = count_traversals(start, end, hit, (185, 186), 0.5, (48, 46), engine, scan)
    big = count_traversals(start, end, hit, (170, 160), 0.5, (90, 100), engine, scan)
    for s_, b in zip(small, big):
        np.testing.assert_array_equal(b[15:15 + 48, 26:26 + 46], s_)
        assert b.sum() > s_.sum() > 0


@pytest.mark.parametrize("engine", ["taichi", "numpy"])
def test_beam_counts_added_scan_by_scan_are_the_grid_of_all_scans(engine):
    """``BeamCounts`` grown by one scan at a time, in any order of growth, gives ``scans_to_grid``
    of all of them bit for bit."""
    poses = np.array([[0.0, 0.0, 0.0], [1.1, 0.4, 0.6], [-1.7, -0.9, 2.5], [0.3, 1.2, -1.9], [2.4, -1.5, 3.0]])
    scans = room_scans(poses)
    whole = scans_to_grid(scans, poses, resolution=0.1, engine=engine)
    for order in ([0, 1, 2, 3, 4], [4, 2, 0, 3, 1]):
        counts = BeamCounts(resolution=0.1, engine=engine)
        for k in order:
            counts.add([scans[k]], poses[k:k + 1])
            grid = counts.grid()
            assert counts.grid() is grid                   # the same object until a beam is added
        assert same_grid(grid, whole)
    with pytest.raises(InvalidOptionError, match="no usable beam"):
        BeamCounts().grid()


def test_beam_counts_within_bounds_are_the_window_of_the_whole_grid():
    """``BeamCounts.grid(bounds)`` is the whole grid's cells that the box touches, bit for bit,
    with its corner on them; a box beside the canvas gives None, a malformed one an error."""
    poses = np.array([[0.0, 0.0, 0.0], [1.1, 0.4, 0.6], [-1.7, -0.9, 2.5]])
    counts = BeamCounts(resolution=0.1).add(room_scans(poses), poses)
    whole = counts.grid()
    x0, x1, y0, y1 = whole.extent
    for box in [(x0 + 1.03, y0 + 0.47, x1 - 2.21, y1 - 0.05), (x0 - 5.0, y0 - 5.0, x0 + 0.01, y1 + 5.0),
                (x0 + 2.03, y0 + 2.04, x0 + 2.03, y0 + 2.04), (x0 - 1.0, y0 - 1.0, x1 + 1.0, y1 + 1.0)]:
        part = counts.grid(box)
        # the cells whose square meets the box, counted independently from the corners
        r0 = max(int(np.floor((box[1] - y0) / 0.1 + 1e-9)), 0)
        c0 = max(int(np.floor((box[0] - x0) / 0.1 + 1e-9)), 0)
        r1 = min(int(np.floor((box[3] - y0) / 0.1 + 1e-9)) + 1, whole.shape[0])
        c1 = min(int(np.floor((box[2] - x0) / 0.1 + 1e-9)) + 1, whole.shape[1])
        assert part.shape == (r1 - r0, c1 - c0)
        np.testing.assert_array_equal(part.prob, whole.prob[r0:r1, c0:c1])
        np.testing.assert_allclose(part.corner_pose, (x0 + 0.1 * c0, y0 + 0.1 * r0, 0.0), atol=1e-9)
    assert counts.grid((x1 + 1.0, y0, x1 + 2.0, y1)) is None
    for bad in [(0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 1.0), (np.nan, 0.0, 1.0, 1.0), "abcd", ("a", "b", "c", "d"),
                (0.0, 0.0, np.inf, 1.0), [[0.0, 0.0], [1.0, 1.0]]]:
        with pytest.raises(InvalidOptionError, match="bounds"):
            counts.grid(bad)


@pytest.mark.parametrize("engine", ENGINES)
def test_trinary_evidence_is_the_trinary_map_of_the_grid(engine):
    """``evidence="trinary"`` gives ``trinary`` of the probability grid bit for bit (the oracle:
    ``trinary`` applied afterwards, cell by cell thresholds), whole and within bounds, from the
    table of count pairs and, with counts too large for it, from the cells; the two evidences
    keep their own whole grid."""
    poses = np.array([[0.0, 0.0, 0.0], [1.1, 0.4, 0.6], [-1.7, -0.9, 2.5]])
    counts = BeamCounts(resolution=0.1, engine=engine).add(room_scans(poses), poses)
    whole = counts.grid()
    code = counts.grid(evidence="trinary")
    assert counts.grid(evidence="trinary") is code and counts.grid() is whole
    assert same_grid(code, trinary(whole))
    assert set(np.unique(np.nan_to_num(code.prob, nan=-1.0))) == {-1.0, 0.0, 1.0}
    x0, x1, y0, y1 = whole.extent
    box = (x0 + 1.03, y0 + 0.47, x1 - 2.21, y1 - 0.05)
    assert same_grid(counts.grid(box, evidence="trinary"), trinary(counts.grid(box)))
    assert same_grid(scans_to_grid(room_scans(poses), poses, resolution=0.1, engine=engine, evidence="trinary"),
                     trinary(scans_to_grid(room_scans(poses), poses, resolution=0.1, engine=engine)))
    from taichi_match.scans import MAX_TABLE, _probabilities

    rng = np.random.default_rng(3)
    hits = rng.integers(0, 400, (31, 47)).astype(np.int32)
    misses = rng.integers(0, 3000, (31, 47)).astype(np.int32)
    hits[::4], misses[::4] = 0, 0
    assert (int(hits.max()) + 1) * (int(misses.max()) + 1) > MAX_TABLE
    model = SensorModel()
    prob = _probabilities(hits, misses, model, engine)
    np.testing.assert_array_equal(_probabilities(hits, misses, model, engine, code=True),
                                  (prob < 0.196) * 1 + (prob > 0.65) * 2)
    with pytest.raises(InvalidOptionError, match="evidence"):
        counts.grid(evidence="binary")


def test_beams_without_a_return_are_free_up_to_no_return_length():
    pose = np.array([[0.2, -0.3, 0.4]])
    scan = Scan(0.0, np.full(181, 30.0), ANGLES, pose[0], 30.0)          # nothing within range
    model = SensorModel(no_return_length=1.0)
    for engine in ENGINES:
        grid = scans_to_grid([scan], pose, model=model, engine=engine)
        x, y = cell_centres(grid)
        p = grid.prob
        d = np.hypot(x - 0.2, y + 0.3)
        bearing = np.arctan2(y + 0.3, x - 0.2) - 0.4
        in_fan = np.abs(np.arctan2(np.sin(bearing), np.cos(bearing))) < np.pi / 2 - 0.05
        assert np.all(p[np.isfinite(p)] < 0.5)                           # no hit anywhere
        assert np.all(np.isfinite(p[in_fan & (d < 0.9)]))                # free up to the length
        assert np.all(np.isnan(p[d > 1.0 + grid.resolution]))           # and unknown beyond
    # no_return_length = 0: beams without a return are ignored, and here no beam is left
    with pytest.raises(InvalidOptionError, match="no usable beam"):
        scans_to_grid([scan], pose, model=SensorModel(no_return_length=0.0))


def test_returns_beyond_max_ray_length_are_cut_and_not_hits():
    model = SensorModel(max_ray_length=1.2)
    grid = scans_to_grid(room_scans(POSES[:1]), POSES[:1], model=model)
    x, y = cell_centres(grid)
    p = grid.prob
    assert np.all(p[np.isfinite(p)] < 0.5)
    assert np.all(np.isnan(p[np.hypot(x, y) > 1.2 + grid.resolution]))


def test_invalid_readings_are_ignored():
    pose = POSES[1]
    ranges = ranges_in_room(pose)
    bad = np.array([3, 17, 40, 41, 90, 150, 180])
    broken = ranges.copy()
    broken[bad] = [np.nan, -1.0, 0.0, np.inf, 0.03, -np.inf, np.nan]      # 0.03 <= min_range
    keep = np.setdiff1d(np.arange(181), bad)
    with_bad = Scan(0.0, broken, ANGLES, pose, 30.0)
    without = Scan(0.0, ranges[keep], ANGLES[keep], pose, 30.0)
    for engine in ENGINES:
        assert same_grid(scans_to_grid([with_bad], [pose], engine=engine),
                         scans_to_grid([without], [pose], engine=engine))


def test_hits_and_misses_are_counted_per_beam():
    # one scan of three beams from the centre of cell (0, 0) of a 0.5 m grid: along +x to a wall
    # at 1.6 m, along +y with no return, and one reading ignored
    scan = Scan(0.0, np.array([1.6, 10.0, np.nan]), np.array([0.0, np.pi / 2, 1.0]),
                np.zeros(3), 10.0)
    pose = np.array([[0.25, 0.25, 0.0]])
    model = SensorModel(hit=1.0, miss=-0.5, clamp=6.0, no_return_length=1.0)
    for engine in ENGINES:
        grid = scans_to_grid([scan], pose, resolution=0.5, model=model, margin=1, engine=engine)
        assert grid.origin == (-0.5, -0.5) and grid.shape == (5, 6)
        sigmoid = 1.0 / (1.0 + np.exp(-np.array([1.0, -0.5, -1.0])))
        want = np.full((5, 6), np.nan)
        want[1, 1] = sigmoid[2]                         # both beams start there: two misses
        want[1, 2:4] = sigmoid[1]                       # the +x beam passes
        want[1, 4] = sigmoid[0]                         # and ends at x = 1.85 m
        want[2:4, 1] = sigmoid[1]                       # the +y beam is free up to y = 1.25 m
        np.testing.assert_array_equal(grid.prob, want)


@pytest.mark.parametrize("most", [(3, 200), (400, 3000)])        # from the table, and cell by cell
def test_probabilities_from_counts_are_the_log_odds_formula_cell_by_cell(most):
    """Each cell's probability is 1 / (1 + exp(-clip(hit h + miss m))) of its own counts, bit for
    bit (the oracle: the formula on one cell at a time), NaN where no beam reached."""
    from taichi_match.scans import MAX_TABLE, _probabilities

    rng = np.random.default_rng(7)
    hits = rng.integers(0, most[0] + 1, (37, 53)).astype(np.int32)
    misses = rng.integers(0, most[1] + 1, (37, 53)).astype(np.int32)
    hits[::5], misses[::5] = 0, 0
    hits[1, 3], misses[1, 3] = most                               # the largest counts present
    assert ((most[0] + 1) * (most[1] + 1) <= MAX_TABLE) == (most == (3, 200))
    model = SensorModel(hit=0.9, miss=-0.4, clamp=6.0)
    want = np.full(hits.shape, np.nan)
    for (r, c), h in np.ndenumerate(hits):
        if h or misses[r, c]:
            x = min(max(model.hit * float(h) + model.miss * float(misses[r, c]), -model.clamp), model.clamp)
            want[r, c] = 1.0 / (1.0 + float(np.exp(-x)))
    for engine in ENGINES:
        got = _probabilities(hits[:, 2:], misses[:, 2:], model, engine)      # a window: not contiguous
        np.testing.assert_array_equal(got, want[:, 2:])


def test_trinary_thresholds():
    grid = GridMap(np.array([[0.9, 0.66, 0.65, 0.5], [0.2, 0.196, 0.1, np.nan]]), 0.1)
    out = trinary(grid)
    np.testing.assert_array_equal(out.prob, [[1.0, 1.0, np.nan, np.nan], [np.nan, np.nan, 0.0, np.nan]])
    assert out.resolution == grid.resolution and out.origin == grid.origin
    out = trinary(grid, occupied=0.5, free=0.3)
    np.testing.assert_array_equal(out.prob, [[1.0, 1.0, 1.0, np.nan], [0.0, 0.0, 0.0, np.nan]])


@pytest.mark.parametrize("field, value", [
    ("hit", -0.1), ("hit", np.nan), ("hit", np.inf), ("miss", 0.1), ("miss", -np.inf), ("clamp", -1.0),
    ("min_range", -0.01), ("max_ray_length", np.nan), ("max_ray_length", 0.05), ("no_return_length", -1.0),
    ("hit", "0.9"), ("miss", None),
])
def test_sensor_model_rejects_bad_values(field, value):
    with pytest.raises(InvalidOptionError, match=field):
        SensorModel(**{field: value})


def test_sensor_model_accepts_its_defaults_and_limits():
    SensorModel()
    SensorModel(hit=0.0, miss=0.0, clamp=0.0, min_range=0.0, max_ray_length=1e-3, no_return_length=0.0)


def test_scans_to_grid_rejects_bad_arguments():
    scans = room_scans(POSES[:2])
    for resolution in (0.0, -0.05, np.nan):
        with pytest.raises(InvalidOptionError, match="resolution"):
            scans_to_grid(scans, POSES[:2], resolution=resolution)
    with pytest.raises(InvalidOptionError, match="engine"):
        scans_to_grid(scans, POSES[:2], engine="gpu")
    with pytest.raises(InvalidPoseError):
        scans_to_grid(scans, POSES[:1])
    with pytest.raises(InvalidPoseError):
        scans_to_grid(scans, [[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]])
    nothing = Scan(0.0, np.full(181, np.nan), ANGLES, POSES[0], 30.0)
    with pytest.raises(InvalidOptionError, match="no usable beam"):
        scans_to_grid([nothing], POSES[:1])


# --- free_margin: a return's beam free only up to that many metres short of it ----------------------

def beam_scan(ranges, angle=0.0):
    """A scan of one beam per range, all along ``angle`` (radians), sensor maximum 80 m."""
    ranges = np.asarray(ranges, dtype=np.float64)
    return Scan(0.0, ranges, np.full(len(ranges), angle), np.zeros(3), 80.0)


@pytest.mark.parametrize("engine", ENGINES)
def test_free_margin_leaves_the_cells_before_a_return_unknown(engine):
    # laser at (0.05, 0.05) on 0.1 m cells, one beam along +x to 1.0 m: its return in the cell of
    # x 1.0-1.1. The cells it passes are free (x 0-1.0); with a margin of 0.23 m its free part ends
    # at x 0.82, so the cell of x 0.9-1.0 is unknown, the one of x 0.8-0.9 still free
    pose = np.array([[0.05, 0.05, 0.0]])
    for margin, unknown_from in ((0.0, None), (0.23, 0.95), (0.5, 0.65)):
        grid = scans_to_grid([beam_scan([1.0])], pose, resolution=0.1, model=SensorModel(free_margin=margin),
                             engine=engine)
        col = lambda x: int(np.floor((x - grid.corner_pose[0]) / 0.1))  # noqa: E731
        row = int(np.floor((0.05 - grid.corner_pose[1]) / 0.1))
        p = grid.prob[row]
        assert p[col(1.05)] > 0.5                                       # the return
        free = [x for x in np.arange(0.05, 1.0, 0.1) if unknown_from is None or x < unknown_from - 1e-9]
        assert all(p[col(x)] < 0.5 for x in free), margin
        if unknown_from is not None:
            assert all(np.isnan(p[col(x)]) for x in np.arange(unknown_from, 1.0, 0.1)), margin


@pytest.mark.parametrize("engine", ENGINES)
def test_free_margin_keeps_a_short_return_of_another_scan(engine):
    # two scans from one pose see a wall at 2.0 m and 2.1 m (range noise): without a margin the
    # longer beam crosses the shorter one's cell, whose log-odds fall to hit + miss = 0.5 (p 0.62,
    # not occupied at 0.65); with a margin of 0.16 m the longer beam is free up to x 1.99 and the
    # cell stays a hit alone (0.9, p 0.71), so the wall keeps its near side
    pose = np.array([[0.05, 0.05, 0.0]] * 2)
    scans = [beam_scan([2.0]), beam_scan([2.1])]
    model = SensorModel()
    for margin, want in ((0.0, model.hit + model.miss), (0.16, model.hit)):
        grid = scans_to_grid(scans, pose, resolution=0.1, model=SensorModel(free_margin=margin), engine=engine)
        col = int(np.floor((2.05 - grid.corner_pose[0]) / 0.1))
        row = int(np.floor((0.05 - grid.corner_pose[1]) / 0.1))
        assert grid.prob[row, col] == pytest.approx(1.0 / (1.0 + np.exp(-want)), abs=1e-12)


def test_free_margin_beams_shorter_than_it_are_their_hits_alone_and_engines_agree():
    rng = np.random.default_rng(5)
    scans = [Scan(0.0, rng.uniform(0.06, 6.0, 90), np.linspace(-np.pi / 2, np.pi / 2, 90), np.zeros(3), 80.0)
             for _ in range(4)]
    poses = np.column_stack([rng.uniform(-1, 1, 4), rng.uniform(-1, 1, 4), rng.uniform(-np.pi, np.pi, 4)])
    model = SensorModel(free_margin=0.3)
    a = scans_to_grid(scans, poses, model=model, engine="taichi")
    assert same_grid(a, scans_to_grid(scans, poses, model=model, engine="numpy"))
    # incremental counts give the same grid
    counts = BeamCounts(model=model)
    for scan, pose in zip(scans, poses):
        counts.add([scan], pose[None])
    assert same_grid(a, counts.grid())
    # one beam of 0.2 m, shorter than the margin: its return only, no free cell
    lone = scans_to_grid([beam_scan([0.2])], np.array([[0.025, 0.025, 0.0]]), model=model)
    assert np.count_nonzero(np.isfinite(lone.prob)) == 1


@pytest.mark.parametrize("value", [-0.1, float("nan"), float("inf"), "0.1"])
def test_free_margin_must_be_a_finite_number_at_least_zero(value):
    with pytest.raises(InvalidOptionError, match="free_margin"):
        SensorModel(free_margin=value)
