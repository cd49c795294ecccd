"""Maps prepared once for matching: blurred (sec. 3.2) and laid out for the engines.

A prepared map can play either role: as A it is a float32 grid padded with a ring of unknown
cells (``_kernels.PAD`` wide); as B it is a float32 grid plus the list of rows holding known cells
and, per row, the column range that holds them, so the kernels skip unknown rows and margins.
Unknown is -1. With the "envelope" blur these hold the map itself (to count the overlap), and
the conflict grid and the occupied cells that the envelope discrepancy (``_envelope``) uses.
"""

import functools

import numpy as np

from ._blur import blur, blur_everywhere, wall_transform
from ._distance import near_weighted_envelope
from ._envelope import (
    WALL,
    conflict_grid,
    envelope_profile,
    envelope_reach,
    near_conflict_grid,
    points_array,
    wall_points,
)
from ._errors import InvalidOptionError
from ._grid import OCCUPIED, UNKNOWN, GridMap, _from_code, cells, grid_code, trinary_values, twin
from ._kernels import PAD
from ._pyramid import coarsen, halve_code
from ._verdict import CONFLICT_CELLS, WallDistance

__all__ = ["PreparedMap"]

_UNKNOWN = np.float32(-1.0)

# The envelope's walls' distances are stamped around each wall (``near_squared_distance``) while
# walls x (2 reach + 1)^2 is at most this many times the map's cells: measured against the exact
# transforms over every cell (2026-12-04, both spread over Taichi's threads: ``_launch.row_spread``),
# a prepared level each, on the shared robot maps, laser submaps of three logs and gdc_3 tiled to
# 4000 x 4000 cells: the finest levels (walls at 1, ratios 2-23) stamped 2.3-5.7x faster; the
# coarser ones (grey walls) 1.0-2.2x faster up to 30, 0.84-1.55x (median 1.06) at 30-42, 0.67-1.16x
# (median 0.83) beyond 45
STAMP_WORK = 40


class PreparedMap:
    """``grid`` blurred (``blur_kind``, ``blur_width`` metres), with engine-ready arrays.

    With ``evidence="trinary"`` the map is kept as ``_grid.trinary_code`` (a byte per cell) and
    the float64 trinary map is made only when asked for (``grid``): the arrays a prepared map keeps
    are new memory, and on laser submaps its first touch (a page fault per 4 KiB) was most of the
    preparation (measured: a kept float64 copy of a 0.9 M-cell submap 7-12 ms, its codes 1.3 ms).
    """

    def __init__(self, grid: GridMap, blur_width: float, blur_kind: str = "gaussian", blur_growth: float = 1.0,
                 evidence: str = "probability"):
        if evidence not in ("trinary", "probability"):
            raise InvalidOptionError(f"evidence must be 'trinary' or 'probability'; got {evidence!r}")
        # The map's geometry, and for "probability" the map itself: a GridMap of its own over the
        # caller's read-only array (no copy), since the matcher caches prepared maps in a
        # WeakKeyDictionary keyed by the caller's map and a reference to it would keep both alive
        self.frame = twin(grid)
        self._code = grid_code(grid) if evidence == "trinary" else None            # the map, for "trinary"
        self._converted = None
        self.resolution = grid.resolution
        self.blur_width = float(blur_width)
        self.blur_kind = blur_kind
        self.blur_growth = float(blur_growth)
        self._squared = self._wall_distances = self._blurred = None
        if blur_kind == "envelope":             # the envelope discrepancy (``_envelope``)
            self.n_known = self._prepare_envelope()
        else:
            grid = self.grid
            # the walls' distance transform, once for the blur and the verdict
            transform = wall_transform(grid) if blur_kind == "ramp" and blur_width > 0 else None
            self._wall_distances = transform[0] if transform is not None else None
            blurred = blur(grid, blur_width, kind=blur_kind, transform=transform)
            self._blurred = blurred if blurred is not grid else grid._with_trusted(grid.prob)
            self.n_known = int(np.count_nonzero(self.known))
        # padded, values, rows, radius, centroid and spread are made when first asked for: the
        # envelope's coarser levels seldom need the first three and never the last three
        self._coarser = None
        self._wall_distance = None
        self._wall_arrays = {}
        self._ready = 0

    @property
    def lower(self) -> GridMap:
        """The map as compared: blurred for the paper's |p_A - p_B| (``_kernels``); for "envelope"
        the map itself, on which the dense kernel only counts the overlap."""
        return self.grid if self.blur_kind == "envelope" else self.blurred

    @property
    def grid(self) -> GridMap:
        """The map this was prepared from, after the evidence conversion (made when first asked
        for, for "trinary")."""
        if self._code is None:
            return self.frame
        if self._converted is None:
            self._converted = self.frame._with_trusted(trinary_values(self._code))
        return self._converted

    @property
    def known(self) -> np.ndarray:
        """The known cells' mask (for "trinary" made anew at each call: not kept)."""
        return self._code != UNKNOWN if self._code is not None else self.frame.known

    def _prepare_envelope(self) -> int:
        """The conflict grid and the walls; for the verdict the walls' distances; returns the
        number of known cells. With few walls (laser-built maps: 0.1-2 % of the cells) each wall
        stamps the disc of the envelope's reach around it, with the conflict values, in one launch
        (``near_conflict_grid``): at 1 (trinary maps) its squared distance, kept for the verdict,
        from which the conflict grid is the same bit for bit as from the exact transform; grey
        (coarse levels) its weighted envelope. Otherwise the exact transforms over every cell
        (``_blur``)."""
        frame, code = self.frame, self._code
        if code is not None:                         # "trinary": its codes
            known, prob = code, None
            rows, cols = cells(code == OCCUPIED)
            self.walls = rows, cols, weights = rows, cols, np.ones(len(rows))
        elif frame._table is not None:               # a map made from codes and their probabilities
            known, prob = frame._code, frame._table  # (a coarse level of a trinary map): read as such
            rows, cols = cells((prob >= WALL).take(known))
            self.walls = rows, cols, weights = rows, cols, prob.take(known[rows, cols])
        else:
            known, prob = frame.known, frame.prob
            self.walls = rows, cols, weights = wall_points(frame)
        ones = len(rows) > 0 and weights.min() == 1.0
        n_known = int(np.count_nonzero(known))
        width = self.blur_width / frame.resolution
        # out to the envelope's reach, and beyond the verdict's conflict distance (``_verdict``)
        reach = self._reach = max(envelope_reach(width), int(np.ceil(CONFLICT_CELLS)) + 1) if width > 0 else 0
        few = width > 0 and 0 < len(rows) * (2 * reach + 1) ** 2 <= STAMP_WORK * known.size
        ratio = frame.resolution / self.blur_width if width > 0 else 0.0
        self._stamp = few
        if few:
            # (a coarse level of codes keeps no squared distances: the verdict reads the finest's)
            self.conflict, self._squared = near_conflict_grid(known, prob, reach, ratio, self.walls, squared=ones)
        else:
            self.conflict = conflict_grid(self._envelope(ones, keep_distances=True), known == 0)
        return n_known

    def _envelope(self, ones, keep_distances=False):
        """The envelope hi on every cell, for maps not stamped with squared distances: NaN (counts
        as 0) where no wall reaches; ``keep_distances``: the walls' exact distances kept for the
        verdict when they are computed."""
        grid = self.grid
        reach, width = self._reach, self.blur_width / grid.resolution
        if self._stamp:
            rows, cols, weights = self.walls
            profile = envelope_profile(reach, grid.resolution / self.blur_width)[:-1]
            return np.fmax(grid.prob, near_weighted_envelope(rows, cols, weights, grid.shape, reach, profile))
        # walls all 1: the exact transform, also the verdict's; grey: the blur's own (``_blur``)
        transform = wall_transform(grid) if width > 0 and ones else None
        if keep_distances:
            self._wall_distances = transform[0] if transform is not None else None
        return blur_everywhere(grid, self.blur_width, kind="envelope", transform=transform)

    @property
    def blurred(self) -> GridMap:
        """The blurred map; for "envelope" the envelope hi (0 beyond its reach where its walls'
        distances were computed only within it, where it is below 2**-25 (``envelope_reach``)),
        made when first asked for (it only shows what the conflict grid holds)."""
        if self._blurred is None:
            grid = self.lower
            if self._squared is not None:
                reach = self._reach
                envelope = envelope_profile(reach, self.resolution / self.blur_width)[
                    np.minimum(self._squared, reach**2 + 1)]
                hi = np.fmax(grid.prob, envelope)
            else:
                weights = self.walls[2]
                hi = self._envelope(len(weights) > 0 and weights.min() == 1.0)
                if hi is grid.prob:
                    return grid
            hi[np.isnan(grid.prob)] = np.nan
            self._blurred = grid._with_trusted(hi)
        return self._blurred

    @functools.cached_property
    def values(self) -> np.ndarray:
        """Role B: the compared map as a float32 grid, unknown -1."""
        p = self.lower.prob
        values = p.astype(np.float32, order="C")
        values[np.isnan(p)] = _UNKNOWN
        return values

    @functools.cached_property
    def padded(self) -> np.ndarray:
        """Role A: ``values`` padded with a ring of ``PAD`` unknown cells."""
        h, w = self.values.shape
        padded = np.full((h + 2 * PAD, w + 2 * PAD), _UNKNOWN, dtype=np.float32)
        padded[PAD:PAD + h, PAD:PAD + w] = self.values
        return padded

    @functools.cached_property
    def rows(self) -> np.ndarray:
        """Role B: (R, 3) int32 rows holding known cells, with their first and last known column + 1.
        The last as the largest (column + 1) * known of a row, a count type's product and maximum
        (vectorised: 4x faster than the argmax of the rows reversed, whose stride defeats it)."""
        known = self.known
        w = known.shape[1]
        index = np.arange(1, w + 1, dtype=_count_type(w))
        last = np.multiply(known.view(np.uint8), index, dtype=index.dtype).max(axis=1) if w else np.zeros(len(known))
        rows = np.flatnonzero(last)
        first = known.argmax(axis=1)[rows]
        return np.ascontiguousarray(np.column_stack([rows, first, last[rows]]), dtype=np.int32)

    @functools.cached_property
    def _moments(self):
        """(radius, centroid, spread) of the known cells' centres, from the known cells per row and
        per column (their centres are affine in (row, col), so the moments need only those
        counts: a tenth of the time of listing every known cell)."""
        known = self.known
        n = self.n_known
        if n == 0:
            return self.resolution, np.zeros(2), self.resolution
        res = self.resolution
        moments = []
        cells = known.view(np.uint8)
        for axis in (0, 1):                 # per column (x), per row (y); in the count type: 3x faster
            counts = np.add.reduce(cells, axis=axis, dtype=_count_type(known.shape[axis]))
            local = (np.arange(len(counts)) + 0.5) * res
            mean = float(np.dot(counts, local)) / n
            moments.append((mean, float(np.dot(counts, (local - mean) ** 2)) / n))
        (mx, vx), (my, vy) = moments
        x0, y0, yaw = self.frame.corner_pose
        c, s = np.cos(yaw), np.sin(yaw)
        # the known cells' centroid in the map frame, and their rms distance from it
        centroid = np.array([x0 + c * mx - s * my, y0 + s * mx + c * my])
        spread2 = vx + vy
        # rms distance of the known cells from the map frame's origin: a rotation by d theta moves
        # a typical cell by radius * d theta (at least one cell, for maps of a single cell)
        radius = max(float(np.sqrt(centroid @ centroid + spread2)), res)
        return radius, centroid, max(float(np.sqrt(spread2)), res)

    @property
    def radius(self) -> float:
        """Rms distance of the known cells from the map frame's origin, metres (at least a cell)."""
        return self._moments[0]

    @property
    def centroid(self) -> np.ndarray:
        """(2,) the known cells' centroid in the map frame."""
        return self._moments[1]

    @property
    def spread(self) -> float:
        """Rms distance of the known cells from their centroid, metres (at least a cell)."""
        return self._moments[2]

    @property
    def wall_distance(self):
        """The map's walls and their distance transform, for the verdict (computed once)."""
        if self._wall_distance is None:
            walls = self.walls[:2] if self.blur_kind == "envelope" else None     # wall_points' are p >= 0.5
            if self._squared is not None:
                known = self._code if self._code is not None else self.frame.known           # nonzero: known
                self._wall_distance = WallDistance(self.frame, walls=walls, squared=self._squared, known=known)
            else:
                self._wall_distance = WallDistance(self.grid, self._wall_distances, walls)
            self._wall_distances = None                                           # taken over
        return self._wall_distance

    def wall_array(self, unknown_cost):
        """The walls as the envelope kernel reads them (``_envelope.points_array``), made once per
        ``unknown_cost``."""
        key = float(unknown_cost)
        if key not in self._wall_arrays:
            self._wall_arrays[key] = points_array(*self.walls, key)
        return self._wall_arrays[key]

    def coarser(self):
        """The next level of the pyramid: the map with cells twice as large, blurred ``blur_growth``
        times wider (cached); for the "envelope" blur reduced so that a one-cell wall stays a wall
        while a lone occupied cell fades (``_pyramid.coarsen``, reduce "line")."""
        if self._coarser is None:
            reduce = "line" if self.blur_kind == "envelope" else "mean"
            if self._code is not None:
                frame = self.frame
                blocks, table = halve_code(self._code, reduce)
                coarse = _from_code(blocks, frame.resolution * 2, frame.corner_pose, table)
            else:
                coarse = coarsen(self.grid, reduce=reduce)
            self._coarser = PreparedMap(coarse, self.blur_width * self.blur_growth, self.blur_kind, self.blur_growth)
        return self._coarser

    def share_coarser(self, older: "PreparedMap"):
        """Take the pyramid above this level from ``older``, an earlier version of the same map
        prepared with the same blur and resolution (a submap before its latest scan): only this
        level is then prepared. The coarse levels only bring the optimiser into the basin; the
        finest decides the pose."""
        same = (older.resolution, older.blur_width, older.blur_kind, older.blur_growth, older._code is None)
        if same != (self.resolution, self.blur_width, self.blur_kind, self.blur_growth, self._code is None):
            raise InvalidOptionError("the coarse levels must come from a map prepared with the same blur, evidence "
                                     "and resolution")
        if self._coarser is None and self._ready == 0:
            self._coarser = older.coarser()

    def ready(self, levels: int):
        """Make now what a match through ``levels`` pyramid levels reads of this map in either
        role: the levels (their conflict grids and walls) and the verdict's wall distances (each
        once). What only B's role reads (the rows of known cells, their moments) is made when
        first read: a mapping loop's target, always A, never needs it (measured on the front
        end's matches, 2026-12-06: edmonton 9.5 -> 8.6 ms, seattle 7.0 -> 6.4, the same bits)."""
        if levels > self._ready:
            _ = self.wall_distance
            for k in range(levels):
                self.level(k)
            self._ready = levels

    def level(self, k):
        """Level ``k`` of the pyramid (0: this map)."""
        prepared = self
        for _ in range(k):
            prepared = prepared.coarser()
        return prepared

    def __repr__(self):
        return f"PreparedMap({self.frame!r}, blur {self.blur_kind} {self.blur_width} m)"


def _count_type(n: int):
    """The smallest unsigned integer type that counts to ``n``."""
    return np.uint16 if n < 2**16 else np.uint32 if n < 2**32 else np.uint64
