"""Taichi hygiene and the reusable matcher: lazy init, silence, host runtime, fork, no recompiles."""

import ast
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import random_map

from taichi_match import GridMap, Matcher, _kernels, _launch, discrepancy


def run_python(code, timeout=300):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("TI_", "ENABLE_TAICHI"))}
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=timeout, env=env)


def test_import_does_not_start_taichi_and_a_match_prints_nothing():
    out = run_python("""
        import os, sys
        import numpy as np
        import taichi_match as tm
        import taichi_match.cli
        eager = {"taichi", "scipy", "matplotlib"} & set(sys.modules)
        assert not eager, f"imported eagerly: {eager}"   # `taichi-match --help` answers fast
        a = tm.GridMap(np.zeros((30, 30)), 0.1)
        res = tm.match(a, a, (0.0, 0.0, 0.0))
        assert os.environ["TI_SKIP_VERSION_CHECK"] == "ON"
        import taichi as ti
        assert ti.lang.impl.get_runtime().prog is not None
    """)
    assert out.returncode == 0, out.stderr
    assert out.stdout == "" and out.stderr == ""


def test_offline_cache_follows_ti_offline_cache_silently():
    """With ``TI_OFFLINE_CACHE=0`` (as helper processes run) Taichi starts without its offline
    cache, and without the warning it gives when an argument overrides the variable."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("TI_", "ENABLE_TAICHI"))}
    out = subprocess.run([sys.executable, "-c", textwrap.dedent("""
        import numpy as np
        import taichi_match as tm
        a = tm.GridMap(np.zeros((30, 30)), 0.1)
        tm.match(a, a, (0.0, 0.0, 0.0))
        import taichi as ti
        assert not ti.lang.impl.current_cfg().offline_cache
    """)], capture_output=True, text=True, timeout=300, env=dict(env, TI_OFFLINE_CACHE="0"))
    assert out.returncode == 0, out.stderr
    assert out.stdout == "" and out.stderr == ""


def test_a_host_runtime_is_reused_not_reset():
    out = run_python("""
        import contextlib, io
        import numpy as np
        with contextlib.redirect_stdout(io.StringIO()):
            import taichi as ti
            ti.init(arch=ti.cpu)
        prog = ti.lang.impl.get_runtime().prog
        field = ti.field(ti.f32, shape=4)
        field[2] = 7.0
        import taichi_match as tm
        a = tm.GridMap(np.zeros((30, 30)), 0.1)
        tm.match(a, a, (0.0, 0.0, 0.0))
        assert ti.lang.impl.get_runtime().prog is prog
        assert field[2] == 7.0
    """)
    assert out.returncode == 0, out.stderr


def test_matching_goes_on_after_a_host_initialises_or_resets_taichi_again():
    # the direct launch path keeps compiled kernels of one Taichi program; a new ti.init or a
    # ti.reset must send the next call the ordinary way (it crashed with std::bad_alloc before)
    out = run_python("""
        import contextlib, io
        import numpy as np
        import taichi_match as tm
        from taichi_match.scenes import corridor
        g = corridor(size=4.0, width=2.0, resolution=0.05)
        first = tm.match(g, g, (0.1, 0.1, 0.05))
        import taichi as ti
        with contextlib.redirect_stdout(io.StringIO()):
            ti.init(arch=ti.cpu)
        again = tm.match(g, g, (0.1, 0.1, 0.05))
        ti.reset()
        third = tm.match(g, g, (0.1, 0.1, 0.05))
        assert np.allclose(first.pose, again.pose) and np.allclose(first.pose, third.pose), (first, again, third)
        assert abs(first.pose[1]) < 0.05
        # a map prepared after the reset: the distance transform's kernel is compiled anew too
        h = corridor(size=4.0, width=2.5, resolution=0.05)
        fourth = tm.match(h, h, (0.1, 0.1, 0.05))
        assert abs(fourth.pose[1]) < 0.05 and fourth.converged
    """)
    assert out.returncode == 0, out.stderr


def test_a_child_forked_after_initialisation_gets_an_error_not_a_hang():
    out = run_python("""
        import os
        import numpy as np
        import taichi_match as tm
        a = tm.GridMap(np.zeros((30, 30)), 0.1)
        tm.discrepancy(a, a, [(0.0, 0.0, 0.0)])
        pid = os.fork()
        if pid == 0:
            try:
                tm.discrepancy(a, a, [(0.0, 0.0, 0.0)])
            except tm.EngineError as exc:
                os._exit(0 if "spawn" in str(exc) else 3)
            os._exit(2)
        _, status = os.waitpid(pid, 0)
        raise SystemExit(os.waitstatus_to_exitcode(status))
    """)
    assert out.returncode == 0, (out.returncode, out.stderr)


def test_a_hundred_children_forked_while_another_thread_matches_get_an_error_and_none_hangs():
    # the thread holds the kernel lock (and the matcher's cache lock) much of the time: a child
    # forked then must not wait for a lock nobody in it will release
    out = run_python("""
        import os, threading, time
        import taichi_match as tm
        from taichi_match.scenes import corridor
        g = corridor(size=4.0, width=2.0, resolution=0.05)
        tm.match(g, g, (0.1, 0.1, 0.05))
        stop = threading.Event()
        def busy():
            while not stop.is_set():
                tm.match(g, g, (0.1, 0.1, 0.05))
        thread = threading.Thread(target=busy)
        thread.start()
        codes = []
        for _ in range(100):
            pid = os.fork()
            if pid == 0:
                try:
                    tm.match(g, g, (0.1, 0.1, 0.05))
                except tm.EngineError:
                    os._exit(0)
                os._exit(2)
            deadline = time.monotonic() + 20.0
            while True:
                done, status = os.waitpid(pid, os.WNOHANG)
                if done:
                    codes.append(os.waitstatus_to_exitcode(status))
                    break
                if time.monotonic() > deadline:
                    os.kill(pid, 9)
                    os.waitpid(pid, 0)
                    codes.append("hung")
                    break
                time.sleep(0.002)
        stop.set()
        thread.join()
        assert codes == [0] * 100, {c: codes.count(c) for c in set(codes)}
    """, timeout=600)
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])


def test_a_child_forked_after_the_host_initialised_taichi_gets_an_error():
    out = run_python("""
        import contextlib, io, os
        import numpy as np
        with contextlib.redirect_stdout(io.StringIO()):
            import taichi as ti
            ti.init(arch=ti.cpu)
        import taichi_match as tm
        a = tm.GridMap(np.zeros((30, 30)), 0.1)
        pid = os.fork()
        if pid == 0:
            try:
                tm.discrepancy(a, a, [(0.0, 0.0, 0.0)])
            except tm.EngineError:
                os._exit(0)
            os._exit(2)
        _, status = os.waitpid(pid, 0)
        raise SystemExit(os.waitstatus_to_exitcode(status))
    """)
    assert out.returncode == 0, (out.returncode, out.stderr)


def test_maps_of_new_sizes_do_not_recompile(rng):
    kernels = _kernels.dense_kernels()

    def compiled():
        return [len(k._primal.compiled_kernels) for k in kernels]

    def use(shapes):
        for shape in shapes:
            b = random_map(rng, shape, 0.05, (-1.0, -1.0))
            discrepancy(b, b, rng.uniform(-1, 1, (7, 3)))
            Matcher().match(b, b, (0.01, 0.0, 0.0))

    use([(30, 40), (480, 480)])              # small and large maps: every variant a match uses
    before = compiled()
    use([(17, 301), (500, 460), (5, 3)])
    assert compiled() == before
    assert before[0] <= len(_kernels.COUNT_MODES) and before[1] <= 2


def test_matcher_caches_prepared_maps_per_blur():
    grid = GridMap(np.zeros((10, 10)), 0.1)
    m = Matcher()
    first = m.prepare(grid)
    assert m.prepare(grid) is first
    assert m.prepare(grid, blur=0.3) is not first
    assert m.prepare(grid, blur=0.3).blur_width == 0.3


def test_same_inputs_give_bit_identical_poses_across_processes():
    code = """
        import numpy as np
        import taichi_match as tm
        from taichi_match.scenes import corridor
        a = corridor()
        res = tm.match(a, a, (0.7, -0.9, 0.25))
        print(" ".join(float(v).hex() for v in np.concatenate([res.pose, res.covariance.ravel()])))
    """
    first, second = run_python(code), run_python(code)
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    assert first.stdout == second.stdout and first.stdout.strip()


def test_matches_from_several_threads_equal_serial_ones():
    from concurrent.futures import ThreadPoolExecutor

    from taichi_match.scenes import corridor

    grid = corridor(size=6.0, resolution=0.05, width=3.0)
    starts = np.random.default_rng(4).uniform(-1, 1, (8, 3)) * (0.5, 0.5, 0.2)
    matcher = Matcher()
    serial = [matcher.match(grid, grid, r0).pose for r0 in starts]
    with ThreadPoolExecutor(max_workers=4) as pool:
        threaded = list(pool.map(lambda r0: matcher.match(grid, grid, r0).pose, starts))
    assert all(np.array_equal(s, t) for s, t in zip(serial, threaded))


def test_a_spawn_process_pool_gives_the_serial_answers():
    """Process pools must use 'spawn' (or 'forkserver'): a child forked after Taichi started hangs."""
    import multiprocessing

    from _pool_worker import match_pose

    starts = [tuple(r) for r in np.random.default_rng(9).uniform(-1, 1, (4, 3)) * (0.4, 0.4, 0.15)]
    serial = [match_pose(r0) for r0 in starts]
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        parallel = pool.map(match_pose, starts)
    assert parallel == serial


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads VmRSS from /proc (Linux)")
def test_resident_memory_stays_flat_over_repeated_matches():
    """The short version of bench/realtime.py's 10,000-match check."""
    from taichi_match.scenes import corridor

    def rss_kib():
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))

    grid = corridor(size=4.0, resolution=0.05, width=2.0)
    matcher = Matcher()
    starts = np.random.default_rng(10).uniform(-1, 1, (600, 3)) * (0.2, 0.2, 0.1)
    for r0 in starts[:100]:
        matcher.match(grid, grid, r0)
    before = rss_kib()
    for r0 in starts[100:]:
        matcher.match(grid, grid, r0)
    assert rss_kib() <= before * 1.05


def test_the_matcher_cache_lets_maps_go():
    """A prepared map must not keep its source map alive (the cache is keyed weakly by it)."""
    import gc
    import weakref

    matcher = Matcher()
    grid = GridMap(np.random.default_rng(0).random((40, 40)), 0.05)
    matcher.match(grid, grid, (0.01, 0.0, 0.0))
    assert len(matcher._cache) == 1
    ref = weakref.ref(grid)
    del grid
    gc.collect()
    assert ref() is None and len(matcher._cache) == 0


def test_the_direct_launch_path_equals_taichis_own_call(rng):
    # _launch bypasses Taichi's argument handling after the first call; it must give the same
    # numbers as an ordinary kernel call for every shape, and for arrays in Fortran order too
    kernels = _kernels.dense_kernels()
    for shape_a, shape_b, order in (((40, 50), (20, 30), "C"), ((33, 21), (17, 9), "F"), ((8, 90), (5, 60), "C")):
        a = np.asarray(rng.random(shape_a), dtype=np.float32, order=order)
        b = np.ascontiguousarray(rng.random(shape_b), dtype=np.float32)
        rows = np.array([[i, 1, shape_b[1] - 2] for i in range(shape_b[0])], dtype=np.int32)
        affine = np.array([[np.cos(t), -np.sin(t), 3.0, np.sin(t), np.cos(t), 2.0] for t in (0.0, 0.1, -0.2)])
        for mode in (0, 2):
            expected = np.zeros((2 if mode else 1, 3, shape_b[0]), np.float32)
            kernels.poses(np.ascontiguousarray(a), b, rows, affine, expected, mode)
            for _ in range(3):                               # the first call compiles, then direct
                out = np.zeros_like(expected)
                _launch.launch(kernels.poses, (a, b, rows, affine, out), mode)
                assert np.array_equal(out, expected)


@pytest.mark.parametrize("rows", [1, 7, 100, 500, 4000, 10**5])
def test_row_spread_gives_enough_items_to_spread(rows):
    from taichi_match._launch import ROW_ITEMS, row_spread

    spread = row_spread(rows)
    assert rows * len(spread) >= ROW_ITEMS and (len(spread) == 1 or rows * (len(spread) - 1) < ROW_ITEMS)


@pytest.mark.parametrize("start, expected", [
    ("import taichi_match._taichi as tt; tt.taichi()", "accepted True"),     # ours, in the main thread
    ("", "accepted True"),                                                    # ours, started in the thread
    ("import taichi as ti; ti.init(arch=ti.cpu, log_level=ti.WARN)", "EngineError: Taichi was started"),
])
def test_the_first_match_may_come_from_another_thread(start, expected):
    """Taichi 1.7 asserts that its first compile runs in the thread that called ``ti.init``. With
    Taichi started by the package in the main thread, a first match from another thread (a ROS
    executor's) works; with Taichi started by the host there and nothing compiled yet, it is an
    EngineError that says what to do, not Taichi's RuntimeError. A fresh interpreter each."""
    code = textwrap.dedent(f"""
        import threading
        {start}
        from taichi_match import EngineError, Matcher
        from taichi_match.scenes import room
        out = []
        def work():
            try:
                grid = room()
                out.append(f"accepted {{Matcher().match(grid, grid, (0.05, 0.0, 0.0)).accepted}}")
            except EngineError as exc:
                out.append(f"EngineError: {{exc}}")
        thread = threading.Thread(target=work)
        thread.start()
        thread.join()
        print(out[0])
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and expected in done.stdout, (done.stdout, done.stderr[-2000:])


def test_our_kernels_compile_without_source_excerpts_a_hosts_keep_them(tmp_path):
    """Taichi 1.7's frontend formats a source excerpt for every syntax node it compiles; for this
    package's kernels only the file, line and kernel are kept (``_taichi._plain_source_lines``),
    for any other file (a host's kernels) Taichi's excerpt with its carets."""
    from types import SimpleNamespace

    from taichi_match import _taichi

    ti = _taichi.taichi()
    if tuple(ti.__version__)[:2] != (1, 7):
        pytest.skip("written for Taichi 1.7's frontend")
    context = ti.lang.ast.ast_transformer_utils.ASTTransformerContext
    node = ast.parse("total = walls + 1").body[0]

    def pos_info(file):
        ctx = SimpleNamespace(file=file, lineno_offset=4, indent=0, src=["total = walls + 1"],
                              func=SimpleNamespace(func=random_map))
        return context.get_pos_info(ctx, node)

    ours, host = _taichi.__file__, str(tmp_path / "host.py")
    assert pos_info(ours) == f'File "{ours}", line 5, in random_map:\n'
    assert pos_info(host).startswith(f'File "{host}", line 5, in random_map:\ntotal = walls + 1\n^^^^')
