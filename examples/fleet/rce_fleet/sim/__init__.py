"""Sans-I/O fleet simulator core (DESIGN section 6: simulated robots).

Plain classes advanced by the caller with ``dt`` (s): no sockets, no asyncio,
no wall clock, so the caller chooses real time or any speed-up.

- :class:`SimWorld` (world.py): pymunk space with the map's walls merged into
  rectangles (walls.py), box obstacles and robots.
- :class:`SimRobot` (robot.py): TurtleBot3-burger-like differential drive
  with lidar (lidar.py), odometry (odometry.py) and an AMCL stand-in
  (localisation.py).
- :class:`LocalNavigator` (local_nav.py): the robot's own local planner
  (dynamic window approach) with obstacle stop / avoidance.
- :class:`ObstacleDetector` (obstacles.py): lidar hits not explained by the
  static map, for marking blocked cells.
"""

from .local_nav import LocalNavigator, NavParams
from .lidar import Lidar, LidarParams, scan_to_points
from .localisation import LocalisationModel, LocalisationParams, wrap_angle
from .obstacles import ObstacleDetector, detected_obstacles
from .odometry import Odometry, OdometryNoise
from .robot import RobotParams, SimRobot
from .walls import PixelRect, blocked_mask, merge_rectangles, rect_to_world
from .world import SimWorld

__all__ = [
    "Lidar", "LidarParams", "LocalNavigator", "NavParams", "ObstacleDetector", "LocalisationModel",
    "LocalisationParams", "Odometry", "OdometryNoise", "PixelRect", "RobotParams", "SimRobot",
    "SimWorld", "blocked_mask", "detected_obstacles", "merge_rectangles", "rect_to_world",
    "scan_to_points", "wrap_angle",
]
