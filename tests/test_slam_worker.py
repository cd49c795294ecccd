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
    os.kill(mapper._process.pid, signal.SIGKILL)
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
    process = mapper._process
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
