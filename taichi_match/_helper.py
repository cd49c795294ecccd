"""Helper processes that match pairs of maps they keep: the mapping loop hands them a share of its
loop-closure candidates (``slam``), so that more than one core matches at once.

A helper is a fresh interpreter (``python -c``; not ``multiprocessing``, which would run the
caller's main script again in it) with its own Taichi on one thread. It talks over a pair of pipes
(``multiprocessing.connection.Connection``: pickled messages); its stdout and stderr go nowhere
(Taichi prints; a failure comes back as a message). It runs at the idle priority, so that it
never slows the caller's kernels (which use every core), and Taichi without its offline cache
(see ``Helper.start``). It keeps the maps it is sent, by key, as ``many._portable`` makes them
(a byte a cell with ``evidence="trinary"``), and its matcher prepares each once. A match depends only on its
maps, guess and options, not on the process (``many``): which process ran a task changes nothing
in the results, bit for bit. A helper that fails in any way (it died, a pipe broke, a task
raised) is no longer used, and the caller runs its task itself.
"""

import os
import subprocess
import sys
from multiprocessing.connection import Connection
from typing import Optional

__all__ = ["Helper", "serve", "start_interpreter"]


class Helper:
    """One helper process for matches with ``options`` (a ``MatchOptions``); POSIX only
    (``start`` returns None elsewhere, or when the process cannot start)."""

    def __init__(self, process, inbox, outbox, options):
        self._process, self._to, self._from = process, inbox, outbox
        self._trinary = options.evidence == "trinary"
        self._sent = {}              # key -> the map object last sent under it
        self.ready = False           # it has started Taichi and compiled the kernels
        self.alive = True
        self.task = None             # the tag of the task it is matching

    @classmethod
    def start(cls, options) -> Optional["Helper"]:
        if os.name != "posix":
            return None
        # Taichi without its offline cache: the cache's lock file, taken while the cache is read
        # at the start and written at exit, stayed locked for every later Taichi process (each
        # then warned at exit) when a helper was killed meanwhile; compiling costs it about 0.6 s
        try:
            process, inbox, outbox = start_interpreter("taichi_match._helper", "serve", TI_OFFLINE_CACHE="0")
        except OSError:
            return None
        helper = cls(process, inbox, outbox, options)
        helper._post(("options", options))
        return helper

    @property
    def idle(self) -> bool:
        """Whether it can take a task now."""
        self.collect()
        return self.alive and self.ready and self.task is None

    def holds(self, grid) -> bool:
        """Whether it was sent this very map (and keeps it prepared)."""
        return any(sent is grid for sent in self._sent.values())

    def give(self, tag, maps, guess, window) -> bool:
        """Send a match of ``maps`` ((key, GridMap) for A and B) from ``guess`` within ``window``;
        False when it cannot take it."""
        if not self.idle:
            return False
        from .many import _portable

        for key, grid in maps:
            if self._sent.get(key) is not grid:
                self._post(("map", key, _portable(grid, self._trinary)))
                self._sent[key] = grid
        self._post(("match", tag, maps[0][0], maps[1][0], guess, window))
        if self.alive:
            self.task = tag
        return self.alive

    def collect(self, wait: bool = False):
        """(tag, MatchResult) of its task once done, else None (``wait``: until it is done or the
        helper failed). A failed task comes back as None."""
        while self.alive and (self.task is not None or not self.ready):
            try:
                if not wait and not self._from.poll(0):
                    return None
                message = self._from.recv()
            except (EOFError, OSError):
                self._fail()
                return None
            if message[0] == "ready":
                self.ready = True
                if self.task is None:
                    return None
            elif message[0] == "result" and message[1] == self.task:
                self.task = None
                return message[1], message[2]
            else:                                   # an error in the helper
                self._fail()
        return None

    def _post(self, message):
        try:
            self._to.send(message)
        except (OSError, ValueError):
            self._fail()

    def _fail(self):
        self.alive = False
        self.task = None
        self.close()

    def close(self):
        """Stop the process (a second call does nothing)."""
        for conn in (self._to, self._from):
            try:
                conn.close()
            except OSError:
                pass
        if self._process.poll() is None:             # it keeps nothing worth a graceful end
            self._process.kill()
        self._process.wait()


def start_interpreter(module: str, function: str, *, new_session: bool = False, **env):
    """A fresh interpreter (``python -c``; not ``multiprocessing``, which would run the caller's
    main script again in it) running ``module.function(read_fd, write_fd)`` on a pair of inherited
    pipes, this package first on its path (ahead of its working directory's), ``env`` added to its
    environment, its stdio going nowhere (Taichi prints); ``new_session``: in a session of its own
    (a terminal's Ctrl-C does not reach it). Returns (process, Connection to it, Connection from
    it); raises OSError when it cannot start. POSIX."""
    down, up = os.pipe(), os.pipe()            # (read, write) to it, from it
    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = (f"import sys; sys.path.insert(0, {package!r}); from {module} import {function}; "
            f"{function}({down[0]}, {up[1]})")
    try:
        process = subprocess.Popen([sys.executable, "-c", code], pass_fds=(down[0], up[1]), env=dict(os.environ, **env),
                                   start_new_session=new_session, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL)
    except OSError:
        for fd in (*down, *up):
            os.close(fd)
        raise
    os.close(down[0])
    os.close(up[1])
    return process, Connection(down[1], readable=False), Connection(up[0], writable=False)


def serve(down: int, up: int):
    """The helper's side: read options, warm Taichi up, say ready, then serve "map" and "match"
    messages until the pipe closes. Any error ends the helper (the caller runs the task)."""
    from ._matcher import Matcher
    from ._taichi import set_threads
    from .scenes import room

    set_threads(1)
    try:                                    # the caller's threads first
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        os.nice(19)
    inbox, outbox = Connection(down, writable=False), Connection(up, readable=False)
    maps = {}
    try:
        _, options = inbox.recv()
        matcher = Matcher(options)
        warm = room()
        matcher.match(warm, warm, (0.05, 0.0, 0.0))             # start Taichi, compile the kernels
        outbox.send(("ready",))
        while True:
            message = inbox.recv()
            if message[0] == "map":
                maps[message[1]] = message[2]
            elif message[0] == "match":
                tag, a, b, guess, window = message[1:]
                outbox.send(("result", tag, matcher.match(maps[a], maps[b], guess, search_window=window)))
    except EOFError:
        return
    except Exception as exc:            # reported, then the helper ends: the caller runs the task
        try:
            outbox.send(("error", repr(exc)))
        except OSError:
            pass
