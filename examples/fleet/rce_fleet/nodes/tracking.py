"""Sans-I/O helpers of the fleet's cloud nodes: which cell a robot is in (with hysteresis at
cell borders), and which cells the robots' lidars show as blocked.

Both are plain classes fed with poses, points and times by the node that owns them
(the global planner), so they are tested without sockets or clocks.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

from ..maps.geometry import GridGeometry
from ..sim.nav_params import NavParams

__all__ = ["CellTracker", "ObstacleFilter"]


class CellTracker:
    """The cell a robot is in, from its pose estimates.

    A pose near a cell border jitters between two cells (localisation noise). The tracker
    changes cell only when the pose lies at least ``margin`` metres inside the new cell, so
    one crossing gives one report. Default margin: 10 % of the smaller cell side, at most 0.1 m.
    A pose outside the grid keeps the last cell.
    """

    def __init__(self, geometry: GridGeometry, margin: float | None = None):
        self.geo = geometry
        self.margin = min(0.1, 0.1 * geometry.cell_size_m) if margin is None else float(margin)
        self.cell: int | None = None

    def update(self, x: float, y: float) -> int | None:
        """Feed a pose; returns the (possibly unchanged) current cell, None before the first
        pose inside the grid."""
        if not (math.isfinite(x) and math.isfinite(y)):
            return self.cell
        c = self.geo.cell_of(x, y)
        if c is None or c == self.cell:
            return self.cell
        if self.cell is None or self.geo.depth_in_cell(x, y, c) >= self.margin:
            self.cell = c
        return self.cell


class ObstacleFilter:
    """Cells to block from lidar points that the static map does not explain.

    A robot reports the world points of its scan that are not near a wall of the map
    (``/RobotN/obstacles``). Points are ignored when they are

    * farther than ``max_range`` m from the reporting robot (a small heading error moves
      far points a lot),
    * within ``robot_clearance`` m of any robot's last pose (robots see each other), plus
      ``robot_speed`` m/s times the age of that pose at the scan (a robot seen in the scan
      has moved on from a pose that arrived late, by at most its top speed times the lag),
    * in a cell that is not free on the static map, in a blocked cell, or within
      ``edge_margin`` m of a blocked cell (the edges of the box that blocks it); a cell the
      operator unblocked counts as blocked here for ``clear_hold_s`` s (see below),
    * in a cell a robot is in.

    A cell with at least ``min_points`` remaining points in one report is *sighted*; it is
    returned for blocking once it was sighted in ``confirm`` reports within ``window_s``
    seconds (a single noisy scan never blocks a cell).

    A cell the operator unblocked (:meth:`clear`) is not sighted for ``clear_hold_s`` seconds:
    scans taken before the obstacle went (still in flight, or from a world that has not yet
    heard of the unblock) must not block it again. An obstacle still there after that is
    sighted as usual.
    """

    def __init__(self, geometry: GridGeometry, *, min_points: int = 3, confirm: int = 2, window_s: float = 5.0,
                 max_range: float = 2.0, robot_clearance: float = 0.3, edge_margin: float = 0.15,
                 robot_speed: float = NavParams.max_linear, clear_hold_s: float = 2.0):
        self.geo = geometry
        self.min_points, self.confirm, self.window_s = int(min_points), int(confirm), float(window_s)
        self.max_range, self.robot_clearance = float(max_range), float(robot_clearance)
        self.robot_speed = float(robot_speed)
        self.edge_margin = float(edge_margin)
        self.clear_hold_s = float(clear_hold_s)
        self.sightings: dict[int, list[float]] = {}
        self.cleared: dict[int, float] = {}       # cell -> when the operator unblocked it, s (within clear_hold_s)

    def clear(self, cell: int, now: float) -> None:
        """The operator unblocked ``cell`` at ``now`` (s): its sightings are forgotten and, for
        ``clear_hold_s`` s, points in it are not counted."""
        self.sightings.pop(cell, None)
        self.cleared = {c: self.cleared[c] for c in self._held(now)}
        self.cleared[cell] = now

    def _held(self, now: float) -> set[int]:
        """The cells unblocked less than ``clear_hold_s`` s before ``now``."""
        return {c for c, t in self.cleared.items() if now - t < self.clear_hold_s}

    def _near_blocked(self, x: float, y: float, blocked: set[int]) -> bool:
        for b in blocked:
            if self.geo.depth_in_cell(x, y, b) > -self.edge_margin:
                return True
        return False

    def update(self, observer: tuple[float, float] | None, points: Iterable[tuple[float, float]], now: float,
               robot_poses: Mapping[str, tuple[float, float]], robot_cells: Iterable[int],
               blocked: Iterable[int], pose_ages: Mapping[str, float] | None = None) -> list[int]:
        """Feed one report; returns the cells to block now (ascending). ``robot_poses``: robot ->
        its last (x, y), m; ``pose_ages``: robot -> how much older (or newer) that pose is than
        the scan, s (absent: 0)."""
        blocked = set(blocked) | self._held(now)
        occupied = set(robot_cells)
        ages = pose_ages or {}
        poses = [(px, py, (self.robot_clearance + self.robot_speed * abs(ages.get(r, 0.0))) ** 2)
                 for r, (px, py) in robot_poses.items()]
        counts: dict[int, int] = {}
        for x, y in points:
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            if observer is not None and math.hypot(x - observer[0], y - observer[1]) > self.max_range:
                continue
            if any((x - px) ** 2 + (y - py) ** 2 < rc2 for px, py, rc2 in poses):
                continue
            c = self.geo.cell_of(x, y)
            if c is None or not self.geo.is_free(c) or c in blocked or c in occupied:
                continue
            if blocked and self._near_blocked(x, y, blocked):
                continue
            counts[c] = counts.get(c, 0) + 1
        out = []
        for c, n in counts.items():
            if n < self.min_points:
                continue
            seen = [t for t in self.sightings.get(c, []) if now - t <= self.window_s] + [now]
            if len(seen) >= self.confirm:
                self.sightings.pop(c, None)
                out.append(c)
            else:
                self.sightings[c] = seen
        return sorted(out)
