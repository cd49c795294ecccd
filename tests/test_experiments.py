"""The paper's scenes and the reproduction harness (small runs; no timing)."""

import json
import os

import numpy as np
import pytest

from taichi_match import GridMap, Matcher, discrepancy
from taichi_match._prepared import PreparedMap
from taichi_match.experiments import TABLES, covariance_check, run_row, surface
from taichi_match.scenes import corridor, noisy_copy, parallel_corridors_y


@pytest.fixture(scope="module")
def grid():
    return corridor()


def test_parallel_corridors_share_a_wall_at_the_stated_y(grid):
    y = parallel_corridors_y()
    values, overlap = discrepancy(grid, grid, [(0.0, y, 0.0), (0.0, y - 0.025, 0.0)], return_overlap=True)
    assert values[0] == 0.0 and overlap[0] == 2 * 480          # wall on wall: two rows of cells agree
    assert values[1] > 0.0                                      # a cell closer: B's wall on A's free space


def test_noisy_copy_changes_exactly_the_requested_fractions(grid):
    noisy = noisy_copy(grid, flip=0.01, drop=0.05, rng=3)
    known = grid.known
    n = known.sum()
    assert np.array_equal(np.isnan(grid.prob) & ~np.isnan(noisy.prob), np.zeros_like(known))   # none revealed
    dropped = known & np.isnan(noisy.prob)
    flipped = known & ~np.isnan(noisy.prob) & (noisy.prob != grid.prob)
    assert dropped.sum() == round(0.05 * n) and flipped.sum() == round(0.01 * n)
    assert np.allclose(noisy.prob[flipped], 1.0 - grid.prob[flipped])
    again = noisy_copy(grid, flip=0.01, drop=0.05, rng=3)
    assert np.array_equal(noisy.prob, again.prob, equal_nan=True)


def test_table_rows_hold_the_papers_numbers():
    assert [row.paper for row in TABLES] == [(99, 1), (98, 0), (62, 73, 93)]
    assert TABLES[2].target_y == pytest.approx(6.05) and TABLES[2].centre == (0.0, 5.0, 0.0)


def test_run_row_counts_as_the_paper(grid):
    res = run_row(Matcher(), grid, TABLES[0], trials=6, seed=1)
    assert len(res.results) == 6 and res.initial.shape == (6, 3)
    assert np.all(np.abs(res.initial) <= 0.5)
    tight = np.mean((np.abs(res.final[:, 1]) < 0.025) & (np.abs(res.final[:, 2]) < 0.045)) * 100
    assert res.rates[0] == pytest.approx(tight)
    assert 0.0 <= sum(res.rates) <= 100.0                      # Table 1's bands are disjoint
    assert res.mean_iterations > 0 and res.median_seconds > 0


def test_surface_equals_the_numpy_oracle_pose_by_pose():
    rng = np.random.default_rng(0)
    prob = rng.random((30, 40))
    prob[rng.random(prob.shape) < 0.2] = np.nan
    a = GridMap(prob, 0.1, (-2.0, -1.5))
    xs, ys = np.linspace(-1, 1, 7), np.linspace(-0.5, 0.5, 5)
    prepared = PreparedMap(a, 0.0)
    z = surface(prepared, prepared, xs, ys, theta=0.1)
    poses = np.array([(x, y, 0.1) for y in ys for x in xs])
    oracle = discrepancy(a, a, poses, engine="numpy").reshape(len(ys), len(xs))
    assert z.shape == (5, 7)
    assert np.allclose(z, oracle, atol=2.0)
    h = surface(prepared, prepared, xs, ys, theta=0.1, prior=(np.zeros(3), 10.0, 2.0))
    assert np.allclose(h - z, 10.0 * np.sqrt(poses[:, 0] ** 2 + poses[:, 1] ** 2 + 0.04).reshape(z.shape))


def test_covariance_check_calibrates_on_one_half_and_tests_on_the_other(grid):
    check = covariance_check(Matcher(), grid, flip=0.001, drop=0.05, trials=8, seed=2)
    assert check.errors.shape == (8, 2) and check.covariances.shape == (8, 2, 2)
    raw = np.array([e @ np.linalg.solve(c, e) for e, c in zip(check.errors, check.covariances)])
    assert check.scale == pytest.approx(raw[:4].mean() / 2)
    assert check.nees_mean == pytest.approx(raw[4:].mean() / check.scale)
    assert check.nees_band[0] < 2 < check.nees_band[1]


def test_reproduce_writes_the_report_figures_and_configuration(tmp_path):
    pytest.importorskip("matplotlib")
    from taichi_match.reproduce import reproduce

    calls = []
    out = reproduce(str(tmp_path), trials=3, covariance_trials=4, surface_step=3.0,
                    progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (3 * 3 + 2 * 4, 3 * 3 + 2 * 4)
    names = sorted(os.listdir(tmp_path / "figures"))
    assert len(names) == 8 and all(n.startswith("fig") for n in names)
    report = (tmp_path / "report.md").read_text()
    assert "Table 1" in report and "Table 2" in report and "NEES" in report
    results = json.loads((tmp_path / "results.json").read_text())
    config = json.loads((tmp_path / "config.json").read_text())
    assert len(results["tables"]) == 3 and config["trials"] == 3 and "revision" in config
    assert config["options"]["prior_weight"] == out["config"]["options"]["prior_weight"]


def test_cli_demo_writes_the_picture(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    from taichi_match.cli import main

    path = tmp_path / "demo.png"
    assert main(["demo", "--plot", str(path)]) == 0
    out = capsys.readouterr().out
    assert "matched pose" in out and "covariance" in out and path.stat().st_size > 10_000
