"""The mapping loop in a process of its own: scans go in through a pipe, so the caller never waits.

``Slam.add`` returns once its scan is mapped: in 7-18 ms at the median on the shared logs, but a
scan that completes a submap also waits for that submap's loop closures and an optimisation (the
99th percentile 90-250 ms, at most 100-320 ms). A driver's callback that calls ``add`` at 40 Hz
stalls in those bursts. A worker thread is not enough: gtsam's optimisation holds Python's
interpreter lock for its whole run, so every other thread of the caller stalls with it (a thread
that fed scans at 40 Hz while a worker thread mapped fhw was held up to 108 ms, freiburg-101 up to
112 ms; 2026-12-07).

``SlamWorker`` runs ``Slam`` in a fresh interpreter (``python -c``, as ``_helper``'s helpers; POSIX
only), fed over a pipe by a sender thread: ``submit`` checks a scan as ``Slam.add`` would, queues
it and returns; ``latest`` gives the newest mapped scan's pose as the worker reported it; ``finish``
waits for the queue to empty and returns the ``SlamResult``. The worker maps the scans in the order
submitted with ``Slam.add``, and a run gives the same bits in any process, so the result is
``Slam.run``'s on the same scans, bit for bit; only when each pose arrives depends on the machine.
The queue is unbounded: ``backlog`` says how far the worker is behind, for a caller that would
rather skip scans. Measured feeding each shared log at 40 Hz: ``bench/slam_worker.py``.
"""

import os
import queue
import signal
import subprocess
import sys
import threading
import time
import weakref
from multiprocessing.connection import Connection
from typing import Optional, Tuple

import numpy as np

from ._errors import InvalidOptionError, SlamRunError
from .logs import Scan
from .slam import Slam, SlamOptions, SlamResult, _checked_scan

__all__ = ["SlamWorker"]

_CLOSED = ("closed",)                          # the reader's last word to a waiting caller
STOP_SECONDS = 10.0                            # a worker not gone this long after SIGTERM is killed


class SlamWorker:
    """A ``Slam`` run in a worker process, fed through a queue.

    Parameters
    ----------
    options : SlamOptions, optional
        The mapping loop's settings; the defaults without it.
    **overrides
        Fields of ``SlamOptions`` replacing those of ``options``.

    Raises
    ------
    InvalidOptionError
        For options ``Slam`` refuses.
    SlamRunError
        When the worker process cannot start (not POSIX, or the interpreter failed).

    Examples
    --------
    >>> from taichi_match.simulate import simulate_log
    >>> from taichi_match.slam_worker import SlamWorker
    >>> scans = simulate_log(1, laps=0.3).log.scans
    >>> with SlamWorker() as mapper:
    ...     for scan in scans:                 # e.g. from a LaserScan callback
    ...         index = mapper.submit(scan)    # returns at once
    ...     result = mapper.finish()           # waits for the queue, then ends the run
    >>> len(result.poses) == len(scans)
    True
    """

    def __init__(self, options: Optional[SlamOptions] = None, **overrides):
        self._checker = Slam(options, **overrides)          # checks the options and each scan
        self.options = self._checker.options
        if os.name != "posix":
            raise SlamRunError("SlamWorker needs POSIX (its worker is a process fed through inherited pipes); "
                               "use Slam.add")
        self._process, self._to, self._from = _start()
        self._finalizer = weakref.finalize(self, _end, self._process, self._to, self._from)
        self._outgoing = queue.SimpleQueue()                 # messages for the sender thread
        self._replies = queue.SimpleQueue()                  # answers to poses, current_map and finish
        self._lock = threading.Lock()                        # the fields below, caller and reader
        self._submitted = 0
        self._last = None                 # (timestamp, odometry pose) of the last scan submitted
        self._latest = None               # (index, pose) of the newest scan mapped
        self._error = None                # why the worker stopped, for the caller
        self._arrived, self._mapped = [], []                 # time.perf_counter() of each submit, mapping
        self._state = "running"                              # then "finished" or "closed"
        self._outgoing.put(("options", self.options))
        self._threads = [threading.Thread(target=target, name=f"taichi-match slam {name}", daemon=True)
                         for target, name in ((self._send, "sender"), (self._read, "reader"))]
        for thread in self._threads:
            thread.start()

    def submit(self, scan: Scan) -> int:
        """Queue ``scan`` for mapping (its ``pose`` read as odometry; scans in time order) and
        return its index at once. The scan is checked here as ``Slam.add`` checks it:
        InvalidOptionError for a scan ``Slam.add`` refuses (nothing is queued; the run goes on);
        SlamRunError once the worker has stopped on an error, or after ``finish`` or ``close``."""
        self._check_running()
        checked = _checked_scan(scan)
        k = self._submitted
        if self._last is not None:
            if not checked.timestamp > self._last[0]:
                raise InvalidOptionError(f"the scans' timestamps must increase (the trajectory's TUM file pairs poses "
                                         f"by time): scan {k} at {checked.timestamp!r} after {self._last[0]!r}")
            self._checker._check_step(k, self._last[1], checked.pose)
        self._last = (checked.timestamp, checked.pose)
        with self._lock:
            self._arrived.append(time.perf_counter())
        self._submitted = k + 1
        self._outgoing.put(("scan", checked))
        return k

    def latest(self) -> Optional[Tuple[int, np.ndarray]]:
        """(index, pose): the newest mapped scan and its pose in the world frame as estimated when it
        was mapped (``Slam.add``'s return); None before the first. Never waits for the worker."""
        with self._lock:
            return None if self._latest is None else (self._latest[0], self._latest[1].copy())

    @property
    def backlog(self) -> int:
        """Scans submitted and not yet reported mapped."""
        with self._lock:
            return self._submitted - len(self._mapped)

    @property
    def delays(self) -> np.ndarray:
        """(M,) seconds from each mapped scan's ``submit`` to its pose arriving here."""
        with self._lock:
            return np.array(self._mapped) - np.array(self._arrived[:len(self._mapped)])

    @property
    def poses(self) -> np.ndarray:
        """(S, 3) the current estimates of the scans submitted so far (waits until they are mapped)."""
        return self._ask(("poses",))

    def current_map(self):
        """The map of the scans submitted so far (``Slam.current_map``; waits until they are mapped)."""
        return self._ask(("map",))

    def finish(self) -> SlamResult:
        """Wait until every submitted scan is mapped, then end the run (``Slam.finish``: the last loop
        closures, optimisation, audit and global map) and the worker. ``Slam.finish``'s refusals
        (InvalidOptionError: no scan, no usable beam, no odometry) leave the run going, as there;
        SlamRunError when the worker stopped on an error."""
        result = self._ask(("finish",))
        self._state = "finished"
        try:                                   # it ends by itself once it has answered
            self._process.wait(STOP_SECONDS)
        except subprocess.TimeoutExpired:      # pragma: no cover - _end stops it
            pass
        self._end()
        return result

    def close(self) -> None:
        """Stop the worker at once (the queue's scans are dropped) and end the run without a result."""
        if self._state == "running":
            self._state = "closed"
        self._end()

    def __enter__(self) -> "SlamWorker":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _ask(self, message):
        """Send ``message`` after the scans queued before it, and wait for the worker's answer."""
        self._check_running()
        self._outgoing.put(message)
        answer = self._replies.get()
        if answer[0] == "refused":
            raise InvalidOptionError(answer[1])
        if answer[0] == "error":
            raise SlamRunError(f"the mapping worker failed: {answer[1]}")
        if answer is _CLOSED:
            self._replies.put(_CLOSED)                       # for the next one who asks
            self._check_running()
            raise SlamRunError("the mapping process ended")  # pragma: no cover - _check_running raised
        return answer[1]

    def _send(self):
        while True:
            message = self._outgoing.get()
            if message is None:
                return
            try:
                self._to.send(message)
            except (OSError, ValueError):                    # the worker is gone: the reader says why
                return

    def _read(self):
        while True:
            try:
                message = self._from.recv()
            except (EOFError, OSError):
                break
            kind = message[0]
            with self._lock:
                if kind == "mapped":
                    self._latest = (len(self._mapped), message[1])
                    self._mapped.append(time.perf_counter())
                    continue
                if kind == "failed":
                    self._error = f"at scan {len(self._mapped)}: {message[1]}"
                    continue
            self._replies.put(message)                       # poses, map, finish, refused, error
        with self._lock:
            if self._error is None and self._state == "running":
                code = self._process.poll()
                self._error = f"because its process ended{'' if code is None else f' (exit status {code})'}"
        self._replies.put(_CLOSED)

    def _end(self):
        self._outgoing.put(None)
        self._finalizer()
        for thread in self._threads:
            thread.join()

    def _check_running(self):
        if self._state != "running":
            raise SlamRunError(f"this SlamWorker is {self._state}: start a new one")
        with self._lock:
            error = self._error
        if error is not None:
            raise SlamRunError(f"the mapping worker stopped {error}")


def _start():
    """The worker process and its two pipe ends (to it, from it)."""
    down, up = os.pipe(), os.pipe()                  # (read, write) to the worker, from it
    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    # the package importable (as for _helper's helpers); Taichi with its offline cache, as in the
    # caller: compiling anew cost a run 0.1-0.5 s at each of the kernels' first uses that the warm-up
    # did not reach (orebro: 1.3 s in all), so the worker is stopped by SIGTERM (``_end``), which lets
    # Taichi release the cache's lock at exit, where a killed process left it held
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (package, os.environ.get("PYTHONPATH")) if p))
    code = f"from taichi_match.slam_worker import _serve; _serve({down[0]}, {up[1]})"
    try:
        process = subprocess.Popen([sys.executable, "-c", code], pass_fds=(down[0], up[1]), env=env,
                                   stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError as exc:
        for fd in (*down, *up):
            os.close(fd)
        raise SlamRunError(f"the mapping worker could not start: {exc}") from None
    os.close(down[0])
    os.close(up[1])
    return process, Connection(down[1], readable=False), Connection(up[0], writable=False)


def _end(process, to, came):
    """Close the pipes and stop the worker process: SIGTERM (it exits as from an error, Taichi
    releasing its offline cache), and after ``STOP_SECONDS`` SIGKILL."""
    for conn in (to, came):
        try:
            conn.close()
        except OSError:
            pass
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(STOP_SECONDS)
        except subprocess.TimeoutExpired:
            process.kill()
    process.wait()


def _serve(down: int, up: int):
    """The worker's side: read the options, then map each "scan" with ``Slam.add`` and report its
    pose (after ``_warm_up``); answer "poses", "map" and "finish" in turn, each with its value, "refused" (the run goes
    on) or "error". An error in ``add`` is reported once ("failed"), and the scans after it are
    dropped."""
    signal.signal(signal.SIGTERM, _exit)
    inbox, outbox = Connection(down, writable=False), Connection(up, readable=False)
    try:
        _, options = inbox.recv()
        _warm_up(options)
        slam, failed = Slam(options), False
        while True:
            message = inbox.recv()
            kind = message[0]
            if kind == "scan":
                if failed:
                    continue
                try:
                    pose = slam.add(message[1])
                except Exception as exc:             # reported; the scans after it are dropped
                    failed = True
                    outbox.send(("failed", f"{type(exc).__name__}: {exc}"))
                else:
                    outbox.send(("mapped", pose))
                continue
            try:
                answer = {"poses": lambda: slam.poses, "map": slam.current_map, "finish": slam.finish}[kind]()
            except InvalidOptionError as exc:
                outbox.send(("refused", str(exc)))
            except Exception as exc:
                outbox.send(("error", f"{type(exc).__name__}: {exc}"))
            else:
                outbox.send((kind, answer))
                if kind == "finish":
                    return
    except (EOFError, OSError):
        return


def _exit(signum, frame):
    """SIGTERM: leave as from an error, so that the interpreter's exit handlers (Taichi's) run."""
    raise SystemExit(0)


def _warm_up(options):
    """Start Taichi and compile the loop's kernels before the first scan comes: a simulated lap
    with the same options, loop closures included (about 3 s; a run's results do not depend on it)."""
    from .simulate import simulate_log

    try:
        Slam(options).run(simulate_log(1, laps=1.1).log)
    except Exception:                        # noqa: BLE001 - the real run will say what is wrong
        pass
