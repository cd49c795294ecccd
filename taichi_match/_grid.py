"""The occupancy grid type and its conventions: eq. (2) and (3) of the paper.

Conventions, stated once for the whole library:

- ``prob[i, j]`` is the occupancy probability of cell (i, j), in [0, 1]; NaN marks an unknown cell.
- ``i`` is the row and grows with y; ``j`` is the column and grows with x (as ROS
  ``nav_msgs/OccupancyGrid``, whose data is row-major with row 0 at the lowest y).
- ``resolution`` is the cell side in metres; ``origin = (x0, y0)`` is the outer corner of cell (0, 0)
  in the map's own frame, so cell (i, j) covers x in [x0 + j*res, x0 + (j+1)*res) and
  y in [y0 + i*res, y0 + (i+1)*res).
- ``origin = (x0, y0, yaw)`` (as in a ROS map_server YAML) also turns the grid by ``yaw`` radians
  about that corner: the cell with local coordinates (x, y) = ((j + 1/2) res, (i + 1/2) res) has
  its centre at (x0, y0) + R(yaw) (x, y) in the map's frame. ``yaw`` is 0 unless given.
- A cell is represented by its centre (eq. 2); a point falls in the cell given by floor (eq. 3).
"""

import numbers
from typing import Optional

import numpy as np
import numpy.typing as npt

from ._errors import InvalidMapError, shown

__all__ = ["GridMap", "MAX_CELLS", "cells", "trinary", "trinary_code", "trinary_values", "UNKNOWN", "FREE", "OCCUPIED"]

MAX_CELLS = 2**31 - 1 - 4 * 65536      # cells of a map, padding included, must fit 32-bit indices


class GridMap:
    """An immutable 2-D occupancy grid with its resolution and origin.

    The conventions (rows grow with y, cells represented by their centres, ``origin``) are those
    of the module docstring of ``taichi_match._grid``.

    Parameters
    ----------
    prob : array_like, shape (rows, cols)
        Occupancy probabilities in [0, 1], NaN for unknown cells. Row i grows with y. Integer and
        boolean arrays are taken as probabilities; the masked cells of a masked array are unknown.
        The values are copied (float64, read-only).
    resolution : float
        Cell side in metres, > 0.
    origin : (float, float) or (float, float, float)
        (x0, y0) of the outer corner of cell (0, 0), metres, in the map's own frame; or
        (x0, y0, yaw) as in a ROS map_server YAML, the grid then turned by ``yaw`` radians about
        that corner.

    Raises
    ------
    InvalidMapError
        If ``prob`` is not a non-empty 2-D array of values in [0, 1] or NaN (or is larger than
        ``MAX_CELLS``), ``resolution`` is not finite and > 0, or ``origin`` is not 2 or 3 finite
        numbers.

    Examples
    --------
    A 2 x 2 m room of 20 x 20 cells, unknown outside a free square with a wall along its
    bottom edge:

    >>> import numpy as np
    >>> from taichi_match import GridMap
    >>> prob = np.full((20, 20), np.nan)
    >>> prob[5:15, 5:15] = 0.0
    >>> prob[5, 5:15] = 1.0                       # row 5: y in [-0.5, -0.4)
    >>> grid = GridMap(prob, resolution=0.1, origin=(-1.0, -1.0))
    >>> grid
    GridMap(20x20 cells, resolution=0.1 m, origin=(-1.0, -1.0), 100 known cells)
    >>> grid.extent
    (-1.0, 1.0, -1.0, 1.0)
    >>> row, col = grid.cell_of([0.03, -0.47])
    >>> int(row), int(col), float(grid.prob[int(row), int(col)])
    (5, 10, 1.0)
    >>> grid.prob.flags.writeable
    False
    """

    __slots__ = ("_prob", "_resolution", "_origin", "_yaw", "_known", "_code", "_table", "__weakref__")

    def __init__(self, prob: npt.ArrayLike, resolution: float, origin: npt.ArrayLike = (0.0, 0.0)) -> None:
        self._known = self._code = self._table = None
        self._prob = _check_prob(prob)
        self._resolution = _check_resolution(resolution)
        *xy, self._yaw = _check_origin(origin)
        self._origin = tuple(xy)

    @property
    def prob(self) -> np.ndarray:
        """Read-only float64 array (rows, cols) of occupancy probabilities; NaN = unknown."""
        if self._prob is None:                  # a map made from its codes (``_from_code``)
            prob = trinary_values(self._code) if self._table is None else self._table.take(self._code)
            prob.setflags(write=False)
            self._prob = prob
        return self._prob

    @property
    def resolution(self) -> float:
        """Cell side, metres."""
        return self._resolution

    @property
    def origin(self) -> tuple[float, float]:
        """(x0, y0): outer corner of cell (0, 0), metres."""
        return self._origin

    @property
    def yaw(self) -> float:
        """Rotation of the grid about ``origin`` in the map's frame, radians (0 for most maps)."""
        return self._yaw

    @property
    def corner_pose(self) -> tuple[float, float, float]:
        """(x0, y0, yaw): the pose of the grid's local frame (corner of cell (0, 0)) in the map frame,
        as ``origin`` in a map_server YAML."""
        return (*self._origin, self._yaw)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the grid."""
        return self._prob.shape if self._prob is not None else self._code.shape

    @property
    def known(self) -> np.ndarray:
        """Read-only boolean mask of known (non-NaN) cells (made once: the map never changes)."""
        if self._known is None:
            known = ~np.isnan(self._prob) if self._prob is not None else self._code != UNKNOWN
            known.setflags(write=False)
            self._known = known
        return self._known

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the grid in the map frame, metres (the bounding box
        of the turned grid when yaw != 0).

        Examples
        --------
        >>> import numpy as np
        >>> from taichi_match import GridMap
        >>> turned = GridMap(np.zeros((10, 20)), 0.1, origin=(1.0, 0.0, np.pi / 2))
        >>> [round(v, 3) for v in turned.extent]              # 2 m along x become 2 m along y
        [0.0, 1.0, 0.0, 2.0]
        """
        rows, cols = self.shape
        w, h = cols * self._resolution, rows * self._resolution
        c, s = np.cos(self._yaw), np.sin(self._yaw)
        xs = self._origin[0] + np.array([0.0, c * w, -s * h, c * w - s * h])
        ys = self._origin[1] + np.array([0.0, s * w, c * h, s * w + c * h])
        return (float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max()))

    def cell_centres(self, rows: npt.ArrayLike | None = None,
                     cols: npt.ArrayLike | None = None) -> np.ndarray:
        """Eq. (2): the (x, y) centres of cells (rows[k], cols[k]) in the map frame.

        Parameters
        ----------
        rows, cols : array_like of int, optional
            Cell indices, broadcast together; both None (the default): every cell.

        Returns
        -------
        numpy.ndarray, shape (..., 2)
            (x, y) in metres, in the map frame; (rows, cols, 2) for every cell.

        Examples
        --------
        >>> import numpy as np
        >>> from taichi_match import GridMap
        >>> grid = GridMap(np.zeros((20, 20)), 0.1, origin=(-1.0, -1.0))
        >>> grid.cell_centres([0, 19], [0, 10]).round(3).tolist()
        [[-0.95, -0.95], [0.05, 0.95]]
        >>> grid.cell_centres().shape
        (20, 20, 2)
        """
        if rows is None and cols is None:
            rows, cols = np.indices(self.shape)
        lx = (np.asarray(cols, dtype=np.float64) + 0.5) * self._resolution
        ly = (np.asarray(rows, dtype=np.float64) + 0.5) * self._resolution
        c, s = np.cos(self._yaw), np.sin(self._yaw)
        x0, y0 = self._origin
        return np.stack([x0 + c * lx - s * ly, y0 + s * lx + c * ly], axis=-1)

    def cell_of(self, points: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Eq. (3): integer (row, col) of the cells the map-frame points (..., 2) fall in.

        Parameters
        ----------
        points : array_like, shape (..., 2)
            (x, y) in the map frame, metres.

        Returns
        -------
        rows, cols : numpy.ndarray, shape (...)
            The floor of ``grid_coordinates``, as float64 arrays of whole numbers; they may lie
            outside the grid (negative or >= ``shape``).

        Examples
        --------
        >>> import numpy as np
        >>> from taichi_match import GridMap
        >>> grid = GridMap(np.zeros((20, 20)), 0.1, origin=(-1.0, -1.0))
        >>> rows, cols = grid.cell_of([[0.03, -0.47], [-1.05, 0.0]])
        >>> rows.tolist(), cols.tolist()                    # the second point is left of the grid
        ([5.0, 10.0], [10.0, -1.0])
        """
        rows, cols = self.grid_coordinates(points)
        return np.floor(rows), np.floor(cols)

    def grid_coordinates(self, points: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (row, col) of map-frame points (..., 2): cell (i, j) spans [i, i+1) x [j, j+1),
        its centre is (i + 1/2, j + 1/2).

        Parameters
        ----------
        points : array_like, shape (..., 2)
            (x, y) in the map frame, metres.

        Returns
        -------
        rows, cols : numpy.ndarray, shape (...)
            Continuous row and column coordinates (float64).

        Examples
        --------
        >>> import numpy as np
        >>> from taichi_match import GridMap
        >>> grid = GridMap(np.zeros((20, 20)), 0.1, origin=(-1.0, -1.0))
        >>> rows, cols = grid.grid_coordinates(grid.cell_centres([3], [7]))
        >>> rows.round(6).tolist(), cols.round(6).tolist()
        ([3.5], [7.5])
        """
        points = np.asarray(points, dtype=np.float64)
        dx = points[..., 0] - self._origin[0]
        dy = points[..., 1] - self._origin[1]
        c, s = np.cos(self._yaw), np.sin(self._yaw)
        return (-s * dx + c * dy) / self._resolution, (c * dx + s * dy) / self._resolution

    def with_prob(self, prob: npt.ArrayLike) -> "GridMap":
        """A map with the same geometry (resolution, origin, yaw) and new probabilities.

        Parameters
        ----------
        prob : array_like, shape (rows, cols)
            As for ``GridMap``; the shape may differ from this map's (what is kept is the cell size
            and the corner pose of cell (0, 0)).

        Returns
        -------
        GridMap

        Examples
        --------
        >>> import numpy as np
        >>> from taichi_match import GridMap
        >>> grid = GridMap(np.zeros((20, 20)), 0.1, origin=(-1.0, -1.0, 0.5))
        >>> walls = grid.with_prob(np.ones((20, 20)))
        >>> walls.corner_pose == grid.corner_pose, float(walls.prob.mean())
        (True, 1.0)
        """
        return GridMap(prob, self._resolution, self.corner_pose)

    def _with_trusted(self, prob):
        """``with_prob`` for an array the library made itself (``_trusted``)."""
        return _trusted(prob, self._resolution, self.corner_pose)

    def __repr__(self):
        rows, cols = self.shape
        known = int(self.known.sum())
        origin = self._origin if self._yaw == 0.0 else self.corner_pose
        return (f"GridMap({rows}x{cols} cells, resolution={self._resolution} m, origin={origin}, "
                f"{known} known cells)")


def _trusted(prob, resolution, corner_pose) -> GridMap:
    """A GridMap of a float64 2-D array the library made itself from checked maps (values in
    [0, 1] or NaN, never changed afterwards): not checked or copied, only made read-only. The
    checks are passes over every cell, a fifth of preparing a map for matching."""
    grid = GridMap.__new__(GridMap)
    prob.setflags(write=False)
    grid._prob = prob
    grid._known = grid._code = grid._table = None
    grid._resolution = float(resolution)
    grid._origin, grid._yaw = (float(corner_pose[0]), float(corner_pose[1])), float(corner_pose[2])
    return grid


def _from_code(code: np.ndarray, resolution, corner_pose, table: Optional[np.ndarray] = None) -> GridMap:
    """A map given by a code per cell (uint8, read-only from here on), its float64 probabilities
    made only when first read: a byte a cell to keep or send where the map has eight. The codes
    are ``trinary_code``'s (``table`` None: what ``grid_code`` returns without a pass over them),
    or indices into ``table``, the float64 probabilities of the codes, NaN at code 0 only (0 is
    unknown, as ``UNKNOWN``, and every other code known)."""
    grid = _trusted(np.empty((0, 0)), resolution, corner_pose)
    code.setflags(write=False)
    grid._prob, grid._code, grid._table = None, code, table
    return grid



def twin(grid: GridMap) -> GridMap:
    """A GridMap of its own over ``grid``'s read-only data (no copy; a map made by ``_from_code``
    stays one)."""
    if grid._code is not None:
        return _from_code(grid._code, grid.resolution, grid.corner_pose, grid._table)
    return grid._with_trusted(grid.prob)


def grid_code(grid: GridMap) -> np.ndarray:
    """``trinary_code(grid.prob)``, without a pass for a map made by ``_from_code``."""
    return grid._code if grid._code is not None and grid._table is None else trinary_code(grid.prob)


def _check_prob(prob):
    try:
        arr = np.asarray(prob)
    except Exception as exc:  # pragma: no cover - exotic array-likes
        raise InvalidMapError(f"prob must be a 2-D array of probabilities; got {type(prob).__name__}") from exc
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
                                   or arr.dtype == bool):
        raise InvalidMapError(f"prob must hold real numbers (float, int or bool); got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise InvalidMapError(f"prob must be 2-D (rows, cols); got {arr.ndim}-D with shape {arr.shape}")
    if arr.shape[0] < 1 or arr.shape[1] < 1:
        raise InvalidMapError(f"prob must have at least one row and one column; got shape {arr.shape}")
    if arr.size > MAX_CELLS:
        raise InvalidMapError(f"a map of {arr.shape[0]} x {arr.shape[1]} cells is too large: at most {MAX_CELLS} "
                              f"cells (the kernels index cells with 32-bit integers); crop or coarsen it")
    try:
        arr = np.array(arr, dtype=np.float64, copy=True)
        if np.ma.isMaskedArray(prob):            # masked cells are unknown (np.asarray drops the mask)
            arr[np.ma.getmaskarray(prob)] = np.nan
    except MemoryError as exc:
        raise InvalidMapError(f"not enough memory for a map of {arr.shape[0]} x {arr.shape[1]} cells "
                              f"({arr.size * 8 / 2**30:.1f} GiB as float64); crop or coarsen it") from exc
    # the least and largest known values (fmin and fmax skip NaN: NaN only if no cell is known),
    # two passes without the copies of np.nanmin or of indexing the known cells (10x faster)
    lo, hi = np.fmin.reduce(arr, axis=None), np.fmax.reduce(arr, axis=None)
    if np.isinf(lo) or np.isinf(hi):
        raise InvalidMapError("prob holds infinite values; use NaN for unknown cells and [0, 1] otherwise")
    if lo < 0.0 or hi > 1.0:
        raise InvalidMapError(f"prob must lie in [0, 1] (NaN = unknown); got values in [{lo:g}, {hi:g}]")
    arr.setflags(write=False)
    return arr


def _check_resolution(resolution):
    if isinstance(resolution, bool) or not isinstance(resolution, (numbers.Real, np.floating, np.integer)):
        raise InvalidMapError(f"resolution must be a positive number of metres per cell; got {shown(resolution)}")
    res = float(resolution)
    if not np.isfinite(res) or res <= 0.0:
        raise InvalidMapError(f"resolution must be finite and > 0 (metres per cell); got {res}")
    return res


def _check_origin(origin):
    """(x0, y0, yaw) as floats from (x0, y0) or (x0, y0, yaw)."""
    try:
        arr = np.asarray(origin, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidMapError(f"origin must be (x0, y0) or (x0, y0, yaw) in metres and radians; "
                              f"got {shown(origin)}") from exc
    if arr.shape not in ((2,), (3,)):
        raise InvalidMapError(f"origin must be (x0, y0) or (x0, y0, yaw), shape (2,) or (3,); got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidMapError(f"origin must be finite; got {arr.tolist()}")
    return (float(arr[0]), float(arr[1]), float(arr[2]) if arr.shape == (3,) else 0.0)


def cells(mask: np.ndarray):
    """(rows, cols) of the True cells of a 2-D mask in row-major order: ``np.nonzero(mask)``, from
    the flat indices (4x faster on laser submaps: NumPy's 2-D nonzero works index by index)."""
    return np.divmod(np.flatnonzero(mask), mask.shape[1])


def trinary(grid: GridMap, *, occupied: float = 0.65, free: float = 0.196) -> GridMap:
    """``grid`` as ROS ``map_saver`` writes it: p > ``occupied`` -> 1, p < ``free`` -> 0, anything
    between -> unknown (NaN). The default thresholds are map_saver's.

    How grey probabilities enter the cost: a cell seen free once (p = 0.4 after one log-odds miss
    of -0.4) against one seen free often (p near 0) would add 0.4 to e, and thousands of such
    differences pull the minimum toward poses with less overlap (measured on laser-built submaps:
    bench/TUNING.md). Maps that are already trinary are unchanged.

    Examples
    --------
    >>> import numpy as np
    >>> from taichi_match import GridMap
    >>> from taichi_match._grid import trinary
    >>> grid = GridMap([[0.1, 0.4, 0.9, np.nan]], 0.05)
    >>> trinary(grid).prob.tolist()
    [[0.0, nan, 1.0, nan]]
    """
    return grid._with_trusted(trinary_values(trinary_code(grid.prob, occupied, free)))


# ``trinary_code``'s values: a byte per cell, a ninth of the float64 map; known is nonzero
UNKNOWN, FREE, OCCUPIED = 0, 1, 2


def trinary_code(prob: np.ndarray, occupied: float = 0.65, free: float = 0.196) -> np.ndarray:
    """``trinary``'s map as uint8 codes ``OCCUPIED`` (p > ``occupied``), ``FREE`` (p < ``free``)
    and ``UNKNOWN`` (anything else, NaN included)."""
    with np.errstate(invalid="ignore"):          # NaN compares False both times: UNKNOWN
        code = (prob < free).view(np.uint8) * np.uint8(FREE)
        code += (prob > occupied).view(np.uint8) * np.uint8(OCCUPIED)
    return code


def trinary_values(code: np.ndarray) -> np.ndarray:
    """The float64 probabilities (1, 0, NaN) of ``trinary_code``'s codes."""
    values = code.astype(np.float64)
    values -= FREE                                    # FREE -> 0, OCCUPIED -> 1
    np.copyto(values, np.nan, where=code == UNKNOWN)
    return values
