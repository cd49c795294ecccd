"""The mapping loop in a thread of its own: scans go in through a queue, so the caller never waits.

``Slam.add`` returns once its scan is mapped: in 7-18 ms at the median on the shared logs, but a
scan that completes a submap also waits for that submap's loop closures and an optimisation (the
99th percentile 60-220 ms, ``bench/SLAM.md``). A driver's callback that calls ``add`` at 40 Hz
stalls in those bursts. ``SlamThread`` runs the same ``Slam`` in a worker thread behind a queue:
``submit`` checks a scan and returns at once, ``latest`` gives the newest mapped scan's pose, and
``finish`` waits for the queue to empty and ends the run. The worker maps the scans in the order
they were submitted with ``Slam.add``, so the result is ``Slam.run``'s on the same scans, bit for
bit; only when each pose becomes available depends on the machine. The queue is unbounded:
``backlog`` says how far the worker is behind, for a caller that would rather skip scans.

Taichi's kernels and gtsam's optimisation hold Python's interpreter lock only between their
calls, so a caller's thread that feeds a 40 Hz laser keeps its period while the worker maps
(``bench/slam_thread.py``).
"""

import queue
import threading
import time
from typing import Optional, Tuple

import numpy as np

from ._errors import InvalidOptionError, SlamRunError
from .logs import Scan
from .slam import Slam, SlamOptions, SlamResult, _checked_scan

__all__ = ["SlamThread"]

_STOP = object()


class SlamThread:
    """A ``Slam`` run fed through a queue and mapped in a worker thread.

    Parameters
    ----------
    options : SlamOptions, optional
        The mapping loop's settings; the defaults without it.
    **overrides
        Fields of ``SlamOptions`` replacing those of ``options``.

    Examples
    --------
    >>> from taichi_match.simulate import simulate_log
    >>> from taichi_match.slam_thread import SlamThread
    >>> scans = simulate_log(1, laps=0.3).log.scans
    >>> with SlamThread() as mapper:
    ...     for scan in scans:                 # e.g. from a LaserScan callback
    ...         index = mapper.submit(scan)    # returns at once
    ...     result = mapper.finish()           # waits for the queue, then ends the run
    >>> len(result.poses) == len(scans)
    True
    """

    def __init__(self, options: Optional[SlamOptions] = None, **overrides):
        self._slam = Slam(options, **overrides)
        self.options = self._slam.options
        self._queue = queue.SimpleQueue()
        self._lock = threading.Lock()            # the fields below, between the caller and the worker
        self._mapping = threading.Lock()         # held by the worker while it maps a scan
        self._submitted = 0
        self._last = None                        # (timestamp, odometry pose) of the last scan submitted
        self._latest = None                      # (index, pose) of the newest scan mapped
        self._error = None                       # what stopped the worker
        self._arrived, self._mapped = [], []     # time.perf_counter() of each scan's submit and mapping
        self._state = "running"                  # then "finished" or "closed"
        self._thread = threading.Thread(target=self._work, name="taichi-match slam", daemon=True)
        self._thread.start()

    def submit(self, scan: Scan) -> int:
        """Queue ``scan`` for mapping (its ``pose`` read as odometry; scans in time order) and
        return its index at once. The scan is checked here as ``Slam.add`` checks it:
        InvalidOptionError for a scan ``Slam.add`` refuses (then nothing is queued and the run
        goes on); SlamRunError once the worker has stopped on an error, or after ``finish`` or
        ``close``. The scan is copied: its arrays may be reused."""
        self._check_running()
        checked = _checked_scan(scan)
        k = self._submitted
        if self._last is not None:
            if not checked.timestamp > self._last[0]:
                raise InvalidOptionError(f"the scans' timestamps must increase (the trajectory's TUM file pairs poses "
                                         f"by time): scan {k} at {checked.timestamp!r} after {self._last[0]!r}")
            self._slam._check_step(k, self._last[1], checked.pose)
        self._last = (checked.timestamp, checked.pose)
        with self._lock:
            self._arrived.append(time.perf_counter())
        self._submitted = k + 1
        self._queue.put(checked)
        return k

    def latest(self) -> Optional[Tuple[int, np.ndarray]]:
        """(index, pose): the newest mapped scan and its pose in the world frame as estimated when
        it was mapped (``Slam.add``'s return); None before the first. Never waits for the worker."""
        with self._lock:
            return None if self._latest is None else (self._latest[0], self._latest[1].copy())

    @property
    def backlog(self) -> int:
        """Scans submitted and not yet mapped."""
        with self._lock:
            return self._submitted - len(self._mapped)

    @property
    def delays(self) -> np.ndarray:
        """(M,) seconds from each mapped scan's ``submit`` to its pose being available."""
        with self._lock:
            return np.array(self._mapped) - np.array(self._arrived[:len(self._mapped)])

    @property
    def poses(self) -> np.ndarray:
        """(M, 3) the current estimates of the scans mapped so far (waits for the scan being mapped)."""
        with self._mapping:
            return self._slam.poses

    def current_map(self):
        """The map of the scans mapped so far (``Slam.current_map``; waits for the scan being mapped)."""
        with self._mapping:
            return self._slam.current_map()

    def finish(self) -> SlamResult:
        """Wait until every submitted scan is mapped, then end the run (``Slam.finish``: the last
        loop closures, optimisation, audit and global map) and stop the worker. Raises what
        stopped the worker (as SlamRunError), or ``Slam.finish``'s refusals (InvalidOptionError:
        no scan, no usable beam, no odometry). Either way this SlamThread is then finished."""
        self._check_running()
        self._stop()
        self._state = "finished"
        self._raise_error()
        return self._slam.finish()

    def close(self) -> None:
        """Stop the worker (after the scan it is mapping; the rest of the queue is dropped) and end
        the run without a result."""
        if self._state == "running":
            self._state = "closed"
            self._error = self._error or _Dropped()
            self._stop()
        self._slam.close()

    def __enter__(self) -> "SlamThread":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _work(self):
        while True:
            scan = self._queue.get()
            if scan is _STOP:
                return
            if self._error is not None:          # stopped: the rest of the queue is dropped
                continue
            k = len(self._mapped)
            try:
                with self._mapping:
                    pose = self._slam.add(scan)
            except BaseException as exc:         # noqa: BLE001 - handed to the caller's thread
                with self._lock:
                    self._error = exc
                continue
            with self._lock:
                self._latest = (k, pose)
                self._mapped.append(time.perf_counter())

    def _stop(self):
        self._queue.put(_STOP)
        self._thread.join()

    def _check_running(self):
        if self._state != "running":
            raise SlamRunError(f"this SlamThread is {self._state}: start a new one")
        self._raise_error()

    def _raise_error(self):
        error = self._error
        if error is not None and not isinstance(error, _Dropped):
            raise SlamRunError(f"the mapping thread stopped at scan {len(self._mapped)}: "
                               f"{type(error).__name__}: {error}") from error


class _Dropped(Exception):
    """The queue's remaining scans are dropped (``close``)."""
