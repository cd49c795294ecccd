"""Many matches in one call: each map prepared once however many tasks name it, the tasks spread
over worker processes when an executor is given.

A task is ``(a, b)`` or ``(a, b, initial_pose)`` (None: search without a guess), each map a
``GridMap``. Every result is the ``MatchResult`` that ``match(a, b, initial_pose, **options)``
gives, the same pose bit for bit: a match depends only on its maps, its guess and the options,
not on the other tasks, the process or Taichi's thread count.

With ``executor`` (any ``concurrent.futures.Executor`` whose workers are processes started with
"spawn" or "forkserver", or Dask's ``Client.get_executor()``) the tasks go out in chunks (blocks
of consecutive tasks dealt out in turn, ``BLOCK``), each with the maps it names, sent and
prepared once per chunk; a worker starts Taichi with its share of the machine's cores
(``_taichi.set_threads``). A ``ProcessPoolExecutor``'s workers get the maps as files in a private
temporary directory (in /dev/shm where there is one), each written once and removed when the call
ends, not down the executor's pipe (``_Handover``).
Each chunk costs a map's transfer and preparation per distinct map it names, so fewer, larger
chunks suit tasks that share maps (an all-pairs check), more chunks balance unequal tasks and start
the workers sooner; without ``chunk_size`` the call weighs the two (``_default_chunk_size``).
A worker forked after Taichi started in the parent would hang; taichi_match detects it and the
task fails with a clear ``EngineError`` instead.
"""

import concurrent.futures
import math
import os
import shutil
import tempfile
from typing import Iterable, Iterator, List, Optional, Tuple, Union

import numpy as np

from ._errors import InvalidMapError, InvalidOptionError, TaichiMatchError, shown
from ._grid import GridMap, _from_code, _trusted, grid_code
from ._matcher import Matcher
from ._options import MatchOptions
from ._result import MatchResult
from ._taichi import _allowed_cpus, set_threads

__all__ = ["match_many", "iter_matches"]

Task = Tuple  # (a, b) or (a, b, initial_pose)


def match_many(tasks: Iterable[Task], options: Optional[MatchOptions] = None, *,
               executor: Optional[concurrent.futures.Executor] = None, chunk_size: Optional[int] = None,
               errors: str = "raise", **overrides) -> List[Union[MatchResult, TaichiMatchError]]:
    """Match every task, results in the tasks' order (see the module docstring).

    Parameters
    ----------
    tasks : iterable of (a, b) or (a, b, initial_pose)
        Maps as ``GridMap``; ``initial_pose`` r_A2B (x, y, theta) or None.
    options : MatchOptions, optional
        The options of every task (default: ``MatchOptions()``).
    executor : concurrent.futures.Executor, optional
        Workers to spread the tasks over (processes started with "spawn", or Dask's
        ``Client.get_executor()``); None: in this process, one ``Matcher``.
    chunk_size : int, optional
        Tasks per chunk sent to a worker; default: up to ``CHUNKS_PER_WORKER`` chunks per worker
        while the maps the chunks send stay within ``MAX_RESENT`` of one chunk per worker's.
    errors : {"raise", "return"}
        A task whose input is bad (a ``TaichiMatchError``): raise it (after the running chunks
        end), or put the error in that task's place and go on.
    **overrides
        Fields of ``MatchOptions`` to change in ``options``.

    Returns
    -------
    list of MatchResult or TaichiMatchError
        One per task, in the tasks' order; an error only with ``errors="return"``.

    Raises
    ------
    InvalidOptionError
        For a bad option, ``errors`` or ``chunk_size``, or a task that is not a 2- or 3-tuple.
    InvalidMapError
        If a task's map is not a ``GridMap`` (whatever ``errors`` says).
    TaichiMatchError
        With ``errors="raise"``, a task's own error, its message prefixed with "task INDEX: ".

    Examples
    --------
    A 4 x 4 m room with two inner walls matched against itself from a guess 0.2 m and 3 degrees
    off; the result is within a cell (0.1 m) of the truth, (0, 0, 0):

    >>> import numpy as np
    >>> from taichi_match import GridMap, match_many
    >>> prob = np.full((40, 40), np.nan)
    >>> prob[2:38, 2:38] = 0.0
    >>> prob[2, 2:38] = prob[37, 2:38] = prob[2:38, 2] = prob[2:38, 37] = 1.0
    >>> prob[8:18, 20] = prob[26, 6:20] = 1.0
    >>> room = GridMap(prob, 0.1)
    >>> [result] = match_many([(room, room, (0.2, -0.1, 0.05))])
    >>> bool(result.accepted), bool(np.all(np.abs(result.pose) < [0.1, 0.1, 0.02]))
    (True, True)
    """
    results = {}
    for index, result in iter_matches(tasks, options, executor=executor, chunk_size=chunk_size, errors=errors,
                                      **overrides):
        results[index] = result
    return [results[k] for k in range(len(results))]


def iter_matches(tasks: Iterable[Task], options: Optional[MatchOptions] = None, *,
                 executor: Optional[concurrent.futures.Executor] = None, chunk_size: Optional[int] = None,
                 errors: str = "raise", **overrides) -> Iterator[Tuple[int, Union[MatchResult, TaichiMatchError]]]:
    """``match_many``'s results as they come: (task index, result) pairs, in the order the tasks
    (serially) or the chunks (with an executor) finish.

    Parameters and errors as ``match_many``; the tasks and options are checked when the first
    pair is asked for (it is a generator).

    Yields
    ------
    index : int
        The task's position in ``tasks``.
    outcome : MatchResult or TaichiMatchError
        Its result; an error only with ``errors="return"``.

    Examples
    --------
    A task with a bad guess, its error returned in its place (no matching runs):

    >>> import numpy as np
    >>> from taichi_match import GridMap, iter_matches
    >>> grid = GridMap(np.zeros((20, 20)), 0.1)
    >>> for index, outcome in iter_matches([(grid, grid, (0.0, 0.0, np.nan))], errors="return"):
    ...     print(index, type(outcome).__name__, outcome)
    0 InvalidPoseError initial_pose must be finite; got [0.0, 0.0, nan]
    """
    if errors not in ("raise", "return"):
        raise InvalidOptionError(f"errors must be 'raise' or 'return'; got {errors!r}")
    tasks = [_task(k, task) for k, task in enumerate(tasks)]
    matcher = Matcher(options, **overrides)          # the options checked here, before any work
    if executor is None:
        for index, (a, b, guess) in enumerate(tasks):
            yield index, _outcome(lambda a=a, b=b, guess=guess: matcher.match(a, b, guess), index, errors)
        return
    if chunk_size is None:
        chunk_size = _default_chunk_size(tasks, _workers(executor))
    elif isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise InvalidOptionError(f"chunk_size must be a whole number >= 1; got {shown(chunk_size)}")
    # a worker's Taichi threads: its share of the cores. Twice that was slower: a loop's 123 consecutive
    # submap pairs on 2 spawned workers, a pool of each kind, six runs each in ABBA order (2026-12-04):
    # 0.883 s with one thread each, 1.004 s with two (1.59x and 1.40x the serial loop). (Taichi takes
    # its thread count when it starts in the worker: a pool keeps its first call's.)
    threads = max(1, len(_allowed_cpus()) // _workers(executor))
    trinary = matcher.options.evidence == "trinary"
    futures = {}
    handover = _Handover(isinstance(executor, concurrent.futures.ProcessPoolExecutor))
    try:
        for indices in _chunks(len(tasks), math.ceil(len(tasks) / chunk_size)):
            maps, named = _chunk([tasks[k] for k in indices])
            maps = [handover.send(grid, trinary) for grid in maps]
            futures[executor.submit(_match_chunk, maps, named, matcher.options, threads, os.getpid())] = indices
        for future in concurrent.futures.as_completed(futures):
            for index, outcome in zip(futures[future], future.result()):
                if isinstance(outcome, TaichiMatchError) and errors == "raise":
                    raise type(outcome)(f"task {index}: {outcome}") from outcome
                yield index, outcome
    finally:
        for future in futures:
            future.cancel()
        handover.close()


def _task(index, task):
    """(a, b, initial_pose or None) from a task, its maps checked."""
    try:
        a, b, *rest = task
    except (TypeError, ValueError):
        raise InvalidOptionError(f"task {index} must be (a, b) or (a, b, initial_pose); got {task!r:.80}") from None
    if len(rest) > 1:
        raise InvalidOptionError(f"task {index} must be (a, b) or (a, b, initial_pose); got {len(rest) + 2} items")
    for name, grid in (("a", a), ("b", b)):
        if not isinstance(grid, GridMap):
            raise InvalidMapError(f"task {index}: {name} must be a GridMap; got {type(grid).__name__}")
    return a, b, rest[0] if rest else None


def _outcome(run, index, errors):
    try:
        return run()
    except TaichiMatchError as exc:
        if errors == "raise":
            raise type(exc)(f"task {index}: {exc}") from exc
        return exc


# Chunks take the tasks in blocks of this many consecutive ones, dealt out in turn: consecutive
# tasks often share maps (a loop's consecutive pairs: a map more per block to send and prepare),
# and far-apart tasks often differ in cost (an all-pairs check's first and last rows: measured on
# 1,225 pairs of 50 laser submaps on 2 workers, 1.31x the serial loop in two halves, 1.47x dealt out)
BLOCK = 16


# Without ``chunk_size``, each worker gets up to this many chunks: smaller chunks start the
# workers sooner and even out their loads (a loop's 123 consecutive submap pairs, 2 workers: 1.49-1.51x
# the serial loop in 2 chunks, 1.61-1.63x in 8), as long as the maps the chunks name, each sent
# and prepared once per chunk, grow by at most MAX_RESENT over one chunk per worker (an all-pairs
# check of 50 submaps, 1,225 pairs: 1.68-1.84x in 2 chunks, 1.51x in 4, 1.2x in 8; measured on
# this 2-core machine, 2026-12-04, on bench/throughput.py's tasks, a warmed pool, two runs each).
CHUNKS_PER_WORKER = 4
MAX_RESENT = 0.1


def _default_chunk_size(tasks, workers: int) -> int:
    """The smallest chunk size that deals the tasks into at most ``CHUNKS_PER_WORKER`` chunks per
    worker and whose chunks name, summed over chunks, at most ``1 + MAX_RESENT`` times the maps
    that one chunk per worker names."""
    def maps_sent(size):
        return sum(len(_chunk([tasks[k] for k in indices])[0])
                   for indices in _chunks(len(tasks), math.ceil(len(tasks) / size)))

    best = max(1, math.ceil(len(tasks) / workers))
    allowed = (1.0 + MAX_RESENT) * maps_sent(best)
    for per_worker in range(2, CHUNKS_PER_WORKER + 1):
        size = max(1, math.ceil(len(tasks) / (workers * per_worker)))
        if maps_sent(size) > allowed:
            break
        best = size
    return best


def _chunks(count, chunks):
    """The task indices of each chunk: blocks of ``BLOCK`` consecutive tasks (fewer when every
    chunk would not get one) dealt out in turn."""
    out = [[] for _ in range(max(1, min(chunks, count)))]
    block = max(1, min(BLOCK, -(-count // len(out))))
    for start in range(0, count, block):
        out[(start // block) % len(out)].extend(range(start, min(start + block, count)))
    return [indices for indices in out if indices]


def _chunk(tasks):
    """(the distinct maps the tasks name, the tasks as (index of a, index of b, guess))."""
    maps, index = [], {}
    for a, b, _ in tasks:
        for grid in (a, b):
            if id(grid) not in index:
                index[id(grid)] = len(maps)
                maps.append(grid)
    return maps, [(index[id(a)], index[id(b)], guess) for a, b, guess in tasks]


class _Handover:
    """How a chunk's maps reach a worker. Through the executor, each map travels pickled down a
    pipe, once per chunk that names it, while the worker waits for it (measured on a loop's 123
    consecutive submap pairs, 2 spawned workers: 85 MB of trinary codes, 0.18-0.24 s to hand
    8 chunks to workers that do nothing with them). For a ``ProcessPoolExecutor`` (its workers on
    this machine) each distinct map is written once, as a ``.npy`` file in a private temporary
    directory (in /dev/shm where there is one: memory, not disk), and a worker maps it read-only
    (``_MapFile``); the directory goes when the call ends, and one left by a process killed during
    a call goes at the next (``_remove_orphans``). Where a file cannot be written, and for
    other executors (Dask's workers may be on other machines), the maps go through the executor."""

    PREFIX = "taichi_match-"

    def __init__(self, local: bool):
        self._folder, self._sent = None, {}
        if local:
            where = "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()
            _remove_orphans(where, self.PREFIX)
            try:
                self._folder = tempfile.mkdtemp(prefix=f"{self.PREFIX}{os.getpid()}-", dir=where)
            except OSError:
                self._folder = None

    def send(self, grid: GridMap, trinary: bool):
        """What the worker gets for ``grid``: a ``_MapFile``, or the map itself (``_portable``)."""
        if id(grid) in self._sent:
            return self._sent[id(grid)][0]
        portable = _portable(grid, trinary)
        if self._folder is None:
            return portable
        path = os.path.join(self._folder, f"{len(self._sent)}.npy")
        try:
            np.save(path, portable._code if trinary else portable.prob, allow_pickle=False)
        except OSError:                                # (a full /dev/shm: this map goes the other way)
            return portable
        self._sent[id(grid)] = (_MapFile(path, trinary, grid.resolution, grid.corner_pose), grid)
        return self._sent[id(grid)][0]

    def close(self):
        """Remove the files (a worker that has one open keeps reading it)."""
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
            self._folder = None


def _remove_orphans(where, prefix):
    """Remove the hand-over folders (``prefix`` PID ``-`` ...) in ``where`` whose process is gone:
    a process killed during a call leaves its folder, which in /dev/shm holds memory until reboot."""
    try:
        names = os.listdir(where)
    except OSError:
        return
    for name in names:
        pid = name[len(prefix):].split("-", 1)[0] if name.startswith(prefix) else ""
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:                 # gone (another user's live process: PermissionError)
            shutil.rmtree(os.path.join(where, name), ignore_errors=True)
        except OSError:
            pass


class _MapFile:
    """A map as a ``.npy`` file of its trinary code or probabilities, read in the worker."""

    def __init__(self, path, trinary, resolution, corner_pose):
        self.path, self.trinary, self.resolution, self.corner_pose = path, trinary, resolution, corner_pose

    def load(self) -> GridMap:
        array = np.load(self.path, mmap_mode="r", allow_pickle=False).view(np.ndarray)
        if self.trinary:
            return _from_code(array, self.resolution, self.corner_pose)
        return _trusted(array, self.resolution, self.corner_pose)


def _portable(grid: GridMap, trinary: bool) -> GridMap:
    """A map as sent to a worker: with ``evidence="trinary"`` made from its ``trinary_code`` (a
    byte a cell where the map has eight; a match reads nothing else of it, so the result is the
    same), otherwise the map itself."""
    return _from_code(grid_code(grid), grid.resolution, grid.corner_pose) if trinary else grid


def _workers(executor):
    """How many tasks the executor runs at once: a process pool's workers, a Dask cluster's
    threads; otherwise this machine's cores."""
    count = getattr(executor, "_max_workers", None)
    client = getattr(executor, "_client", None)
    if count is None and client is not None:
        try:
            count = sum(client.nthreads().values())
        except Exception:  # pragma: no cover - a client that cannot say
            count = None
    return max(1, int(count or len(_allowed_cpus())))


def _match_chunk(maps, tasks, options, threads, parent):
    """A worker's part: the tasks of one chunk with one matcher (each map prepared once). A
    ``TaichiMatchError`` takes its task's place in the list."""
    if os.getpid() != parent:           # a worker process, not a thread of the caller's
        set_threads(threads)
    maps = [grid.load() if isinstance(grid, _MapFile) else grid for grid in maps]
    matcher = Matcher(options)
    out = []
    for ia, ib, guess in tasks:
        try:
            out.append(matcher.match(maps[ia], maps[ib], guess))
        except TaichiMatchError as exc:
            out.append(exc)
    return out
