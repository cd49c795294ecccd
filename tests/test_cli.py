"""The command line end to end on small maps made here."""

import json
import math

import numpy as np
import pytest
from conftest import rasterize, room_scene

from taichi_match import GridMap, InvalidOptionError, io
from taichi_match.cli import main
from taichi_match.merge import merge_maps


@pytest.fixture
def pair(tmp_path):
    truth = (0.15, -0.1, 0.05)
    a = rasterize(room_scene, (130, 170), 0.05, (-4.1, -3.1))
    b = rasterize(room_scene, (120, 160), 0.05, (-4.0, -3.0), pose_a2b=truth)
    io.write_ros_map(a, tmp_path / "a.yaml")
    io.write_ros_map(b, tmp_path / "b.yaml")
    return tmp_path / "a.yaml", tmp_path / "b.yaml", truth


def test_align_json_g2o_and_plot(pair, tmp_path, capsys):
    a, b, truth = pair
    code = main(["align", str(a), str(b), "--initial", "0", "0", "0", "--json", "--g2o", "3", "4",
                 "--plot", str(tmp_path / "o.png")])
    result = json.loads(capsys.readouterr().out)         # stdout is one JSON document, the edge inside
    assert code == 0 and result["converged"] and result["status"] and result["not_accepted_because"] is None
    assert np.allclose(result["pose"], truth, atol=0.05)
    assert np.array(result["covariance"]).shape == (3, 3) and result["seconds"] > 0
    fields = result["g2o"].split()
    assert fields[:3] == ["EDGE_SE2", "3", "4"] and len(fields) == 12
    fields = fields[1:]
    assert np.allclose([float(v) for v in fields[2:5]], result["pose"], atol=1e-5)
    assert (tmp_path / "o.png").stat().st_size > 10_000


def test_align_prints_the_g2o_edge_as_text_without_json(pair, capsys):
    a, b, _ = pair
    assert main(["align", str(a), str(b), "--initial", "0", "0", "0", "--g2o", "3", "4"]) == 0
    edges = [line for line in capsys.readouterr().out.splitlines() if line.startswith("EDGE_SE2 3 4 ")]
    assert len(edges) == 1 and len(edges[0].split()) == 12


def test_align_refuses_negative_g2o_vertex_ids(pair, capsys):
    a, b, _ = pair
    with pytest.raises(SystemExit) as stop:
        main(["align", str(a), str(b), "--initial", "0", "0", "0", "--g2o", "-1", "4"])
    assert stop.value.code == 2
    assert "--g2o takes two vertex ids >= 0" in capsys.readouterr().err


@pytest.mark.parametrize("extra", [["--interpolation", "bilinear", "--blur-kind", "gaussian", "--blur", "0.5"],
                                   ["--optimizer", "bfgs"]])
def test_align_with_other_methods(pair, capsys, extra):
    a, b, truth = pair
    assert main(["align", str(a), str(b), "--initial", "0", "0", "0", "--json", *extra]) == 0
    assert np.allclose(json.loads(capsys.readouterr().out)["pose"], truth, atol=0.05)


def test_align_exit_codes(pair, tmp_path, capsys):
    a, b, _ = pair
    assert main(["align", str(a), str(b), "--initial", "0", "0", "0", "--max-iterations", "0"]) == 1
    assert main(["align", str(a), str(tmp_path / "missing.yaml"), "--initial", "0", "0", "0"]) == 2
    assert "error" in capsys.readouterr().err
    assert main(["align", str(a), str(b), "--initial", "1e9", "0", "0"]) == 1      # no overlap: reported
    assert main(["align", str(a), str(b), "--initial", "0", "0", "0", "--plot", str(tmp_path / "no" / "o.png")]) == 2
    with pytest.raises(SystemExit) as exc:
        main(["align", str(a), str(b), "--initial", "0", "zero", "0"])
    assert exc.value.code == 2


def test_align_exits_0_only_for_an_accepted_match(pair, capsys):
    """Exit 0 iff accepted; --json carries the verdict and its evidence. Wrong poses that the
    optimiser reports as converged must exit 1 (they used to exit 0)."""
    a, b, truth = pair
    wrong_converged = 0
    for guess in (("0", "0", "0"), ("2.5", "-1.5", "0.7"), ("-2", "2", "-0.8"), ("3", "1", "1.2")):
        code = main(["align", str(a), str(b), "--initial", *guess, "--json"])
        out = json.loads(capsys.readouterr().out)
        assert set(out["evidence"]) == {"walls_compared", "wall_agreement", "wall_conflict", "uncertainty_m"}
        err = np.array(out["pose"]) - truth
        right = np.hypot(err[0], err[1]) < 0.1 and abs((err[2] + np.pi) % (2 * np.pi) - np.pi) < np.radians(1)
        assert code == (0 if out["accepted"] else 1)
        if out["accepted"]:
            assert right, (guess, out)
        wrong_converged += out["converged"] and not right
    assert main(["align", str(a), str(b), "--initial", "0", "0", "0", "--json"]) == 0      # a good guess
    capsys.readouterr()
    assert wrong_converged >= 1        # the far guesses do produce converged wrong poses, and exit 1


def test_merge_writes_a_map_in_as_frame(pair, tmp_path):
    a, b, truth = pair
    out = tmp_path / "merged.yaml"
    assert main(["merge", str(a), str(b), "--pose", *map(str, truth), "-o", str(out), "--mode", "raw"]) == 0
    merged = io.read_ros_map(out)
    grid_a = io.read_ros_map(a)
    assert merged.resolution == grid_a.resolution
    assert merged.known.sum() >= grid_a.known.sum()
    x0, x1, y0, y1 = merged.extent
    ax0, ax1, ay0, ay1 = grid_a.extent
    assert x0 <= ax0 and y0 <= ay0 and x1 >= ax1 and y1 >= ay1


def test_merge_plot_writes_the_picture_and_a_bad_one_is_bad_input_before_any_work(pair, tmp_path, capsys):
    a, b, truth = pair
    out, picture = tmp_path / "merged.yaml", tmp_path / "merged.png"
    args = ["merge", str(a), str(b), "--pose", *map(str, truth), "-o", str(out)]
    assert main([*args, "--plot", str(picture)]) == 0
    assert picture.stat().st_size > 10_000 and picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for bad in (str(tmp_path / "m.jpg"), str(tmp_path / "no" / "m.png"), str(a)):
        capsys.readouterr()
        assert main([*args, "-o", str(tmp_path / "other.yaml"), "--plot", bad]) == 2
        assert "taichi-match: error:" in capsys.readouterr().err
        assert not (tmp_path / "other.yaml").exists()


def test_merge_fuses_in_log_odds_and_respects_unknown():
    a = io.GridMap(np.array([[0.8, np.nan, 0.3, np.nan]]), 1.0)
    b = io.GridMap(np.array([[0.8, 0.6, np.nan, np.nan]]), 1.0)
    m = merge_maps(a, b, (0.0, 0.0, 0.0), fusion="log-odds")
    assert m.shape == (1, 4)
    assert m.prob[0, 0] == pytest.approx(0.64 / (0.64 + 0.04))
    assert m.prob[0, 1] == pytest.approx(0.6) and m.prob[0, 2] == pytest.approx(0.3) and np.isnan(m.prob[0, 3])


def test_merge_keeps_an_obstacle_either_map_saw_by_default():
    a = io.GridMap(np.array([[1.0, 0.0, 0.0, np.nan, np.nan]]), 1.0)
    b = io.GridMap(np.array([[0.0, 1.0, 0.0, 0.0, np.nan]]), 1.0)
    assert np.array_equal(merge_maps(a, b, (0.0, 0.0, 0.0)).prob, [[1.0, 1.0, 0.0, 0.0, np.nan]], equal_nan=True)
    # in log-odds a wall one map saw and the other saw through is erased (1/2: unknown in a map_server file)
    assert merge_maps(a, b, (0.0, 0.0, 0.0), fusion="log-odds").prob[0, 0] == pytest.approx(0.5)
    with pytest.raises(InvalidOptionError):
        merge_maps(a, b, (0.0, 0.0, 0.0), fusion="min")


def test_a_refusal_with_no_walls_compared_says_so_and_no_made_up_shares(tmp_path, capsys):
    # one wall cell each: whatever the pose, no wall lands within reach of the other's, and the
    # verdict's shares (defined as 0 agreeing and 1 conflicting when nothing is compared) are not
    # reported as findings
    p = np.zeros((3, 3))
    p[1, 1] = 1.0
    for name in ("a", "b"):
        io.write_ros_map(GridMap(p, 0.05), tmp_path / f"{name}.yaml")
    code = main(["align", str(tmp_path / "a.yaml"), str(tmp_path / "b.yaml"), "--json"])
    result = json.loads(capsys.readouterr().out)
    assert code == 1 and not result["accepted"] and result["evidence"]["walls_compared"] == 0
    assert "0 walls compared" in result["not_accepted_because"]
    assert "agree" not in result["not_accepted_because"] and "free space" not in result["not_accepted_because"]


def test_align_without_a_guess_searches_and_lists_the_hypotheses(tmp_path, capsys):
    truth = (0.3, -0.2, 2.2)
    a = rasterize(room_scene, (130, 170), 0.05, (-4.1, -3.1))
    b = rasterize(room_scene, (100, 120), 0.05, (-3.0, -2.5), pose_a2b=truth)
    io.write_ros_map(a, tmp_path / "a.yaml")
    io.write_ros_map(b, tmp_path / "b.yaml")
    code = main(["align", str(tmp_path / "a.yaml"), str(tmp_path / "b.yaml"), "--json"])
    result = json.loads(capsys.readouterr().out)
    assert code == 0 and result["accepted"] and len(result["hypotheses"]) >= 1
    assert result["search_complete"] is True and 0.0 < result["search_proven"] < 1.0
    assert np.allclose(result["pose"][:2], truth[:2], atol=0.05) and abs(result["pose"][2] - truth[2]) < 0.01
    # a window around a guess 1 m and 10 degrees off, in plain text
    code = main(["align", str(tmp_path / "a.yaml"), str(tmp_path / "b.yaml"), "--initial", "1.0", "0.5", "2.4",
                 "--window", "1.5", "20"])
    out = capsys.readouterr().out
    assert code == 0 and "searched" in out


def test_a_window_without_a_guess_is_bad_input(pair, capsys):
    a, b, _ = pair
    assert main(["align", str(a), str(b), "--window", "1", "10"]) == 2
    assert "--window needs --initial" in capsys.readouterr().err


def test_merge_without_a_pose_aligns_first(pair, tmp_path, capsys):
    a, b, truth = pair
    out = tmp_path / "merged.yaml"
    assert main(["merge", str(a), str(b), "-o", str(out)]) == 0
    assert "aligned:" in capsys.readouterr().out and out.exists()


def test_merge_without_a_pose_writes_nothing_when_the_alignment_is_ambiguous(tmp_path, capsys):
    from taichi_match.scenes import corridor

    a = corridor(size=8.0, resolution=0.05)
    b = rasterize(lambda x, y: np.where(np.abs(y) < 3.0, 0.0, np.where(np.abs(y) < 3.05, 1.0, np.nan)),
                  (140, 60), 0.05, (-1.5, -3.5), (1.3, 0.4, 0.0))
    io.write_ros_map(a, tmp_path / "a.yaml")
    io.write_ros_map(b, tmp_path / "b.yaml")
    out = tmp_path / "merged.yaml"
    assert main(["merge", str(tmp_path / "a.yaml"), str(tmp_path / "b.yaml"), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert "not accepted (ambiguous: a runner-up scores" in err and not out.exists()


def test_version(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.startswith("taichi-match ")


def test_degrees_reads_theta_in_degrees(pair, capsys):
    a, b, truth = pair
    deg = [str(truth[0] + 0.05), str(truth[1] - 0.05), str(math.degrees(truth[2]) + 2.0)]
    assert main(["align", str(a), str(b), "--initial", *deg, "--degrees", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert np.allclose(result["initial_pose"], [truth[0] + 0.05, truth[1] - 0.05, truth[2] + math.radians(2.0)])
    assert np.allclose(result["pose"], truth, atol=0.05)


def test_degrees_without_an_angle_to_read_is_bad_input(pair, capsys):
    a, b, _ = pair
    with pytest.raises(SystemExit) as stop:
        main(["align", str(a), str(b), "--degrees"])
    assert stop.value.code == 2 and "--degrees needs --initial" in capsys.readouterr().err


def test_plot_without_matplotlib_is_bad_input_before_any_work(pair, tmp_path, capsys, monkeypatch):
    import importlib.util

    a, b, _ = pair
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *args: None if name == "matplotlib" else real(name, *args))
    assert main(["align", str(a), str(b), "--initial", "0", "0", "0", "--plot", str(tmp_path / "o.png")]) == 2
    err = capsys.readouterr()
    assert "--plot needs matplotlib" in err.err and err.out == "" and not (tmp_path / "o.png").exists()


def test_a_bad_plot_path_is_bad_input_before_any_work(pair, tmp_path, capsys):
    a, b, _ = pair
    for plot in (str(tmp_path), str(tmp_path / "o.jpg"), str(tmp_path / "no" / "o.png")):
        assert main(["align", str(a), str(b), "--initial", "0", "0", "0", "--json", "--plot", plot]) == 2
        out = capsys.readouterr()
        assert out.out == "" and "picture" in out.err


def test_plot_never_writes_over_an_input(tmp_path, capsys):
    grid = rasterize(room_scene, (60, 60), 0.1, (-3.0, -3.0))
    io.write_ros_map(grid, tmp_path / "m.yaml", mode="scale")          # its image is m.png
    image = tmp_path / "m.png"
    before = image.read_bytes()
    assert main(["align", str(tmp_path / "m.yaml"), str(tmp_path / "m.yaml"), "--initial", "0", "0", "0",
                 "--plot", str(image)]) == 2
    assert "input" in capsys.readouterr().err and image.read_bytes() == before


def test_a_best_search_score_of_zero_prints_without_dividing_by_it(tmp_path, capsys):
    empty = io.GridMap(np.zeros((40, 40)), 0.1)                         # all free: nothing to meet B's walls
    io.write_ros_map(empty, tmp_path / "a.yaml")
    io.write_ros_map(rasterize(room_scene, (60, 60), 0.1, (-3.0, -3.0)), tmp_path / "b.yaml")
    assert main(["align", str(tmp_path / "a.yaml"), str(tmp_path / "b.yaml")]) == 1
    out = capsys.readouterr()
    assert "not accepted" in out.out and out.err == ""


def test_merge_keeps_the_walls_of_a_finer_b():
    a = io.GridMap(np.zeros((20, 20)), 0.1)                              # 2 x 2 m, all free
    fine = np.zeros((40, 40))
    fine[16, 5:35] = 1.0                                                 # a wall one fine cell thick
    b = io.GridMap(fine, 0.05)
    merged = merge_maps(a, b, (0.0, 0.0, 0.0))
    # the fine wall, y in [0.80, 0.85) and x in [0.25, 1.75) m, lies in the merged row 8, columns 2-17
    # (its cells miss every merged cell's centre: one sample per merged cell would lose it all)
    assert np.all(merged.prob[8, 2:18] == 1.0) and np.count_nonzero(merged.prob == 1.0) == 16


@pytest.mark.parametrize("resolution", [0, -1.0, float("nan"), "x"])
def test_merge_refuses_a_bad_resolution(resolution):
    a = io.GridMap(np.zeros((4, 4)), 0.1)
    with pytest.raises(InvalidOptionError, match="resolution"):
        merge_maps(a, a, (0.0, 0.0, 0.0), resolution=resolution)


def write_pairs(path, rows):
    path.write_text("\n".join(",".join(str(v) for v in row) for row in rows) + "\n")
    return path


def test_align_many_writes_a_line_per_pair_in_order(pair, tmp_path, capsys):
    a, b, truth = pair
    pairs = write_pairs(tmp_path / "pairs.csv", [
        ("map_a", "map_b", "x", "y", "theta"), ("a.yaml", "b.yaml", 0, 0, 0), ("# a comment",),
        ("a.yaml", "b.yaml", 0.1, 0.0, math.degrees(0.02)), ("a.yaml", "missing.yaml", 0, 0, 0), ("a.yaml", "b.yaml")])
    code = main(["align-many", str(pairs), "--degrees", "-o", str(tmp_path / "out.jsonl")])
    lines = [json.loads(line) for line in (tmp_path / "out.jsonl").read_text().splitlines()]
    assert code == 1                                   # one pair failed: not every pair accepted
    assert "3 of 4 pairs accepted" in capsys.readouterr().err
    assert [line["row"] for line in lines] == [2, 4, 5, 6]
    assert "missing.yaml" in lines[2]["error"] and "pose" not in lines[2]
    for line in (lines[0], lines[1], lines[3]):        # with a guess, in degrees, and without one
        assert line["accepted"] and np.allclose(line["pose"], truth, atol=0.05)
    assert lines[1]["initial_pose"][2] == pytest.approx(0.02)
    main(["align", str(a), str(b), "--initial", "0", "0", "0", "--json"])
    expected = json.loads(capsys.readouterr().out)
    assert lines[0]["pose"] == expected["pose"] and lines[0]["covariance"] == expected["covariance"]


def test_align_many_never_writes_over_an_input_maps_image(pair, tmp_path, capsys):
    """--force replaces an earlier output, never a file a pair reads: the CSV, a YAML, or the image
    a YAML names."""
    pairs = write_pairs(tmp_path / "pairs.csv", [("a.yaml", "b.yaml", 0, 0, 0)])
    image = tmp_path / "b.pgm"
    before = image.read_bytes()
    assert main(["align-many", str(pairs), "-o", str(image), "--force"]) == 2
    assert "it is an input" in capsys.readouterr().err and image.read_bytes() == before


def test_merge_refuses_a_map_far_finer_than_the_merged_one(pair, tmp_path, capsys):
    """A map 500 times finer than the merged map would take 500 x 500 samples per merged cell
    (1e-300 m: forever): refused at once."""
    a, b, _ = pair
    text = b.read_text()
    fine = tmp_path / "fine.yaml"
    fine.write_text("\n".join("resolution: 0.0001" if line.startswith("resolution") else line
                              for line in text.splitlines()) + "\n")
    assert main(["merge", str(a), str(fine), "--pose", "0", "0", "0", "-o", str(tmp_path / "m.yaml")]) == 2
    assert "finer" in capsys.readouterr().err and not (tmp_path / "m.yaml").exists()


def test_align_many_force_replaces_its_output_only_once_complete(pair, tmp_path, capsys, monkeypatch):
    """With --force an earlier output stays as it was when the run is interrupted (no partial file,
    no temporary left behind), and is replaced when the run completes."""
    import taichi_match

    pairs = write_pairs(tmp_path / "pairs.csv", [("a.yaml", "b.yaml", 0, 0, 0), ("b.yaml", "a.yaml", 0, 0, 0)])
    output = tmp_path / "out.jsonl"
    output.write_text("earlier\n")
    real = taichi_match.iter_matches

    def interrupted(*args, **kwargs):
        results = real(*args, **kwargs)
        yield next(results)
        raise KeyboardInterrupt

    monkeypatch.setattr(taichi_match, "iter_matches", interrupted)
    try:
        main(["align-many", str(pairs), "-o", str(output), "--force"])
    except KeyboardInterrupt:
        pass
    hidden = [path.name for path in tmp_path.iterdir() if path.name.startswith(".")]
    assert output.read_text() == "earlier\n" and hidden == []
    monkeypatch.setattr(taichi_match, "iter_matches", real)
    assert main(["align-many", str(pairs), "-o", str(output), "--force"]) == 0
    assert [json.loads(line)["row"] for line in output.read_text().splitlines()] == [1, 2]


def test_align_many_on_two_workers_gives_the_same_lines(pair, tmp_path, capsys):
    pairs = write_pairs(tmp_path / "pairs.csv", [("a.yaml", "b.yaml", 0, 0, 0), ("b.yaml", "a.yaml", 0, 0, 0),
                                                 ("a.yaml", "b.yaml", 0.1, 0.1, 0.0)])
    assert main(["align-many", str(pairs)]) == 0
    serial = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert main(["align-many", str(pairs), "--workers", "2", "--chunk-size", "1"]) == 0
    parallel = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    drop = ("seconds",)
    assert [{k: v for k, v in d.items() if k not in drop} for d in parallel] == \
        [{k: v for k, v in d.items() if k not in drop} for d in serial]


@pytest.mark.parametrize("rows, message", [([("a.yaml",)], "a row is"), ([("a.yaml", "b.yaml", "x", 0, 0)], "numbers"),
                                           ([("# nothing",)], "no pairs")])
def test_align_many_bad_pairs_files_are_bad_input(pair, tmp_path, capsys, rows, message):
    pairs = write_pairs(tmp_path / "pairs.csv", rows)
    assert main(["align-many", str(pairs)]) == 2
    assert message in capsys.readouterr().err


def test_align_many_refuses_to_overwrite(pair, tmp_path, capsys):
    pairs = write_pairs(tmp_path / "pairs.csv", [("a.yaml", "b.yaml", 0, 0, 0)])
    assert main(["align-many", str(pairs), "-o", str(pairs), "--force"]) == 2
    assert "is an input" in capsys.readouterr().err and pairs.read_text().startswith("a.yaml")
    (tmp_path / "out.jsonl").write_text("keep")
    assert main(["align-many", str(pairs), "-o", str(tmp_path / "out.jsonl")]) == 2
    assert (tmp_path / "out.jsonl").read_text() == "keep"
    assert main(["align-many", str(tmp_path / "none.csv")]) == 2
    assert main(["align-many", str(pairs), "--workers", "0"]) == 2
    assert main(["align-many", str(pairs), "--workers", "1000"]) == 2
    assert "workers" in capsys.readouterr().err


def test_a_progress_bar_whose_stderr_closed_lets_the_work_go_on(monkeypatch):
    # `taichi-match slam ... --progress 2>&1 | head -c 10`: the bar's writes fail once the reader has
    # left, and the run lost its outputs with them
    pytest.importorskip("tqdm")
    from taichi_match import cli

    class Closing:
        closed = False

        def write(self, text):
            if self.closed:
                raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            self.write("")

    stream = Closing()
    monkeypatch.setattr(cli.sys, "stderr", stream)
    bar = cli._progress("slam", 3, True)
    stream.closed = True                               # the reader leaves part-way
    for done in (1, 2, 3):
        bar(done, 3)                                   # no error
    assert cli._progress("slam", 3, True) is None      # closed before the bar: no bar
