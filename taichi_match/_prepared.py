"""Maps prepared once for matching: blurred (sec. 3.2) and laid out for the engines.

A prepared map can play either role: as A it is a float32 grid padded with one ring of unknown
cells; as B it is a float32 grid plus the list of rows holding known cells and, per row, the
column range that holds them, so the kernels skip unknown rows and margins. Unknown is -1.
"""

import weakref

import numpy as np

from ._blur import blur
from ._cost import AffineMap
from ._errors import InvalidOptionError
from ._grid import GridMap
from ._kernels import TaichiEngine
from ._pyramid import coarsen
from ._reference import NumpyDiscrepancy

__all__ = ["PreparedMap", "make_engine", "ENGINES"]

ENGINES = ("taichi", "numpy")
_UNKNOWN = np.float32(-1.0)


class PreparedMap:
    """``grid`` blurred (``blur_kind``, ``blur_width`` metres), with engine-ready arrays."""

    def __init__(self, grid: GridMap, blur_width: float, blur_kind: str = "gaussian"):
        # Only a weak reference to the source map: the matcher caches prepared maps in a
        # WeakKeyDictionary keyed by that map, and a strong one would keep both alive forever.
        self._grid = weakref.ref(grid)
        self.resolution = grid.resolution
        self.blur_width = float(blur_width)
        self.blur_kind = blur_kind
        blurred = blur(grid, blur_width, kind=blur_kind)
        self.blurred = blurred if blurred is not grid else grid.with_prob(grid.prob)
        values = np.where(np.isnan(self.blurred.prob), _UNKNOWN, self.blurred.prob).astype(np.float32)
        self.padded = np.pad(values, 1, constant_values=_UNKNOWN)          # role A
        self.values = np.ascontiguousarray(values)                         # role B
        known = grid.known
        rows = np.flatnonzero(known.any(axis=1))
        first = known[rows].argmax(axis=1)
        last = known.shape[1] - known[rows][:, ::-1].argmax(axis=1)
        self.rows = np.ascontiguousarray(np.column_stack([rows, first, last]), dtype=np.int32)  # (R, 3)
        self.n_known = int(known.sum())
        # rms distance of the known cells from the map frame's origin: a rotation by d theta moves
        # a typical cell by radius * d theta (at least one cell, for maps of a single cell)
        centres = grid.cell_centres()[known]
        self.radius = max(float(np.sqrt(np.mean(np.sum(centres**2, axis=1)))) if len(centres) else 0.0,
                          grid.resolution)

        self._coarser = None
        self._coarser_grid = None

    @property
    def grid(self) -> GridMap:
        """The map this was prepared from (alive for as long as its owner keeps it)."""
        grid = self._grid()
        if grid is None:
            raise ReferenceError("the map this PreparedMap was made from no longer exists")
        return grid

    def coarser(self):
        """The next level of the pyramid: the map with cells twice as large, blurred alike (cached)."""
        if self._coarser is None:
            self._coarser_grid = coarsen(self.grid)            # owned here: the level holds it weakly
            self._coarser = PreparedMap(self._coarser_grid, self.blur_width, self.blur_kind)
        return self._coarser

    def level(self, k):
        """Level ``k`` of the pyramid (0: this map)."""
        prepared = self
        for _ in range(k):
            prepared = prepared.coarser()
        return prepared

    def __repr__(self):
        return f"PreparedMap({self._grid()!r}, blur {self.blur_kind} {self.blur_width} m)"


def make_engine(name, a: PreparedMap, b: PreparedMap):
    """A callable ``(poses (N, 3), count="all") -> (discrepancy (N,), overlap (N,) or None)``.

    ``count`` says whose overlap (known cells of B on known cells of A) is needed: "all" poses,
    only the "first" (the others may be returned as 0), or "none" (None may be returned); an
    engine may skip the counting that is not asked for.
    """
    if name == "taichi":
        kernel = TaichiEngine(a.padded, b.values, b.rows)
        affine = AffineMap(a.blurred, b.blurred)
        return lambda poses, count="all": kernel(affine(poses), count)
    if name == "numpy":
        oracle = NumpyDiscrepancy(a.blurred, b.blurred)
        return lambda poses, count="all": oracle(poses)
    raise InvalidOptionError(f"engine must be one of {ENGINES}; got {name!r}")
