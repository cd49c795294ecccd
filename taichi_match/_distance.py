"""Squared distance transforms on the grid, as Taichi kernels (Felzenszwalb & Huttenlocher, "Distance
Transforms of Sampled Functions", Theory of Computing 8, 2012).

``squared_distance(f)`` returns, per cell c, ``min_o (|c - o|^2 + f(o))`` over the cells o where
``f`` is finite (distances in cells; +inf where no cell is): with ``f = 0`` on the walls and +inf
elsewhere, the squared Euclidean distance to the nearest wall, exact (integers in float64). (With
``f(o) = -2 s^2 ln p(o)``, ``exp(-D / (2 s^2))`` would be the upper envelope of grey walls'
Gaussians; the blur does not use that yet.) Two passes of the one-dimensional transform, down every
column then along every row, each line a work item (the lower envelope of parabolas, with its
scratch arrays per line), so the result does not depend on the schedule. Equal to
``scipy.ndimage.distance_transform_edt`` bit for bit in the tests, and 3x faster here on
800 x 800 cells (20 ms against 60: no feature indices, both passes reading memory in order).
"""

import numpy as np

from ._kernels import _STATE, ensure_initialized, kernel_lock

__all__ = ["squared_distance", "wall_distance"]

_KERNELS = {}


def _build(ti):
    f64_2d = ti.types.ndarray(dtype=ti.f64, ndim=2)
    i32_2d = ti.types.ndarray(dtype=ti.i32, ndim=2)

    @ti.kernel
    def rows(f: f64_2d, d: f64_2d, v: i32_2d, z: f64_2d):
        # per row: the lower envelope of the parabolas (x - q)^2 + f(q) over its finite f(q), in v
        # (their q) and z (where each takes over), then read off at every x
        n = f.shape[1]
        for line in range(f.shape[0]):
            k = -1
            for q in range(n):
                fq = f[line, q]
                if fq < ti.math.inf:
                    qf = ti.cast(q, ti.f64)
                    s = ti.f64(-ti.math.inf)
                    while k >= 0:
                        p = v[line, k]
                        pf = ti.cast(p, ti.f64)
                        s = ((fq + qf * qf) - (f[line, p] + pf * pf)) / (2.0 * (qf - pf))
                        if s > z[line, k]:
                            break
                        k -= 1
                    k += 1
                    v[line, k] = q
                    z[line, k] = ti.select(k == 0, -ti.math.inf, s)
                    z[line, k + 1] = ti.math.inf
            if k < 0:
                for q in range(n):
                    d[line, q] = ti.math.inf
            else:
                j = 0
                for q in range(n):
                    while z[line, j + 1] < q:
                        j += 1
                    p = v[line, j]
                    dq = ti.cast(q - p, ti.f64)
                    d[line, q] = dq * dq + f[line, p]

    return rows


class _Scratch:
    """Flat buffers kept between calls, grown as needed: fresh arrays of megabytes cost a page
    fault per 4 KiB on first touch, which here cost more than the transform itself (measured:
    34 ms against 13 ms for 800 x 800 cells). Grids above ``KEEP_CELLS`` get fresh arrays, so
    at most about 60 MB stay held."""

    KEEP_CELLS = 2**21

    def __init__(self):
        self._flat = {}

    def get(self, name, shape, dtype):
        size = int(np.prod(shape))
        if size > self.KEEP_CELLS:
            self._flat.pop(name, None)
            return np.empty(shape, dtype=dtype)
        flat = self._flat.get(name)
        if flat is None or flat.size < size or flat.dtype != dtype:
            flat = self._flat[name] = np.empty(max(size, 1), dtype=dtype)
        return flat[:size].reshape(shape)


_SCRATCH = _Scratch()


def squared_distance(f: np.ndarray) -> np.ndarray:
    """``min_o (|c - o|^2 + f(o))`` per cell c (see the module docstring); ``f`` (H, W), +inf where
    no source is. Returns float64 (H, W), +inf everywhere when ``f`` has no finite value."""
    f = np.asarray(f, dtype=np.float64)
    h, w = f.shape
    d = np.empty((h, w))
    with kernel_lock():
        ensure_initialized()
        if "kernels" not in _KERNELS:
            _KERNELS["kernels"] = _build(_STATE["ti"])
        rows = _KERNELS["kernels"]
        # down the columns as rows of the transpose: both passes read memory in order
        f_t = _SCRATCH.get("f_t", (w, h), np.float64)
        f_t[...] = f.T
        g_t = _SCRATCH.get("g_t", (w, h), np.float64)
        rows(f_t, g_t, _SCRATCH.get("v", (w, h + 1), np.int32), _SCRATCH.get("z", (w, h + 2), np.float64))
        g = _SCRATCH.get("f_t", (h, w), np.float64)            # f_t is spent
        g[...] = g_t.T
        rows(g, d, _SCRATCH.get("v", (h, w + 1), np.int32), _SCRATCH.get("z", (h, w + 2), np.float64))
    return d


def wall_distance(walls: np.ndarray) -> np.ndarray:
    """The Euclidean distance, in cells, from every cell to the nearest True cell of ``walls``
    (+inf when there is none): ``scipy.ndimage.distance_transform_edt(~walls)``, bit for bit."""
    return np.sqrt(squared_distance(np.where(walls, 0.0, np.inf)))
