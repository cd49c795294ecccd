"""The mapping loop behind a queue (``slam_thread.SlamThread``): the same result as ``Slam.run``
bit for bit, a ``submit`` that does not wait for the worker, refusals in the caller's thread, and
a worker's error handed back."""

import dataclasses
import threading
import time

import numpy as np
import pytest

from taichi_match import GridMap, InvalidOptionError, SlamRunError
from taichi_match.simulate import simulate_log

pytest.importorskip("gtsam")

from taichi_match.slam import Slam  # noqa: E402  (needs gtsam)
from taichi_match.slam_thread import SlamThread  # noqa: E402


@pytest.fixture(scope="module")
def scans():
    return simulate_log(1, laps=0.4).log.scans


@pytest.fixture(scope="module")
def plain(scans):
    """``Slam.add`` scan by scan in this thread: each scan's pose when it was mapped, and the result."""
    mapper = Slam()
    added = [mapper.add(scan) for scan in scans]
    return np.array(added), mapper.finish()


def test_the_thread_maps_the_scans_as_slam_add_does(scans, plain):
    """Every scan submitted at once (the worker far behind): the poses, each scan's pose when it was
    mapped (``latest`` at the end) and the graph's size are those of ``Slam.add`` in one thread."""
    added, result = plain
    with SlamThread() as mapper:
        for k, scan in enumerate(scans):
            assert mapper.submit(scan) == k
        done = mapper.finish()
        index, pose = mapper.latest()
    assert np.array_equal(done.poses, result.poses)
    assert index == len(scans) - 1 and np.array_equal(pose, added[-1])
    assert done.graph.size() == result.graph.size() and len(done.loops) == len(result.loops)
    assert mapper.backlog == 0 and len(mapper.delays) == len(scans) and np.all(mapper.delays >= 0)


def test_submit_does_not_wait_for_the_worker(scans):
    """With the worker held inside its first scan's mapping, three scans are still taken at once:
    the backlog counts them and no pose is out yet; released, the worker maps them all."""
    release, entered = threading.Event(), threading.Event()
    mapper = SlamThread()
    add = mapper._slam.add

    def held(scan):
        entered.set()
        assert release.wait(30)
        return add(scan)

    mapper._slam.add = held
    try:
        for scan in scans[:3]:
            mapper.submit(scan)
        assert entered.wait(30)
        assert mapper.backlog == 3 and mapper.latest() is None
        release.set()
        result = mapper.finish()
    finally:
        release.set()
        mapper.close()
    assert len(result.poses) == 3 and mapper.latest()[0] == 2


def test_refused_scans_are_refused_in_the_callers_thread(scans, plain):
    """A scan ``Slam.add`` refuses (a NaN pose, a timestamp that does not increase, an odometry
    jump beyond a ray's reach) raises at ``submit`` and is not queued; the run goes on, and its
    result is that of the good scans alone."""
    _, result = plain
    bad_pose = dataclasses.replace(scans[1], pose=np.array([np.nan, 0.0, 0.0]))
    stale = dataclasses.replace(scans[1], timestamp=scans[0].timestamp)
    jump = dataclasses.replace(scans[1], pose=scans[1].pose + np.array([50.0, 0.0, 0.0]))
    with SlamThread() as mapper:
        mapper.submit(scans[0])
        for bad, what in ((bad_pose, "pose"), (stale, "timestamps must increase"), (jump, "jumps")):
            with pytest.raises(InvalidOptionError, match=what):
                mapper.submit(bad)
        for scan in scans[1:]:
            mapper.submit(scan)
        assert np.array_equal(mapper.finish().poses, result.poses)


def test_a_worker_error_is_handed_to_the_caller(scans):
    """An error inside the worker's mapping stops it: the next ``submit`` or ``finish`` raises
    SlamRunError naming the scan and the error (chained), and ``close`` still ends the run."""
    mapper = SlamThread()
    add = mapper._slam.add

    def failing(scan):
        if len(mapper._mapped) == 2:
            raise RuntimeError("the disk is on fire")
        return add(scan)

    mapper._slam.add = failing
    for scan in scans[:4]:
        mapper.submit(scan)
    with pytest.raises(SlamRunError, match="scan 2: RuntimeError: the disk is on fire") as info:
        mapper.finish()
    assert isinstance(info.value.__cause__, RuntimeError)
    mapper.close()
    with pytest.raises(SlamRunError, match="finished"):
        mapper.submit(scans[0])


def test_after_finish_or_close_nothing_more_is_taken(scans):
    """``finish`` and ``close`` end the SlamThread: ``submit`` and ``finish`` then raise
    SlamRunError; ``close`` may be called again; the map of the mapped scans is there while it runs."""
    mapper = SlamThread()
    for scan in scans[:12]:
        mapper.submit(scan)
    deadline = time.monotonic() + 60
    while mapper.latest() is None and time.monotonic() < deadline:
        time.sleep(0.01)                                  # the first scan mapped (kernels compiled)
    assert isinstance(mapper.current_map(), GridMap)
    assert len(mapper.poses) <= 12
    mapper.close()
    mapper.close()
    for call in (lambda: mapper.submit(scans[12]), mapper.finish):
        with pytest.raises(SlamRunError, match="closed"):
            call()
