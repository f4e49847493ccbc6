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
