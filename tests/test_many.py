"""match_many: the results of one match each, in order, in this process or spread over workers."""

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

import numpy as np
import pytest

import taichi_match as tm
from taichi_match.simulate import floor_plan


def crops(world, windows):
    """Crops of ``world`` (rows, cols slices), each keeping the world's frame (so r_A2B = 0)."""
    res = world.resolution
    x0, y0 = world.origin
    return [tm.GridMap(world.prob[r0:r1, c0:c1], res, (x0 + c0 * res, y0 + r0 * res)) for r0, r1, c0, c1 in windows]


@pytest.fixture(scope="module")
def tasks():
    world = floor_plan(0)
    h, w = world.shape
    windows = [(0, h // 2 + 40, 0, w // 2 + 40), (h // 2 - 40, h, 0, w // 2 + 40),
               (0, h // 2 + 40, w // 2 - 40, w), (h // 2 - 40, h, w // 2 - 40, w),
               (h // 4, 3 * h // 4, w // 4, 3 * w // 4)]
    maps = crops(world, windows)
    rng = np.random.default_rng(3)
    out = []
    for i in range(len(maps)):
        for j in range(len(maps)):
            if i != j:
                out.append((maps[i], maps[j], rng.uniform(-1, 1, 3) * (0.2, 0.2, 0.05)))
    return out


def same(results, expected):
    return all(np.array_equal(r.pose, e.pose) and np.array_equal(r.covariance, e.covariance)
               and r.status == e.status and r.accepted == e.accepted for r, e in zip(results, expected))


@pytest.fixture(scope="module")
def one_each(tasks):
    """The oracle: a fresh matcher per task, so nothing is shared between them."""
    return [tm.Matcher().match(a, b, guess) for a, b, guess in tasks]


def test_in_process_gives_one_match_each_in_order(tasks, one_each):
    results = tm.match_many(tasks)
    assert len(results) == len(tasks) and same(results, one_each)
    # the overlapping crops are placed where the world puts them
    assert sum(r.accepted and np.abs(r.pose[:2]).max() < 0.1 for r in results) >= len(tasks) // 2


def test_options_reach_every_task(tasks):
    results = tm.match_many(tasks[:3], levels=1, blur=0.15)
    assert same(results, [tm.match(a, b, g, levels=1, blur=0.15) for a, b, g in tasks[:3]])
    assert all(r.options.levels == 1 and r.options.blur == 0.15 for r in results)


def test_a_spawned_process_pool_gives_the_same_bits(tasks, one_each):
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        results = tm.match_many(tasks, executor=pool)
        small_chunks = tm.match_many(tasks, executor=pool, chunk_size=3)
    assert same(results, one_each) and same(small_chunks, one_each)


def test_a_local_pool_gets_the_maps_as_files_removed_after_the_call(tasks, one_each, monkeypatch):
    import os
    import tempfile

    from taichi_match import many

    folders, made = [], tempfile.mkdtemp

    def mkdtemp(**kwargs):
        folders.append(made(**kwargs))
        return folders[-1]

    monkeypatch.setattr(many.tempfile, "mkdtemp", mkdtemp)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        assert same(tm.match_many(tasks, executor=pool), one_each)
        assert len(folders) == 1 and not os.path.exists(folders[0])
        # a consumer that stops early: the files go when the generator is closed
        outcomes = many.iter_matches(tasks, executor=pool, chunk_size=2)
        next(outcomes)
        assert len(os.listdir(folders[1])) == 5                  # each distinct map once
        outcomes.close()
        assert not os.path.exists(folders[1])


def test_a_killed_callers_folder_is_removed_by_the_next_call(tmp_path):
    import subprocess
    import sys

    from taichi_match import many

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead = int(gone.stdout)                                   # a process that has ended
    orphan = tmp_path / f"{many._Handover.PREFIX}{dead}-abc"
    orphan.mkdir()
    (orphan / "0.npy").write_bytes(b"x")
    alive = tmp_path / f"{many._Handover.PREFIX}{os.getppid()}-def"      # a live process's: kept
    alive.mkdir()
    other = tmp_path / "taichi_match-notes"                    # not a hand-over folder: kept
    other.mkdir()
    many._remove_orphans(str(tmp_path), many._Handover.PREFIX)
    assert not orphan.exists() and alive.exists() and other.exists()


def test_maps_go_through_the_executor_where_no_file_can_be_made(tasks, one_each, monkeypatch):
    from taichi_match import many

    def refuse(**kwargs):
        raise OSError("no space left on device")

    monkeypatch.setattr(many.tempfile, "mkdtemp", refuse)
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        assert same(tm.match_many(tasks[:6], executor=pool), one_each[:6])


def test_probability_maps_go_to_workers_whole(tasks):
    few = tasks[:4]
    expected = [tm.match(a, b, g, evidence="probability") for a, b, g in few]
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        assert same(tm.match_many(few, executor=pool, evidence="probability"), expected)


def test_a_thread_pool_works_too(tasks, one_each):
    with ThreadPoolExecutor(2) as pool:
        assert same(tm.match_many(tasks, executor=pool, chunk_size=4), one_each)


def test_tasks_without_a_guess_are_searched(tasks):
    a, b, _ = tasks[0]
    expected = tm.match(a, b)
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        (result,) = tm.match_many([(a, b)], executor=pool)
    assert same([result], [expected]) and result.hypotheses


def test_iter_matches_yields_every_index_once(tasks):
    seen = [index for index, _ in tm.iter_matches(tasks[:5])]
    assert sorted(seen) == list(range(5))


def test_dask_local_cluster_gives_the_same_bits(tasks, one_each):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  worker_class=distributed.Nanny) as cluster, distributed.Client(cluster) as client:
        results = tm.match_many(tasks, executor=client.get_executor())
    assert same(results, one_each)


def test_bad_tasks_and_options_are_clear_errors(tasks):
    a, b, guess = tasks[0]
    with pytest.raises(tm.InvalidOptionError, match="task 1 must be"):
        tm.match_many([(a, b), (a,)])
    with pytest.raises(tm.InvalidOptionError, match="task 0 must be"):
        tm.match_many([(a, b, guess, "extra")])
    with pytest.raises(tm.InvalidMapError, match="task 1: b must be a GridMap"):
        tm.match_many([(a, b), (a, np.zeros((4, 4)))])
    with pytest.raises(tm.InvalidOptionError):
        tm.match_many([(a, b)], blur=-1.0)
    with pytest.raises(tm.InvalidOptionError, match="errors"):
        tm.match_many([(a, b)], errors="ignore")
    with ThreadPoolExecutor(1) as pool, pytest.raises(tm.InvalidOptionError, match="chunk_size"):
        tm.match_many([(a, b)], executor=pool, chunk_size=0)
    assert tm.match_many([]) == []


def test_a_bad_guess_fails_its_task_only_when_asked(tasks):
    a, b, guess = tasks[0]
    bad = [(a, b, guess), (a, b, (np.nan, 0.0, 0.0)), (a, b, guess)]
    with pytest.raises(tm.InvalidPoseError, match="task 1"):
        tm.match_many(bad)
    results = tm.match_many(bad, errors="return")
    assert isinstance(results[1], tm.InvalidPoseError)
    assert np.array_equal(results[0].pose, results[2].pose)
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        returned = tm.match_many(bad, executor=pool, errors="return")
        assert isinstance(returned[1], tm.InvalidPoseError) and np.array_equal(returned[0].pose, results[0].pose)
        with pytest.raises(tm.InvalidPoseError, match="task 1"):
            tm.match_many(bad, executor=pool)


@pytest.mark.parametrize("count, chunks", [(0, 2), (1, 4), (5, 2), (40, 3), (1225, 2), (100, 100)])
def test_chunks_deal_every_task_out_once(count, chunks):
    from taichi_match.many import BLOCK, _chunks

    out = _chunks(count, chunks)
    assert sorted(k for c in out for k in c) == list(range(count))
    assert len(out) <= max(chunks, 1) and all(c for c in out)
    if count >= 2 * BLOCK * chunks:                       # blocks of BLOCK consecutive tasks
        assert out[0][:BLOCK] == list(range(BLOCK)) and out[1 % len(out)][0] == BLOCK


def test_default_chunks_follow_how_tasks_share_maps():
    from taichi_match.many import _default_chunk_size

    maps = [tm.GridMap(np.zeros((4, 4)), 0.1) for _ in range(65)]
    # a loop's consecutive pairs (m_i, m_i+1): one chunk per worker (2 chunks, blocks of 16 dealt
    # in turn) names 34 + 34 = 68 maps; 8 chunks of 8 consecutive pairs name 8 x 9 = 72, within
    # 10 % more: 8 tasks a chunk
    consecutive = [(maps[i], maps[i + 1], None) for i in range(64)]
    assert _default_chunk_size(consecutive, 2) == 8
    # an all-pairs check of 10 maps (45 pairs): 2 chunks name 10 + 9 maps, 4 chunks 31: one chunk
    # per worker
    pairs = [(maps[i], maps[j], None) for i in range(10) for j in range(i + 1, 10)]
    assert _default_chunk_size(pairs, 2) == 23
    # one task: one chunk
    assert _default_chunk_size(consecutive[:1], 4) == 1
