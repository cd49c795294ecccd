"""Launching Taichi kernels with less overhead than Taichi's own call: the private launch path.

Taichi's Python call checks and converts every argument on every call, about 30 us per launch
here, a tenth of a small launch. ``launch`` keeps a kernel's compiled form after its first
(ordinary) call and passes the arrays' addresses straight to a launch context; a ``Launcher``
goes further and relaunches one context per batch shape (measured in bench/ABLATION.md: 1.15x
end to end on the corridor). This uses Taichi 1.7's internals (``Kernel._primal``,
``compiled_kernels``, ``Program.launch_kernel``): it is probed once, on the Taichi version, and any
error falls back to the ordinary call, as does TAICHI_MATCH_DIRECT_LAUNCH=0.
"""

import os

import numpy as np

from ._taichi import kernel_lock, runtime_program, taichi

__all__ = ["launch", "Launcher", "direct_launch_enabled", "use_direct_launch", "row_spread"]

_WRITTEN_FOR = (1, 7)            # the Taichi (major, minor) whose internals this path uses

# Taichi's CPU backend runs a parallel loop of n items in tasks of max(512, n / (32 x threads)) items
# (``block_dim`` when adaptive, its default): a loop over the rows of a map of fewer than 1024 rows
# is one task, on one thread. A kernel working a row at a time loops over at least this many
# items instead (``row_spread``; strips of rows before 2026-12-06): measured on the preparation of edmonton's
# laser submaps (832 x 1036 cells and its two coarser levels), 2 threads, the median over its
# 16 submaps 11.3-12.3 -> 10.5-10.8 ms (the level's conflict grid 1.6 -> 1.0 ms in strips, the
# coarser levels' stamps 1.56 -> 1.16 and 0.76 -> 0.65 ms spread)
ROW_ITEMS = 4096

_FAST = {}       # (kernel, count mode, dtypes) -> (program, compiled kernel, compiled data), or None: no fast path
_DIRECT = {"enabled": None}      # None: not probed yet


def direct_launch_enabled() -> bool:
    """Whether launches go through Taichi's launch context directly: probed once, on the Taichi
    version whose internals the path was written for (1.7), unless TAICHI_MATCH_DIRECT_LAUNCH=0."""
    if _DIRECT["enabled"] is None:
        ti = taichi()
        _DIRECT["enabled"] = (tuple(getattr(ti, "__version__", ()))[:2] == _WRITTEN_FOR
                              and os.environ.get("TAICHI_MATCH_DIRECT_LAUNCH", "1") != "0"
                              and hasattr(runtime_program(), "launch_kernel"))
    return _DIRECT["enabled"]


def use_direct_launch(enabled: bool) -> None:
    """Turn the direct path on or off for this process (for a benchmark's A/B; on a Taichi other
    than 1.7 it cannot be turned on)."""
    _DIRECT["enabled"] = None
    _DIRECT["enabled"] = bool(enabled) and direct_launch_enabled()


def row_spread(rows: int) -> np.ndarray:
    """An int32 array whose length S makes ``rows`` x S reach ``ROW_ITEMS``: a kernel whose rows
    cannot be cut (each of its items goes through every wall near its row) loops over (row, S)
    and works row r at item (r, 0) alone, the others empty, so that its rows spread over Taichi's
    tasks (``ROW_ITEMS``)."""
    return np.zeros(max(1, -(-ROW_ITEMS // max(rows, 1))), dtype=np.int32)


def launch(kernel, arrays, mode=None):
    """``kernel(*arrays, mode)`` (``kernel(*arrays)`` if mode is None), through Taichi's launch
    context directly once compiled.

    Taichi's Python call path checks and converts every argument on every call, about 30 us per
    launch here, a tenth of a small launch. Our arrays are always C-contiguous with the dtypes
    the kernels declare, so after the first (ordinary) call with a given ``mode`` we keep the
    compiled kernel and pass the arrays' addresses and shapes straight to a launch context,
    which is what Taichi 1.7's ``Kernel.launch_kernel`` does for numpy arrays. The compiled
    kernel belongs to the Taichi program it was made in: when a host calls ``ti.init`` or
    ``ti.reset`` again, the next call goes the ordinary way and is kept anew. Should Taichi's
    internals differ from 1.7's, the ordinary call is used.
    """
    prog = runtime_program()
    key = _fast_key(kernel, arrays, mode)
    fast = _FAST.get(key, False) if direct_launch_enabled() else None
    if fast and fast[0] is prog and all(array.flags.c_contiguous for array in arrays):
        _, t_kernel, compiled = fast
        prog.launch_kernel(compiled, _context(t_kernel, arrays))
        return
    kernel(*arrays, *_templates(mode))             # (Taichi copies arrays that are not C-contiguous)
    if fast is False or (fast and fast[0] is not prog):
        _FAST[key] = _compiled(kernel, arrays, mode)


class Launcher:
    """One kernel and the arguments that stay the same from launch to launch (the maps), with
    buffers for the others (poses in, sums out) kept per shape, each set in a launch context once.

    ``layout`` lists the kernel's arguments in order: an array where it is fixed, None where a
    varying input goes; the output comes last. ``run`` copies the inputs into their buffers and
    relaunches the context as it is, so after the first launch of a shape nothing goes through
    Taichi's Python layer or ``launch``'s argument setting (measured: 60-70 us less per launch,
    a third of a laser submap's launch). Every buffer lives as long as the launcher, so the
    addresses in a context stay valid; a new Taichi program (``ti.init`` again) gets new contexts.
    """

    _MAX_SHAPES = 8              # batch shapes kept (the optimisers use two or three)

    def __init__(self, kernel, layout):
        self._kernel = kernel    # called under the lock: returns the Taichi kernel
        self._layout = layout
        self._bound = {}

    def run(self, inputs, out_shape, mode=None):
        """Launch on ``inputs`` (float64 arrays, in the order of the None slots) and ``mode``;
        returns the float32 output of ``out_shape``, valid until the next run."""
        key = (tuple(x.shape for x in inputs), out_shape, mode)
        with kernel_lock():
            bound = self._bound.get(key)
            if bound is None:
                if len(self._bound) >= self._MAX_SHAPES:
                    self._bound.clear()
                buffers = [np.empty(x.shape, dtype=np.float64) for x in inputs]
                out = np.empty(out_shape, dtype=np.float32)
                slots = iter(buffers)
                arrays = tuple(next(slots) if a is None else a for a in self._layout) + (out,)
                bound = self._bound[key] = (buffers, out, _BoundLaunch(self._kernel(), arrays, mode))
            buffers, out, launch = bound
            for buffer, x in zip(buffers, inputs):
                buffer[...] = x
            launch()
        return out


class _BoundLaunch:
    """``kernel(*arrays, mode)`` launched again and again on the same arrays: once the kernel is
    compiled for them (by this launch's first call through ``launch``, or by any launch before it),
    a launch context with the arrays' addresses, made once, is relaunched (Taichi 1.7's CPU
    launcher reads the addresses afresh from the context at every launch and changes nothing else
    in it). A one-off launch costs what ``launch`` does."""

    def __init__(self, kernel, arrays, mode):
        if not all(array.flags.c_contiguous for array in arrays):
            raise ValueError("a bound launch needs C-contiguous arrays")
        self._kernel, self._arrays, self._mode = kernel, arrays, mode
        self._prog = self._compiled = self._ctx = None

    def __call__(self):
        prog = runtime_program()
        if self._ctx is not None and self._prog is prog and direct_launch_enabled():
            prog.launch_kernel(self._compiled, self._ctx)
            return
        fast = _FAST.get(_fast_key(self._kernel, self._arrays, self._mode))
        if fast and fast[0] is prog and direct_launch_enabled():
            try:
                ctx = _context(fast[1], self._arrays)
            except Exception:  # pragma: no cover - another Taichi version: the ordinary call
                _FAST[_fast_key(self._kernel, self._arrays, self._mode)] = None
            else:
                self._prog, self._compiled, self._ctx = prog, fast[2], ctx
                prog.launch_kernel(self._compiled, self._ctx)
                return
        launch(self._kernel, self._arrays, self._mode)


def _fast_key(kernel, arrays, mode):
    """``_FAST``'s key: a kernel with an untyped array argument compiles once per dtype."""
    return kernel, mode, tuple(array.dtype.num for array in arrays)


def _context(t_kernel, arrays):
    """A launch context of ``t_kernel`` holding the arrays' addresses and shapes."""
    ctx = t_kernel.make_launch_context()
    for index, array in enumerate(arrays):
        ctx.set_arg_external_array_with_shape((index,), array.ctypes.data, array.nbytes, array.shape, 0)
    return ctx


def _templates(mode):
    """The template arguments after the arrays: ``mode`` (a tuple: several), or none (None)."""
    return () if mode is None else mode if isinstance(mode, tuple) else (mode,)


def _compiled(kernel, arrays, mode):
    """(program, compiled kernel, compiled data) of ``kernel`` for these arguments, or None."""
    try:
        primal = kernel._primal
        t_kernel = primal.compiled_kernels[primal.ensure_compiled(*arrays, *_templates(mode))]
        prog = runtime_program()
        compiled = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
        t_kernel.make_launch_context()
        return prog, t_kernel, compiled
    except Exception:  # pragma: no cover - another Taichi version
        return None
