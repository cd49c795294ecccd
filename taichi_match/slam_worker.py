"""The mapping loop in a process of its own: scans go in through a pipe, so the caller never waits.

``Slam.add`` returns once its scan is mapped: in 7-18 ms at the median on the shared logs, but a
scan that completes a submap also waits for that submap's loop closures and an optimisation (the
99th percentile 60-250 ms, at most 0.08-0.37 s). A driver's callback that calls ``add`` at 40 Hz
stalls in those bursts. A worker thread is not enough: gtsam's optimisation holds Python's
interpreter lock for its whole run, so every other thread of the caller stalls with it (a thread
that fed scans at 40 Hz while a worker thread mapped fhw was held up to 108 ms, freiburg-101 up to
112 ms; 2026-12-07, docs/slam.md).

``SlamWorker`` runs ``Slam`` in a fresh interpreter (``python -c``, as ``_helper``'s helpers; POSIX
only), fed over a pipe by a sender thread, while a reader thread takes what the worker says:
``submit`` checks a scan as ``Slam.add`` would, queues it and returns; ``latest`` gives the newest
mapped scan's pose; ``finish`` waits for the queue to empty and returns the ``SlamResult``. The
worker maps the scans in the order submitted with ``Slam.add``, and a run gives the same bits in
any process, so the result is ``Slam.run``'s on the same scans, bit for bit (with the package's own
Taichi settings: a host that called ``ti.init`` itself with others, ``fast_math=False`` say, has
them in its own process only). Only when each pose arrives depends on the machine. The queue is
unbounded: ``backlog`` says how far the worker is behind, for a caller that would rather skip
scans. Measured feeding each shared log at 40 Hz: ``bench/slam_worker.py``.
"""

import os
import pickle
import queue
import signal
import subprocess
import threading
import time
import weakref
from multiprocessing.connection import Connection
from typing import Optional, Tuple

import numpy as np

from ._errors import InvalidOptionError, SlamRunError
from ._helper import start_interpreter
from .logs import Scan
from .slam import Slam, SlamOptions, SlamResult, _checked_scan

__all__ = ["SlamWorker"]

STOP_SECONDS = 10.0            # a worker not gone this long after SIGTERM is killed


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
        For options ``Slam`` refuses, or that cannot be sent to another process (a value of a
        class defined in the calling script).
    SlamRunError
        When the worker process cannot start (not POSIX, or the interpreter failed).

    Notes
    -----
    The methods may be called from several threads; ``submit``'s checks and queueing are one step,
    so the indices it returns are those of the scans' order in the run. A worker process that is
    stopped (SIGSTOP) is waited for; one that ends is an error for every call after it.

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
        try:
            sent = pickle.dumps(self.options)
        except Exception as exc:                             # noqa: BLE001 - any pickling failure
            raise InvalidOptionError(f"the options cannot be sent to the worker process: {exc}") from None
        if b"__main__" in sent:
            raise InvalidOptionError("an option's value is of a class defined in the calling script (__main__), "
                                     "which the worker process cannot load: give plain numbers")
        if os.name != "posix":
            raise SlamRunError("SlamWorker needs POSIX (its worker is a process fed through inherited pipes); "
                               "use Slam.add")
        self._link = _Link(self.options)
        # the link holds no reference to this object: one dropped without close() is collected,
        # and this stops its process and threads
        self._finalizer = weakref.finalize(self, self._link.stop)
        self._submitting = threading.Lock()                  # submit's checks and queueing, close
        self._asking = threading.Lock()                      # one question to the worker at a time
        self._last = None                 # (timestamp, odometry pose) of the last scan submitted
        self._owed = None                 # (id, kind) of a question whose wait was interrupted
        self._questions = 0
        self._state = "running"           # then "finished" or "closed"

    def submit(self, scan: Scan) -> int:
        """Queue ``scan`` for mapping (its ``pose`` read as odometry; scans in time order) and
        return its index at once. The scan is checked here as ``Slam.add`` checks it:
        InvalidOptionError for a scan ``Slam.add`` refuses (nothing is queued; the run goes on);
        SlamRunError once the worker has stopped on an error, or after ``finish`` or ``close``."""
        with self._submitting:
            self._check_running()
            checked = _checked_scan(scan)
            k = self._link.submitted
            if self._last is not None:
                if not checked.timestamp > self._last[0]:
                    raise InvalidOptionError(f"the scans' timestamps must increase (the trajectory's TUM file pairs "
                                             f"poses by time): scan {k} at {checked.timestamp!r} after "
                                             f"{self._last[0]!r}")
                self._checker._check_step(k, self._last[1], checked.pose)
            self._link.submit(checked)
            self._last = (checked.timestamp, checked.pose)
            return k

    def latest(self) -> Optional[Tuple[int, np.ndarray]]:
        """(index, pose): the newest mapped scan and its pose in the world frame as estimated when it
        was mapped (``Slam.add``'s return); None before the first. Never waits for the worker."""
        with self._link.heard:
            latest = self._link.latest
        return None if latest is None else (latest[0], latest[1].copy())

    @property
    def backlog(self) -> int:
        """Scans submitted and not yet reported mapped."""
        with self._link.heard:
            return self._link.submitted - len(self._link.mapped)

    @property
    def delays(self) -> np.ndarray:
        """(M,) seconds from each mapped scan's ``submit`` to its pose arriving here."""
        with self._link.heard:
            mapped, arrived = list(self._link.mapped), self._link.arrived[:len(self._link.mapped)]
        return np.array(mapped) - np.array(arrived)

    @property
    def poses(self) -> np.ndarray:
        """(S, 3) the current estimates of the scans submitted so far (waits until they are mapped)."""
        return self._ask("poses")

    def current_map(self):
        """The map of the scans submitted so far (``Slam.current_map``; waits until they are mapped)."""
        return self._ask("map")

    def finish(self) -> SlamResult:
        """Wait until every submitted scan is mapped, then end the run (``Slam.finish``: the last loop
        closures, optimisation, audit and global map) and the worker. ``Slam.finish``'s refusals
        (InvalidOptionError: no scan, no usable beam, no odometry) leave the run going, as there;
        SlamRunError when the worker stopped on an error. A wait interrupted (KeyboardInterrupt)
        leaves the run's end under way: calling ``finish`` again takes its result."""
        result = self._ask("finish")
        with self._submitting:
            self._state = "finished"
        try:                                   # it ends by itself once it has answered
            self._link.process.wait(STOP_SECONDS)
        except subprocess.TimeoutExpired:      # pragma: no cover - stop() ends it
            pass
        self._finalizer()
        return result

    def close(self) -> None:
        """Stop the worker at once (the queue's scans are dropped) and end the run without a result."""
        with self._submitting:
            if self._state == "running":
                self._state = "closed"
        self._finalizer()

    def __enter__(self) -> "SlamWorker":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _ask(self, kind):
        """Ask the worker for ``kind`` after the scans queued before, and wait for its answer."""
        with self._asking:
            resuming = self._owed is not None and self._owed[1] == "finish"
            if resuming and kind != "finish":
                raise SlamRunError("a finish() was interrupted while the run ended: call finish() again for its "
                                   "result")
            if resuming:                                 # its answer is on the way, or here (the worker ended)
                if self._state != "running":
                    self._check_running()
                number = self._owed[0]
            else:
                self._check_running()
                number = self._questions
                self._questions += 1
                self._link.send(("ask", number, kind))
            self._owed = (number, kind)
            answer = self._link.answer(number)           # a KeyboardInterrupt here leaves it owed
            self._owed = None
        if answer is None:
            self._check_running()
            raise SlamRunError("the mapping worker ended")  # pragma: no cover - _check_running raised
        what, value = answer
        if what == "refused":
            raise InvalidOptionError(value)
        if what == "error":
            self._link.fail(value)
            raise SlamRunError(f"the mapping worker stopped: {value}")
        return value

    def _check_running(self):
        if self._state != "running":
            raise SlamRunError(f"this SlamWorker is {self._state}: start a new one")
        with self._link.heard:
            error = self._link.error
        if error is not None:
            raise SlamRunError(f"the mapping worker stopped {error}")


class _Link:
    """The caller's end of one worker process: the process, the pipes, the sender thread that
    writes the queued messages and the reader thread that takes the worker's, and what it said.
    It holds no reference to its ``SlamWorker``."""

    def __init__(self, options):
        self.process, self._to, self._from = _start()
        self._outgoing = queue.SimpleQueue()
        self.heard = threading.Condition()       # the fields below, between the threads
        self.submitted = 0
        self.arrived, self.mapped = [], []       # time.perf_counter() of each submit and mapping
        self.latest = None                       # (index, pose) of the newest scan mapped
        self.error = None                        # why the worker stopped, for the caller
        self._answers = {}                       # question number -> (kind, value)
        self._ended = False                      # the worker's pipe closed
        self._broken = False                     # a message could not be sent: no answer will come
        self._stopped = False
        self._outgoing.put(("options", options))
        self._threads = [threading.Thread(target=target, name=f"taichi-match slam {name}", daemon=True)
                         for target, name in ((self._send, "sender"), (self._read, "reader"))]
        for thread in self._threads:
            thread.start()

    def submit(self, scan):
        with self.heard:
            self.arrived.append(time.perf_counter())
            self.submitted += 1
        self._outgoing.put(("scan", scan))

    def send(self, message):
        self._outgoing.put(message)

    def answer(self, number):
        """The worker's answer to question ``number`` ((kind, value)), or None once it has ended;
        answers to older questions (whose waits were interrupted) are dropped."""
        with self.heard:
            while number not in self._answers and not self._ended and not self._broken:
                self.heard.wait()
            for older in [n for n in self._answers if n < number]:
                del self._answers[older]
            return self._answers.pop(number, None)

    def fail(self, why):
        with self.heard:
            if self.error is None:
                self.error = why
            self.heard.notify_all()

    def _send(self):
        while True:
            message = self._outgoing.get()
            if message is None:
                return
            try:
                self._to.send(message)
            except OSError:                      # the pipe broke: the worker ended, as the reader says
                return
            except Exception as exc:             # noqa: BLE001 - a message that would not go: no answer will come
                why = f"because a message could not be sent to it ({type(exc).__name__}: {exc})"
                with self.heard:
                    self.error = self.error or why
                    self._broken = True
                    self.heard.notify_all()
                return

    def _read(self):
        while True:
            try:
                message = self._from.recv()
            except Exception:                    # noqa: BLE001 - EOF: the worker ended, or the pipe was closed
                break
            with self.heard:
                if message[0] == "mapped":
                    self.latest = (len(self.mapped), message[1])
                    self.mapped.append(time.perf_counter())
                elif message[0] == "failed":
                    self.error = self.error or f"at scan {len(self.mapped)}: {message[1]}"
                else:                            # ("answer", number, kind, value)
                    self._answers[message[1]] = message[2:]
                self.heard.notify_all()
        try:
            code = self.process.wait(1.0)
        except subprocess.TimeoutExpired:
            code = None
        with self.heard:
            self._ended = True
            if self.error is None and not self._stopped:
                self.error = f"because its process ended{'' if code is None else f' (exit status {code})'}"
            self.heard.notify_all()

    def stop(self):
        """Stop the worker (SIGTERM, so that Taichi releases its offline cache at exit; SIGKILL
        after ``STOP_SECONDS``), then the threads, and close the pipes. A second call does nothing."""
        if self._stopped:
            return
        self._stopped = True
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.send_signal(signal.SIGCONT)      # a stopped worker takes its SIGTERM now
            except OSError:                                   # pragma: no cover - it ended meanwhile
                pass
        try:
            self.process.wait(STOP_SECONDS)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self._outgoing.put(None)                 # the sender ends (a write under way failed: the pipe broke)
        for thread in self._threads:
            if thread is not threading.current_thread():  # (a collection may run the finalizer in one)
                thread.join()
        for conn in (self._to, self._from):
            conn.close()


def _start():
    """The worker process and its two pipe ends (to it, from it), in a session of its own.
    Taichi keeps its offline cache, as in the caller: compiling anew cost a run 0.1-0.5 s at each
    of the kernels' first uses that the warm-up did not reach (orebro: 1.3 s in all), so the worker
    is stopped by SIGTERM, which lets Taichi release the cache's lock at exit."""
    try:
        return start_interpreter("taichi_match.slam_worker", "_serve", new_session=True)
    except OSError as exc:
        raise SlamRunError(f"the mapping worker could not start: {exc}") from None


def _serve(down: int, up: int):
    """The worker's side: read the options and warm up (``_warm_up``), then map each "scan" with
    ``Slam.add`` and report its pose, and answer each question ("poses", "map", "finish") with its
    value, "refused" (``Slam``'s InvalidOptionError: the run goes on) or "error". After an error
    the scans are dropped and every question is answered with it. SIGINT is the caller's: the
    worker runs in a session of its own (a terminal's Ctrl-C does not reach it) and ignores one
    sent to it, so that a caller that catches Ctrl-C can still finish the run."""
    signal.signal(signal.SIGTERM, _exit)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    inbox, outbox = Connection(down, writable=False), Connection(up, readable=False)
    try:
        try:
            _, options = inbox.recv()
        except (EOFError, OSError):
            return
        except Exception as exc:                 # noqa: BLE001 - reported, then the worker ends
            outbox.send(("failed", f"its options could not be read ({type(exc).__name__}: {exc})"))
            return
        _warm_up(options)
        slam, failed = Slam(options), None
        asked = {"poses": lambda: slam.poses, "map": slam.current_map, "finish": slam.finish}
        while True:
            message = inbox.recv()
            if message[0] == "scan":
                if failed is None:
                    try:
                        outbox.send(("mapped", slam.add(message[1])))
                    except Exception as exc:     # noqa: BLE001 - reported; the scans after it are dropped
                        failed = f"{type(exc).__name__}: {exc}"
                        outbox.send(("failed", failed))
                continue
            _, number, kind = message
            if failed is not None:
                outbox.send(("answer", number, "error", failed))
                continue
            try:
                value = asked[kind]()
            except InvalidOptionError as exc:
                outbox.send(("answer", number, "refused", str(exc)))
            except Exception as exc:             # noqa: BLE001 - reported; the run is over
                failed = f"{type(exc).__name__}: {exc}"
                outbox.send(("answer", number, "error", failed))
            else:
                outbox.send(("answer", number, kind, value))
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
    except Exception:                            # noqa: BLE001 - the real run will say what is wrong
        pass
