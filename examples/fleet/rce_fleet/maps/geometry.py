"""The grid as the fleet's nodes see it: cell numbers <-> world metres, free cells and
connections, in plain Python (no numpy/scipy import, so a move_client starts fast).

The fleet manager cuts the map into a :class:`rce_fleet.maps.grid.CellGrid` once and hands
it to the container's nodes as the parameter ``/fleet/grid`` (:meth:`GridGeometry.to_param`);
the global planner and every move_client rebuild the same geometry from it
(:meth:`GridGeometry.from_param`). So the nodes never read the map file: a sandboxed
container needs no access to the manager's files, and every node uses one grid.

Conventions are those of :mod:`rce_fleet.maps.grid` and :mod:`rce_fleet.maps.occupancy`: cells are
numbered ``r * cols + c``, row 0 at the TOP of the map image; continuous pixel
coordinates ``(row_f, col_f)`` grow down and right; the map origin ``(x, y, yaw)`` is the
lower-left corner of the image (map_server).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

__all__ = ["GridGeometry", "GRID_PARAM", "ROBOTS_PARAM", "components", "quaternion_from_yaw", "quaternion_yaw",
           "yaw_from_quaternion"]

#: Container parameter holding the grid (a dict, see :meth:`GridGeometry.to_param`).
GRID_PARAM = "/fleet/grid"
#: Container parameter listing the robot IDs the global planner serves.
ROBOTS_PARAM = "/fleet/robots"


def quaternion_from_yaw(yaw: float) -> dict:
    """``geometry_msgs/Quaternion`` (JSON form) of a rotation by ``yaw`` rad about z."""
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2.0), "w": math.cos(yaw / 2.0)}


def yaw_from_quaternion(quaternion: Any) -> float:
    """Yaw (rad) of a quaternion given as an object with x, y, z, w attributes or a dict."""
    if isinstance(quaternion, dict):
        x, y, z, w = (float(quaternion.get(k, 0.0)) for k in ("x", "y", "z", "w"))
    else:
        x, y, z, w = float(quaternion.x), float(quaternion.y), float(quaternion.z), float(quaternion.w)
    return quaternion_yaw(x, y, z, w)


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rad) of the quaternion ``(x, y, z, w)`` (its rotation about z, ZYX Euler angles)."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def components(grid: Any) -> list[set[int]]:
    """Connected sets of free cells, largest first (equal sizes: in the order of their smallest
    cell). ``grid``: a :class:`GridGeometry` or :class:`rce_fleet.maps.grid.CellGrid` (anything with
    ``free_cells()`` and ``neighbours(cell)``)."""
    seen: set[int] = set()
    comps = []
    for c in grid.free_cells():
        if c in seen:
            continue
        comp, todo = {c}, [c]
        seen.add(c)
        while todo:
            for v in grid.neighbours(todo.pop()):
                if v not in seen:
                    seen.add(v)
                    comp.add(v)
                    todo.append(v)
        comps.append(comp)
    return sorted(comps, key=len, reverse=True)


def pixel_f_to_world(origin: tuple[float, float, float], resolution: float, height_px: float,
                     row_f: float, col_f: float) -> tuple[float, float]:
    """Continuous pixel coordinates of a map_server image (row 0 at the top) -> world (x, y) in m.

    ``origin`` is the (x, y, yaw) of the lower-left pixel corner (m, m, rad), ``resolution``
    m/pixel, ``height_px`` the image height in pixels (map_server YAML convention)."""
    ox, oy, yaw = origin
    u = col_f * resolution
    v = (height_px - row_f) * resolution
    if yaw:
        cs, sn = math.cos(yaw), math.sin(yaw)
        u, v = cs * u - sn * v, sn * u + cs * v
    return ox + u, oy + v


@dataclass(frozen=True, eq=False)
class GridGeometry:
    """Cell geometry and connectivity of the planner's grid.

    rows, cols: grid size. cell_w_m, cell_h_m: cell size (m). resolution: map m/pixel.
    origin: map origin (x, y, yaw). map_height_px: map image height (pixels).
    row0_px, col0_px: top-left corner of cell 0 in continuous pixel coordinates.
    free: ``rows * cols`` bools. east: for each cell, can a robot drive to the cell to its
    east; south: to the cell below it (both False at the grid border and for non-free cells).
    """

    rows: int
    cols: int
    cell_w_m: float
    cell_h_m: float
    resolution: float
    origin: tuple[float, float, float]
    map_height_px: int
    row0_px: float
    col0_px: float
    free: tuple[bool, ...]
    east: tuple[bool, ...]
    south: tuple[bool, ...]

    # -- construction --------------------------------------------------------
    @classmethod
    def from_cellgrid(cls, grid) -> "GridGeometry":
        """From a :class:`rce_fleet.maps.grid.CellGrid`."""
        n = grid.rows * grid.cols
        free = tuple(bool(v) for v in grid.free.ravel())
        east, south = [False] * n, [False] * n
        for cell in range(n):
            for nb in grid.neighbours(cell):
                if nb == cell + 1:
                    east[cell] = True
                elif nb == cell + grid.cols:
                    south[cell] = True
        m = grid.map
        return cls(rows=grid.rows, cols=grid.cols, cell_w_m=float(grid.cell_w_m), cell_h_m=float(grid.cell_h_m),
                   resolution=float(m.resolution), origin=tuple(float(v) for v in m.origin),
                   map_height_px=int(m.height), row0_px=float(grid.row0_px), col0_px=float(grid.col0_px),
                   free=free, east=tuple(east), south=tuple(south))

    def to_param(self) -> dict:
        """JSON-ready dict for the ``/fleet/grid`` parameter (bit strings for the masks)."""
        bits = lambda values: "".join("1" if b else "0" for b in values)  # noqa: E731
        return {"rows": self.rows, "cols": self.cols, "cell_w_m": self.cell_w_m, "cell_h_m": self.cell_h_m,
                "resolution": self.resolution, "origin": list(self.origin), "map_height_px": self.map_height_px,
                "row0_px": self.row0_px, "col0_px": self.col0_px, "free": bits(self.free),
                "east": bits(self.east), "south": bits(self.south)}

    @classmethod
    def from_param(cls, param: dict) -> "GridGeometry":
        """Inverse of :meth:`to_param`. Raises ValueError naming the bad key."""
        try:
            rows, cols = int(param["rows"]), int(param["cols"])
            n = rows * cols
            masks = {}
            for k in ("free", "east", "south"):
                s = str(param[k])
                if len(s) != n or set(s) - {"0", "1"}:
                    raise ValueError(f"'{k}' must be {n} characters 0/1")
                masks[k] = tuple(ch == "1" for ch in s)
            origin = tuple(float(v) for v in param["origin"])
            if len(origin) != 3:
                raise ValueError("'origin' must be [x, y, yaw]")
            return cls(rows=rows, cols=cols, cell_w_m=float(param["cell_w_m"]), cell_h_m=float(param["cell_h_m"]),
                       resolution=float(param["resolution"]), origin=origin, map_height_px=int(param["map_height_px"]),
                       row0_px=float(param["row0_px"]), col0_px=float(param["col0_px"]), **masks)
        except KeyError as e:
            raise ValueError(f"grid parameter: missing key {e.args[0]!r}") from None
        except (TypeError, ValueError) as e:
            raise ValueError(f"grid parameter: {e}") from None

    # -- numbering -----------------------------------------------------------
    @property
    def n_cells(self) -> int:
        """rows * cols."""
        return self.rows * self.cols

    @property
    def cell_size_m(self) -> float:
        """The smaller cell side (m)."""
        return min(self.cell_w_m, self.cell_h_m)

    def rc(self, cell: int) -> tuple[int, int]:
        """Cell number -> (row, col)."""
        return divmod(int(cell), self.cols)

    def valid(self, cell: int) -> bool:
        """True when ``cell`` is a cell number of the grid (free or not)."""
        return 0 <= cell < self.n_cells

    def is_free(self, cell: int) -> bool:
        """True when ``cell`` is inside the grid and free."""
        return 0 <= cell < self.n_cells and self.free[cell]

    def free_cells(self) -> list[int]:
        """Numbers of all free cells, ascending."""
        return [i for i, f in enumerate(self.free) if f]

    def neighbours(self, cell: int) -> list[int]:
        """Cells a robot can drive to from ``cell`` (north, west, east, south), as CellGrid.neighbours."""
        if not self.is_free(cell):
            return []
        out = []
        if cell >= self.cols and self.south[cell - self.cols]:
            out.append(cell - self.cols)
        if cell % self.cols and self.east[cell - 1]:
            out.append(cell - 1)
        if self.east[cell]:
            out.append(cell + 1)
        if self.south[cell]:
            out.append(cell + self.cols)
        return out

    # -- metric --------------------------------------------------------------
    def _pixel_f_to_world(self, row_f: float, col_f: float) -> tuple[float, float]:
        return pixel_f_to_world(self.origin, self.resolution, self.map_height_px, row_f, col_f)

    def _world_to_cell_f(self, x: float, y: float) -> tuple[float, float]:
        """World point -> continuous (row, col) in cell units (cell (r, c) covers [r, r+1) x [c, c+1))."""
        ox, oy, yaw = self.origin
        dx, dy = x - ox, y - oy
        if yaw:
            cs, sn = math.cos(yaw), math.sin(yaw)
            dx, dy = cs * dx + sn * dy, -sn * dx + cs * dy
        row_f = self.map_height_px - dy / self.resolution
        col_f = dx / self.resolution
        return ((row_f - self.row0_px) * self.resolution / self.cell_h_m,
                (col_f - self.col0_px) * self.resolution / self.cell_w_m)

    def center(self, cell: int) -> tuple[float, float]:
        """World (x, y) of the centre of ``cell`` (m)."""
        r, c = self.rc(cell)
        return self._pixel_f_to_world(self.row0_px + (r + 0.5) * self.cell_h_m / self.resolution,
                                      self.col0_px + (c + 0.5) * self.cell_w_m / self.resolution)

    def cell_of(self, x: float, y: float) -> int | None:
        """Number of the cell containing world point (x, y), or None outside the grid."""
        rf, cf = self._world_to_cell_f(x, y)
        r, c = math.floor(rf), math.floor(cf)
        if 0 <= r < self.rows and 0 <= c < self.cols:
            return r * self.cols + c
        return None

    def depth_in_cell(self, x: float, y: float, cell: int) -> float:
        """How far (m) the point lies inside ``cell``: distance to the cell's nearest border
        (negative outside it)."""
        rf, cf = self._world_to_cell_f(x, y)
        r, c = self.rc(cell)
        dr = min(rf - r, r + 1 - rf) * self.cell_h_m
        dc = min(cf - c, c + 1 - cf) * self.cell_w_m
        return min(dr, dc)

    def grid_corner(self) -> tuple[float, float]:
        """World (x, y) of the grid's top-left corner (the top-left corner of cell 0)."""
        return self._pixel_f_to_world(self.row0_px, self.col0_px)

    def path_length(self, cells: list[int]) -> float:
        """Metres along the centres of ``cells``."""
        total = 0.0
        for a, b in zip(cells, cells[1:], strict=False):
            (ax, ay), (bx, by) = self.center(a), self.center(b)
            total += math.hypot(bx - ax, by - ay)
        return total
