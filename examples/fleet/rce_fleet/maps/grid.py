"""Cut an :class:`~rce_fleet.maps.occupancy.OccupancyMap` into the global planner's grid of cells.

The seed paper (section IV-A, "Global Planner") divides the map into an
equispaced 8x8 grid and runs Dijkstra on it. Cells are numbered row-major from
0, row 0 at the TOP of the image, column 0 at the left (docs/design.md, section 6.1).

Which part of the image is cut: by default (``crop=True``) the bounding box of
the map's *known* pixels (not -1). A SLAM map such as ``turtlebot3_world`` is a
small explored area in a large unknown canvas; cutting the whole canvas 8x8
would put the arena in two or three cells.

When a cell is free (documented rule, all three must hold):

1. **Free area**: at least ``free_fraction`` of the cell's area is free pixels
   (area outside the image counts as not free).
2. **The robot fits at the centre**: the cell centre (the goal the robot is sent
   to) has clearance >= ``robot_radius + margin`` from every obstacle pixel
   (and unknown pixel, when ``unknown_is_occupied``). Clearance is the
   Euclidean distance transform of free space (``scipy.ndimage``) minus half a
   pixel diagonal, so it never over-estimates the distance to a pixel's edge.
3. The cell itself is at least ``2 * (robot_radius + margin)`` on each side
   (otherwise :func:`make_grid` raises), so two robots at the centres of
   adjacent cells never touch.

Two adjacent free cells are connected (:meth:`CellGrid.neighbours`) only when
the straight segment between their centres keeps that clearance all along,
so a thin wall along a cell border, which rule 1 alone would miss, cuts the
connection.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .occupancy import OccupancyMap

__all__ = ["CellGrid", "make_grid", "fleet_grid", "DEFAULT_ROWS_COLS", "ROBOT_RADIUS", "ROBOT_MARGIN"]

DEFAULT_ROWS_COLS = (8, 8)
#: TurtleBot3 burger footprint radius (m).
ROBOT_RADIUS = 0.105
#: Extra clearance (m) on top of the robot radius: localisation error and control slack.
ROBOT_MARGIN = 0.05
#: Without a grid or cell size the fleet cuts a map 8x8, unless that gives cells larger than
#: this (m) ...
LARGE_CELL_M = 2.0
#: ... then square cells of this side (m).
DEFAULT_LARGE_MAP_CELL_M = 1.2


@dataclass(frozen=True, eq=False)
class CellGrid:
    """The planner's grid of cells over a map.

    rows, cols: grid size; cells are numbered ``r * cols + c`` (row 0 at the top).
    cell_w_m, cell_h_m: cell width (along image columns) and height, metres.
    free: (rows, cols) bool, cells a robot may occupy (see module docstring).
    map: the OccupancyMap the grid was cut from.
    row0_px, col0_px: top-left corner of cell 0 in the map's continuous pixel
        coordinates (see :meth:`OccupancyMap.world_to_pixel_f`).
    free_fraction: (rows, cols) float in [0, 1], free share of each cell's area.
    clearance: (rows, cols) float, metres from each cell centre to the nearest obstacle.
    open_east: (rows, cols - 1) bool, robot can drive between (r, c) and (r, c + 1).
    open_south: (rows - 1, cols) bool, robot can drive between (r, c) and (r + 1, c).
        When ``open_east``/``open_south`` are None every pair of free neighbours is connected.
    """

    rows: int
    cols: int
    cell_w_m: float
    cell_h_m: float
    free: np.ndarray
    map: OccupancyMap
    row0_px: float = 0.0
    col0_px: float = 0.0
    free_fraction: np.ndarray | None = field(default=None, repr=False)
    clearance: np.ndarray | None = field(default=None, repr=False)
    open_east: np.ndarray | None = field(default=None, repr=False)
    open_south: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        free = np.asarray(self.free, dtype=bool)
        if free.shape != (self.rows, self.cols):
            raise ValueError(f"free has shape {free.shape}, expected ({self.rows}, {self.cols})")
        free.setflags(write=False)
        object.__setattr__(self, "free", free)

    # -- numbering --------------------------------------------------------
    @property
    def n_cells(self) -> int:
        """Number of cells, rows * cols."""
        return self.rows * self.cols

    def rc(self, cell: int) -> tuple[int, int]:
        """Cell number -> (row, col). Raises IndexError for a number outside the grid."""
        if not 0 <= cell < self.n_cells:
            raise IndexError(f"cell {cell} outside the {self.rows}x{self.cols} grid")
        return divmod(int(cell), self.cols)

    def cell(self, row: int, col: int) -> int:
        """(row, col) -> cell number. Raises IndexError outside the grid."""
        if not (0 <= row < self.rows and 0 <= col < self.cols):
            raise IndexError(f"(row {row}, col {col}) outside the {self.rows}x{self.cols} grid")
        return int(row) * self.cols + int(col)

    def is_free(self, cell: int) -> bool:
        """True when ``cell`` is a free cell."""
        r, c = self.rc(cell)
        return bool(self.free[r, c])

    def free_cells(self) -> list[int]:
        """Numbers of all free cells, ascending."""
        return [int(i) for i in np.flatnonzero(self.free.ravel())]

    # -- geometry ---------------------------------------------------------
    @property
    def cell_h_px(self) -> float:
        """Cell height in image pixels (may be fractional)."""
        return self.cell_h_m / self.map.resolution

    @property
    def cell_w_px(self) -> float:
        """Cell width in image pixels (may be fractional)."""
        return self.cell_w_m / self.map.resolution

    def cell_of(self, x: float, y: float) -> int | None:
        """World point (m) -> number of the cell containing it, or None outside the grid."""
        rf, cf = self.map.world_to_pixel_f(x, y)
        r = math.floor((rf - self.row0_px) / self.cell_h_px)
        c = math.floor((cf - self.col0_px) / self.cell_w_px)
        if 0 <= r < self.rows and 0 <= c < self.cols:
            return r * self.cols + c
        return None

    def center(self, cell: int) -> tuple[float, float]:
        """World (x, y) in metres of the centre of ``cell``."""
        r, c = self.rc(cell)
        return self.map.pixel_f_to_world(self.row0_px + (r + 0.5) * self.cell_h_px,
                                         self.col0_px + (c + 0.5) * self.cell_w_px)

    # -- connectivity -----------------------------------------------------
    def connected(self, cell_a: int, cell_b: int) -> bool:
        """True when a robot can drive between adjacent free cells ``cell_a`` and ``cell_b``."""
        ra, ca = self.rc(cell_a)
        rb, cb = self.rc(cell_b)
        if abs(ra - rb) + abs(ca - cb) != 1 or not (self.free[ra, ca] and self.free[rb, cb]):
            return False
        if ra == rb:
            return True if self.open_east is None else bool(self.open_east[ra, min(ca, cb)])
        return True if self.open_south is None else bool(self.open_south[min(ra, rb), ca])

    def neighbours(self, cell: int) -> list[int]:
        """4-connected free neighbours of ``cell`` a robot can drive to (north, west, east, south).

        Empty for a cell that is not free.
        """
        r, c = self.rc(cell)
        if not self.free[r, c]:
            return []
        out = []
        if r > 0 and self.free[r - 1, c] and (self.open_south is None or self.open_south[r - 1, c]):
            out.append(cell - self.cols)
        if c > 0 and self.free[r, c - 1] and (self.open_east is None or self.open_east[r, c - 1]):
            out.append(cell - 1)
        if c + 1 < self.cols and self.free[r, c + 1] and (self.open_east is None or self.open_east[r, c]):
            out.append(cell + 1)
        if r + 1 < self.rows and self.free[r + 1, c] and (self.open_south is None or self.open_south[r, c]):
            out.append(cell + self.cols)
        return out

    def ascii(self) -> str:
        """The grid as text: cell numbers of free cells, ``##`` for occupied ones."""
        w = len(str(self.n_cells - 1))
        lines = []
        for r in range(self.rows):
            lines.append(" ".join(str(r * self.cols + c).rjust(w) if self.free[r, c] else "#" * w
                                  for c in range(self.cols)))
        return "\n".join(lines)


def _clearance_px(blocked: np.ndarray, pad_blocked: bool) -> np.ndarray:
    """Distance (pixels) from each pixel centre to the nearest blocked pixel's edge (conservative)."""
    arr = np.pad(blocked, 1, constant_values=pad_blocked)
    if not arr.any():
        return np.full(blocked.shape, np.inf)
    d = ndimage.distance_transform_edt(~arr)[1:-1, 1:-1]
    return np.where(d > 0, d - math.sqrt(0.5), -1.0)


@dataclass(frozen=True)
class _Cut:
    """Where the grid lies on the image: top-left corner of cell 0 (continuous pixel
    coordinates), cells per side and cell size in pixels."""
    r0: float
    c0: float
    rows: int
    cols: int
    cell_h_px: float
    cell_w_px: float


def _cut(occupancy: OccupancyMap, rows_cols: tuple[int, int] | None, cell_m: float | None, crop: bool) -> _Cut:
    """The grid's placement for :func:`make_grid`'s ``rows_cols``/``cell_m``/``crop``; raises ValueError."""
    r0, c0, r1, c1 = occupancy.known_bounds() if crop else (0, 0, occupancy.height, occupancy.width)
    area_h, area_w = r1 - r0, c1 - c0
    if cell_m is not None:
        if not cell_m > 0:
            raise ValueError(f"cell_m must be > 0, got {cell_m!r}")
        cell_h_px = cell_w_px = cell_m / occupancy.resolution
        rows = max(1, math.ceil(area_h / cell_h_px - 1e-9))
        cols = max(1, math.ceil(area_w / cell_w_px - 1e-9))
    else:
        rows, cols = rows_cols if rows_cols is not None else DEFAULT_ROWS_COLS
        if int(rows) != rows or int(cols) != cols or rows < 1 or cols < 1:
            raise ValueError(f"rows_cols must be two positive integers, got {rows_cols!r}")
        rows, cols = int(rows), int(cols)
        cell_h_px, cell_w_px = area_h / rows, area_w / cols
    return _Cut(r0, c0, rows, cols, cell_h_px, cell_w_px)


def _free_fractions(occupancy: OccupancyMap, free_px: np.ndarray, cut: _Cut) -> np.ndarray:
    """(rows, cols) free share of each cell's area: every pixel belongs to the cell holding
    its centre; area outside the image is not free."""
    rows, cols = cut.rows, cut.cols
    span_r = np.arange(math.floor(cut.r0), math.ceil(cut.r0 + rows * cut.cell_h_px))
    span_c = np.arange(math.floor(cut.c0), math.ceil(cut.c0 + cols * cut.cell_w_px))
    ri = np.floor((span_r + 0.5 - cut.r0) / cut.cell_h_px).astype(np.int64)
    ci = np.floor((span_c + 0.5 - cut.c0) / cut.cell_w_px).astype(np.int64)
    keep_r, keep_c = (ri >= 0) & (ri < rows), (ci >= 0) & (ci < cols)
    span_r, ri, span_c, ci = span_r[keep_r], ri[keep_r], span_c[keep_c], ci[keep_c]
    in_r = (span_r >= 0) & (span_r < occupancy.height)
    in_c = (span_c >= 0) & (span_c < occupancy.width)
    sub = np.zeros((span_r.size, span_c.size), dtype=bool)
    sub[np.ix_(in_r, in_c)] = free_px[np.ix_(span_r[in_r], span_c[in_c])]
    ids = (ri[:, None] * cols + ci[None, :]).ravel()
    total = np.bincount(ids, minlength=rows * cols).astype(np.float64)
    nfree = np.bincount(ids, weights=sub.ravel().astype(np.float64), minlength=rows * cols)
    return (nfree / np.maximum(total, 1.0)).reshape(rows, cols)


def _clearance_at(clear_m: np.ndarray, rf: np.ndarray, cf: np.ndarray) -> np.ndarray:
    """Clearance (m) at continuous pixel coordinates; -inf outside the image."""
    ri, ci = np.floor(rf).astype(np.int64), np.floor(cf).astype(np.int64)
    ok = (ri >= 0) & (ri < clear_m.shape[0]) & (ci >= 0) & (ci < clear_m.shape[1])
    out = np.full(rf.shape, -np.inf)
    out[ok] = clear_m[ri[ok], ci[ok]]
    return out


def _segment_min(clear_m: np.ndarray, rf0: np.ndarray, cf0: np.ndarray, rf1: np.ndarray, cf1: np.ndarray,
                 length_px: float) -> np.ndarray:
    """Smallest clearance (m) along the segments from (rf0, cf0) to (rf1, cf1), sampled every half pixel."""
    n = max(2, int(math.ceil(length_px * 2)) + 1)
    t = np.linspace(0.0, 1.0, n)
    rf = rf0[..., None] + (rf1 - rf0)[..., None] * t
    cf = cf0[..., None] + (cf1 - cf0)[..., None] * t
    return _clearance_at(clear_m, rf, cf).min(axis=-1)


def make_grid(occupancy: OccupancyMap, rows_cols: tuple[int, int] | None = None, cell_m: float | None = None,
              free_fraction: float = 0.8, robot_radius: float = ROBOT_RADIUS,
              unknown_is_occupied: bool = True, *, margin: float = ROBOT_MARGIN,
              crop: bool = True) -> CellGrid:
    """Cut ``occupancy`` into a grid of cells and decide which are free.

    Args:
        m: the map.
        rows_cols: (rows, cols): that many equal cells over the cut area (paper: 8x8).
        cell_m: square cells of this side (m) instead; the grid covers the cut area
            from its top-left corner, the last row/column may stick out of it.
            Default when neither is given: ``rows_cols = (8, 8)``.
        free_fraction: minimum free share of a cell's area (0..1].
        robot_radius, margin: the robot needs ``robot_radius + margin`` metres of
            clearance around a cell centre, and between connected centres.
        unknown_is_occupied: treat unknown (-1) pixels as obstacles.
        crop: cut the bounding box of known pixels (True) or the whole image.
    Returns:
        The CellGrid (free cells, clearances and connections included).
    Raises:
        ValueError: both or invalid ``rows_cols``/``cell_m``, ``free_fraction``
            outside (0, 1], or cells smaller than the robot's footprint.
    """
    if rows_cols is not None and cell_m is not None:
        raise ValueError("give rows_cols or cell_m, not both")
    if not 0.0 < free_fraction <= 1.0:
        raise ValueError(f"free_fraction must be in (0, 1], got {free_fraction!r}")
    if robot_radius < 0 or margin < 0:
        raise ValueError("robot_radius and margin must be >= 0")
    res = occupancy.resolution
    g = _cut(occupancy, rows_cols, cell_m, crop)
    rows, cols, cell_h_px, cell_w_px = g.rows, g.cols, g.cell_h_px, g.cell_w_px
    need = robot_radius + margin
    if min(cell_h_px, cell_w_px) * res < 2 * need - 1e-9:
        raise ValueError(f"cells of {cell_w_px * res:.3f} x {cell_h_px * res:.3f} m are smaller than the "
                         f"robot footprint (2 x {need:.3f} m); use fewer rows/cols or a larger cell_m")

    free_px = occupancy.free_mask(unknown_is_occupied)
    clear_m = _clearance_px(~free_px, pad_blocked=unknown_is_occupied) * res
    # 1. free fraction; 2. clearance at cell centres (points outside the image have none)
    frac = _free_fractions(occupancy, free_px, g)
    cr = g.r0 + (np.arange(rows) + 0.5) * cell_h_px
    cc = g.c0 + (np.arange(cols) + 0.5) * cell_w_px
    centre_clear = _clearance_at(clear_m, np.repeat(cr[:, None], cols, 1), np.repeat(cc[None, :], rows, 0))
    free = (frac >= free_fraction - 1e-12) & (centre_clear >= need)
    # 3. connections: clearance along the segment between neighbouring centres.
    R, C = np.meshgrid(cr, cc, indexing="ij")
    open_east = _segment_min(clear_m, R[:, :-1], C[:, :-1], R[:, 1:], C[:, 1:], cell_w_px) >= need
    open_south = _segment_min(clear_m, R[:-1, :], C[:-1, :], R[1:, :], C[1:, :], cell_h_px) >= need
    return CellGrid(rows=rows, cols=cols, cell_w_m=cell_w_px * res, cell_h_m=cell_h_px * res,
                    free=free, map=occupancy, row0_px=float(g.r0), col0_px=float(g.c0), free_fraction=frac,
                    clearance=centre_clear, open_east=open_east, open_south=open_south)


def fleet_grid(occupancy: OccupancyMap, rows_cols: tuple[int, int] | None = None,
               cell_m: float | None = None) -> tuple[CellGrid, str]:
    """The grid the fleet (``rce-fleet demo``, ``serve``, ``grid``) cuts ``occupancy`` into, and a
    note saying why when it is not the one asked for ('' otherwise).

    ``rows_cols`` or ``cell_m`` as :func:`make_grid`; with neither, the paper's 8x8, unless its
    cells would be over :data:`LARGE_CELL_M` on a side (a warehouse): then square cells of
    :data:`DEFAULT_LARGE_MAP_CELL_M`. Raises ValueError (from :func:`make_grid`) for cells
    smaller than a robot or a grid with no free cell."""
    if rows_cols or cell_m:
        return make_grid(occupancy, rows_cols, cell_m), ""
    grid = make_grid(occupancy)
    if max(grid.cell_w_m, grid.cell_h_m) <= LARGE_CELL_M:
        return grid, ""
    grid = make_grid(occupancy, cell_m=DEFAULT_LARGE_MAP_CELL_M)
    return grid, (f"grid: {grid.rows}x{grid.cols} cells of {DEFAULT_LARGE_MAP_CELL_M} m (8x8 would give cells "
                  f"over {LARGE_CELL_M:g} m on this map; pass --grid or --cell to choose)")
