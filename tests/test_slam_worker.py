"""The mapping loop in a worker process (``slam_worker.SlamWorker``): the same result as
``Slam.add`` in this process bit for bit, a ``submit`` that does not wait, refusals in the
caller's thread, and a worker that dies or refuses handed back as errors."""

import dataclasses
import os
import signal

import numpy as np
import pytest

from taichi_match import GridMap, InvalidOptionError, SlamRunError
from taichi_match.simulate import simulate_log

pytest.importorskip("gtsam")
if os.name != "posix":                                        # pragma: no cover
    pytest.skip("SlamWorker needs POSIX", allow_module_level=True)

from taichi_match.slam import Slam  # noqa: E402  (needs gtsam)
from taichi_match.slam_worker import SlamWorker  # noqa: E402


@pytest.fixture(scope="module")
def scans():
    return simulate_log(1, laps=0.4).log.scans


def _plain(scans):
    """``Slam.add`` scan by scan in this process: each scan's pose when it was mapped, and the result."""
    mapper = Slam()
    added = [mapper.add(scan) for scan in scans]
    return np.array(added), mapper.finish()


@pytest.fixture(scope="module")
def plain(scans):
    return _plain(scans)


def test_the_worker_maps_the_scans_as_slam_add_does_here(scans, plain):
    """Every scan submitted at once, before the worker has even started: the poses, each scan's
    pose when it was mapped, the graph and the loop closures are those of ``Slam.add`` in this
    process, bit for bit."""
    added, result = plain
    with SlamWorker() as mapper:
        for k, scan in enumerate(scans):
            assert mapper.submit(scan) == k
        assert mapper.backlog > 0                 # the worker takes a second to start: submit did not wait
        done = mapper.finish()
        index, pose = mapper.latest()
    assert np.array_equal(done.poses, result.poses)
    assert index == len(scans) - 1 and np.array_equal(pose, added[-1])
    assert done.graph.size() == result.graph.size() and len(done.loops) == len(result.loops)
    assert mapper.backlog == 0 and len(mapper.delays) == len(scans) and np.all(mapper.delays >= 0)


def test_refused_scans_are_refused_in_the_callers_thread(scans, plain):
    """A scan ``Slam.add`` refuses (a NaN pose, a timestamp that does not increase, an odometry jump
    beyond a ray's reach) raises at ``submit`` and is not queued; the run goes on, and its result
    is that of the good scans alone. The poses and the map of the scans so far come back."""
    _, result = plain
    bad_pose = dataclasses.replace(scans[1], pose=np.array([np.nan, 0.0, 0.0]))
    stale = dataclasses.replace(scans[1], timestamp=scans[0].timestamp)
    jump = dataclasses.replace(scans[1], pose=scans[1].pose + np.array([50.0, 0.0, 0.0]))
    with SlamWorker() as mapper:
        mapper.submit(scans[0])
        for bad, what in ((bad_pose, "pose"), (stale, "timestamps must increase"), (jump, "jumps")):
            with pytest.raises(InvalidOptionError, match=what):
                mapper.submit(bad)
        for scan in scans[1:12]:
            mapper.submit(scan)
        assert len(mapper.poses) == 12 and isinstance(mapper.current_map(), GridMap)
        for scan in scans[12:]:
            mapper.submit(scan)
        assert np.array_equal(mapper.finish().poses, result.poses)


def test_a_refused_finish_leaves_the_run_going(scans):
    """``finish`` with no usable beam yet is refused (InvalidOptionError), as ``Slam.finish``
    refuses it, and the run goes on: the scans after it finish it, with ``Slam.add``'s result."""
    blind = [dataclasses.replace(scan, ranges=np.full_like(scan.ranges, np.nan)) for scan in scans[:3]]
    _, expected = _plain(blind + list(scans[3:20]))
    with SlamWorker() as mapper:
        for scan in blind:
            mapper.submit(scan)
        with pytest.raises(InvalidOptionError, match="no usable beam"):
            mapper.finish()
        for scan in scans[3:20]:
            mapper.submit(scan)
        assert np.array_equal(mapper.finish().poses, expected.poses)


def test_a_worker_that_dies_is_an_error_for_the_caller(scans):
    """The worker process killed: ``finish`` raises SlamRunError saying the process ended, then
    every call does; ``close`` still ends it."""
    mapper = SlamWorker()
    for scan in scans[:5]:
        mapper.submit(scan)
    os.kill(mapper._link.process.pid, signal.SIGKILL)
    with pytest.raises(SlamRunError, match="process ended"):
        mapper.finish()
    with pytest.raises(SlamRunError, match="process ended"):
        mapper.submit(scans[5])
    mapper.close()
    with pytest.raises(SlamRunError, match="closed"):
        mapper.submit(scans[5])


def test_after_finish_or_close_nothing_more_is_taken(scans):
    """``finish`` and ``close`` end the SlamWorker and its process: ``submit``, ``finish`` and the
    poses then raise SlamRunError; ``close`` may be called again."""
    mapper = SlamWorker()
    for scan in scans[:12]:
        mapper.submit(scan)
    process = mapper._link.process
    mapper.close()
    mapper.close()
    assert process.poll() is not None
    for call in (lambda: mapper.submit(scans[12]), mapper.finish, lambda: mapper.poses):
        with pytest.raises(SlamRunError, match="closed"):
            call()
    finished = SlamWorker()
    for scan in scans[:12]:
        finished.submit(scan)
    finished.finish()
    with pytest.raises(SlamRunError, match="finished"):
        finished.submit(scans[12])


def test_the_readme_worker_example_runs():
    """The README's Python block for ``SlamWorker``, run as written: every scan mapped."""
    import re
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = next(b for b in re.findall(r"```python\n(.*?)```", readme, re.S) if "SlamWorker()" in b)
    scope = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert len(scope["result"].poses) == len(scope["scans"])
    assert scope["mapper"].latest()[0] == len(scope["scans"]) - 1


def test_threads_that_submit_and_ask_at_once_get_their_own_answers(scans, plain):
    """Four threads submitting (the checks and the queueing are one step: each index is a scan's
    place in the run, a scan out of time order is refused) while another asks for the poses and
    the main thread finishes: every answer is the asker's own, and the result holds every scan
    taken."""
    import threading

    taken, refused, answers = [], [], []
    with SlamWorker() as mapper:
        def feed(part):
            for scan in part:
                try:
                    taken.append((mapper.submit(scan), scan.timestamp))
                except InvalidOptionError:
                    refused.append(scan.timestamp)

        def ask():
            for _ in range(5):
                try:
                    answers.append(type(mapper.poses).__name__)
                except SlamRunError:               # finish came first
                    answers.append("finished")

        feeders = [threading.Thread(target=feed, args=(scans[i::4],)) for i in range(4)]
        asker = threading.Thread(target=ask)
        for thread in feeders + [asker]:
            thread.start()
        for thread in feeders:
            thread.join()
        result = mapper.finish()
        asker.join()
    indices = sorted(k for k, _ in taken)
    assert indices == list(range(len(taken))) and len(taken) + len(refused) == len(scans)
    stamps = [t for _, t in sorted(taken)]
    assert stamps == sorted(stamps) and len(result.poses) == len(taken)
    assert set(answers) <= {"ndarray", "finished"}


def test_options_the_worker_could_not_load_are_refused_at_once():
    """An option value that cannot be pickled, or whose class the worker's interpreter cannot
    import (defined in the calling script), is an InvalidOptionError before any process starts."""
    from taichi_match.slam import SlamOptions

    default = np.array(SlamOptions().odometry_sd)
    with pytest.raises(InvalidOptionError, match="cannot be sent"):
        SlamWorker(odometry_sd=memoryview(default))

    class Metres(float):
        pass

    Metres.__module__, Metres.__qualname__ = "__main__", "Metres"
    import __main__

    __main__.Metres = Metres
    try:
        with pytest.raises(InvalidOptionError, match="__main__"):
            SlamWorker(resolution=Metres(0.05))
    finally:
        del __main__.Metres


def test_the_worker_ignores_ctrl_c_and_its_callers_working_directory(scans, plain, tmp_path, monkeypatch):
    """A terminal's Ctrl-C reaches the whole process group: the worker ignores SIGINT, so a caller
    that catches it can still finish. A ``taichi_match`` in the caller's working directory does not
    shadow the package in the worker (it would raise on import)."""
    _, result = plain
    shadow = tmp_path / "taichi_match"
    shadow.mkdir()
    (shadow / "__init__.py").write_text("raise ImportError('a shadowing package was imported')\n")
    monkeypatch.chdir(tmp_path)
    with SlamWorker() as mapper:
        assert len(mapper.poses) == 0                     # the worker is up
        for scan in scans:
            mapper.submit(scan)
        os.kill(mapper._link.process.pid, signal.SIGINT)
        assert np.array_equal(mapper.finish().poses, result.poses)


def test_a_worker_dropped_without_close_is_stopped(scans, capfd):
    """A SlamWorker no longer referenced (never closed) is collected: its process ends. Closing one
    with a backlog of scans under way prints nothing (no thread's traceback)."""
    import gc

    mapper = SlamWorker()
    process = mapper._link.process
    for scan in scans[:10]:
        mapper.submit(scan)
    del mapper
    gc.collect()
    assert process.wait(30) is not None
    busy = SlamWorker()
    big = [dataclasses.replace(scan, ranges=np.tile(scan.ranges, 50),
                               angles=np.linspace(-1.5, 1.5, 50 * len(scan.ranges))) for scan in scans[:30]]
    for scan in big:
        busy.submit(scan)
    busy.close()
    assert "Traceback" not in capfd.readouterr().err
