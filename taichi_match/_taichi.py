"""Taichi's runtime for taichi_match: started lazily, once, on the CPU, and guarded.

Taichi is imported and initialised on the first evaluation: CPU backend, all allowed cores (its
worker threads pinned one per core, see ``_pin_threads``), no banner, no network version check,
and its frontend spared the source excerpts of our kernels (``_plain_source_lines``).
A host that already called ``ti.init`` keeps its runtime, threads untouched. Calls are serialised
with a lock (Taichi is not thread-safe), and a process forked after Taichi was initialised gets
an error instead of the hang Taichi would give. Every module with kernels gets them through
``kernels(build)``; they launch through ``_launch``.
"""

import contextlib
import io
import os
import sys
import threading
import warnings

from ._errors import EngineError

__all__ = ["taichi", "kernels", "kernel_lock", "check_not_forked", "set_threads", "runtime_program"]

_LOCK = threading.RLock()
_STATE = {"ti": None, "forked": False, "threads": None}
_BUILT = {}          # builder -> what it built


def set_threads(threads):
    """The number of CPU threads Taichi gets when taichi_match starts it (None: one per allowed
    CPU, pinned one to a CPU). For a process that shares the machine with others doing the same
    (workers of a pool, one per core): 1. No effect once Taichi runs."""
    _STATE["threads"] = threads


def _after_fork_in_child():
    """Remember that this process was forked while Taichi (ours or the host's) was running, or
    while another thread held the kernel lock (it would never be released here)."""
    stuck = not _LOCK.acquire(blocking=False)
    if not stuck:
        _LOCK.release()
    ti = sys.modules.get("taichi")
    try:
        running = ti is not None and ti.lang.impl.get_runtime().prog is not None
    except Exception:  # pragma: no cover - a half-imported taichi
        running = True
    if running or stuck:
        _STATE["forked"] = True


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def _import_taichi():
    if _STATE["ti"] is None:
        os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
        os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
        os.environ.setdefault("TI_ENABLE_PYBUF", "0")      # else a wrapped stdout adds a print per launch
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)   # taichi 1.7 uses deprecated stdlib calls
            import taichi as ti
        _plain_source_lines(ti)
        _STATE["ti"] = ti
    return _STATE["ti"]


def _plain_source_lines(ti):
    """Taichi 1.7's frontend, compiling one of our kernels, formats for every node of its syntax
    tree the source excerpt an error message would quote (``ASTTransformerContext.get_pos_info``,
    a ``textwrap`` per line): half of the frontend's time for our kernels (measured: 0.21 -> 0.10 s
    a process on seattle, the offline cache warm). For kernels in this package the message keeps
    the file, line and kernel, without the excerpt; other kernels (a host's) keep Taichi's. Done on
    the Taichi (major, minor) it was written for; TAICHI_MATCH_PLAIN_SOURCE_LINES=0 turns it off."""
    try:
        context = ti.lang.ast.ast_transformer_utils.ASTTransformerContext
        full = context.get_pos_info
    except AttributeError:  # pragma: no cover - another Taichi
        return
    if (tuple(getattr(ti, "__version__", ()))[:2] != (1, 7) or getattr(full, "_taichi_match", False)
            or os.environ.get("TAICHI_MATCH_PLAIN_SOURCE_LINES", "1") == "0"):
        return
    package = os.path.dirname(os.path.abspath(__file__)) + os.sep

    def get_pos_info(self, node):
        if not str(self.file).startswith(package):
            return full(self, node)
        return f'File "{self.file}", line {node.lineno + self.lineno_offset}, in {self.func.func.__name__}:\n'

    get_pos_info._taichi_match = True
    context.get_pos_info = get_pos_info


def kernel_lock():
    """The lock that serialises every Taichi call (``check_not_forked`` first)."""
    check_not_forked()
    return _LOCK


def check_not_forked():
    """Raise ``EngineError`` in a process forked after Taichi started. Called before any lock is
    taken: another thread of the parent may have held it at the fork, and in the child nobody
    would ever release it."""
    if _STATE["forked"]:
        raise EngineError(
            "Taichi was initialised in a parent process before this one was forked; Taichi kernels "
            "hang in a forked child. Start worker processes with the 'spawn' or 'forkserver' method "
            "(multiprocessing.get_context('spawn')), or use the engine only in the children.")


def taichi():
    """The ``taichi`` module, its runtime initialised on the CPU once (or the host's adopted)."""
    with kernel_lock():
        ti = _import_taichi()
        runtime = ti.lang.impl.get_runtime()
        if runtime.prog is None:
            before = _thread_ids()
            with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                # Taichi's offline cache of compiled kernels, unless TI_OFFLINE_CACHE says otherwise
                # (helper processes: one killed while it holds the cache's lock file would leave
                # it locked; Taichi warns when an argument overrides the variable)
                cache = {} if "TI_OFFLINE_CACHE" in os.environ else {"offline_cache": True}
                ti.init(arch=ti.cpu, cpu_max_num_threads=_STATE["threads"] or len(_allowed_cpus()),
                        log_level=ti.WARN, **cache)
            if _STATE["threads"] is None and os.environ.get("TAICHI_MATCH_PIN_THREADS", "1") != "0":
                _pin_threads(sorted(_thread_ids() - before))
        _materialize(ti.lang.impl.get_runtime())          # (ti.init made a new runtime)
        return ti


def _materialize(runtime):
    """Taichi's root fields made now, in this thread: Taichi 1.7 makes them on its first compile
    and asserts that this happens in the thread that called ``ti.init`` (``llvm_context.cpp``:
    ``this_thread::get_id() == main_thread_id_``), so a first match from another thread, a ROS
    executor's say, failed with Taichi's RuntimeError. Once made, any thread may compile. A host
    that started Taichi itself in another thread, compiling nothing there, gets ``EngineError``."""
    if getattr(runtime, "materialized", True):
        return
    try:
        runtime.materialize()
    except RuntimeError as exc:
        if "main_thread_id" not in str(exc):
            raise
        raise EngineError("Taichi was started (ti.init) in another thread and has compiled nothing yet; Taichi "
                          "makes its first compile in that thread only: run a first match there (or call "
                          "taichi.lang.impl.get_runtime().materialize() there after ti.init)") from None


def kernels(build):
    """What ``build(ti)`` returns (a module's Taichi kernels), built once, Taichi started first."""
    with kernel_lock():
        ti = taichi()
        if build not in _BUILT:
            _BUILT[build] = build(ti)
        return _BUILT[build]


def _allowed_cpus():
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):              # not Linux
        return list(range(os.cpu_count() or 1))


def _thread_ids():
    try:
        return {int(t) for t in os.listdir(f"/proc/{os.getpid()}/task")}
    except OSError:
        return set()


def _pin_threads(thread_ids):
    """Pin the threads Taichi started, one per allowed CPU in turn (Linux only).

    Taichi's CPU thread pool sleeps between launches; on wake-up Linux often puts both workers on
    the same core, and a launch then takes as long as on one thread (measured on the 2-core
    machine: median 1.2 ms instead of 0.65 ms for the 13-pose stencil on the paper's corridor).
    Done only when taichi_match initialises Taichi itself; TAICHI_MATCH_PIN_THREADS=0 turns it off.
    """
    cpus = _allowed_cpus()
    for n, tid in enumerate(thread_ids):
        try:
            os.sched_setaffinity(tid, {cpus[n % len(cpus)]})
        except (AttributeError, OSError):
            return


def runtime_program():
    """The current Taichi program (a new one after each ``ti.init``)."""
    return _STATE["ti"].lang.impl.get_runtime().prog
