"""Sans-I/O fleet simulator core (docs/design.md, section 6.3: simulated robots).

Plain classes advanced by the caller with ``dt`` (s): no sockets, no asyncio,
no wall clock, so the caller chooses real time or any speed-up.

- :class:`SimWorld` (world.py): pymunk space with the map's walls merged into
  rectangles (walls.py), box obstacles and robots.
- :class:`SimRobot` (robot.py): TurtleBot3-burger-like differential drive
  with lidar (lidar.py), odometry (odometry.py) and an AMCL stand-in
  (localisation.py).
- :class:`LocalNavigator` (local_nav.py): the robot's own local planner
  (dynamic window approach) with obstacle stop / avoidance; its parameters
  :class:`NavParams` (nav_params.py).
- :class:`ObstacleDetector` (obstacles.py): lidar hits not explained by the
  static map, for marking blocked cells.
"""

from __future__ import annotations

import importlib

#: each public name -> the module that defines it; a module is imported on the first use of one of its
#: names, so that importing one part (:mod:`.nav_params`, a node's) does not load the others (numba, scipy, pymunk)
_WHERE = {
    "LocalNavigator": "local_nav", "NavParams": "nav_params",
    "Lidar": "lidar", "LidarParams": "lidar", "scan_to_points": "lidar",
    "LocalisationModel": "localisation", "LocalisationParams": "localisation", "wrap_angle": "localisation",
    "ObstacleDetector": "obstacles", "detected_obstacles": "obstacles",
    "Odometry": "odometry", "OdometryNoise": "odometry",
    "RobotParams": "robot", "SimRobot": "robot",
    "PixelRect": "walls", "blocked_mask": "walls", "merge_rectangles": "walls", "rect_to_world": "walls",
    "SimWorld": "world",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    """``rce_fleet.sim.SimWorld`` (...): the name from its module, imported then."""
    if name in _WHERE:
        return getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
