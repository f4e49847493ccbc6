"""The simulated world: a pymunk space with the map's walls, boxes and robots.

Sans-I/O: no clock, no sockets; the caller advances it with :meth:`SimWorld.step`
(``dt`` seconds of simulated time) as fast or as slowly as it likes.
"""

from __future__ import annotations

import math
import zlib
from typing import Any

import numpy as np
import pymunk

from .lidar import LidarParams
from .localisation import LocalisationParams
from .odometry import OdometryNoise
from .raycast import RayCaster
from .robot import RobotParams, SimRobot
from .walls import PixelRect, blocked_mask, merge_rectangles, rect_to_world


class SimWorld:
    """Physics world built from an occupancy map (ROS map_server convention).

    ``occupancy_map`` needs ``occupancy`` ((H, W) int8, row 0 = top; 0 free,
    100 occupied, -1 unknown), ``resolution`` (m/pixel) and ``origin``
    ((x, y, yaw) of the lower-left pixel corner, m; yaw must be 0).
    Occupied AND unknown pixels become static walls, merged into rectangles
    (:func:`.walls.merge_rectangles`); four more walls close the map's outer
    border so nothing leaves the image.  ``seed`` makes every noise source
    (lidar, odometry, localisation) reproducible.  ``substep`` is the fixed
    physics step, s.
    """

    def __init__(self, occupancy_map: Any, *, seed: int = 0, substep: float = 0.02,
                 robot_params: RobotParams | None = None,
                 lidar_params: LidarParams | None = None,
                 odometry_noise: OdometryNoise | None = None,
                 localisation_params: LocalisationParams | None = None) -> None:
        if substep <= 0:
            raise ValueError("substep must be > 0")
        self.map = occupancy_map
        self.seed = int(seed)
        self.substep = float(substep)
        self.robot_params = robot_params or RobotParams()
        self.lidar_params = lidar_params or LidarParams()
        self.odometry_noise = odometry_noise
        self.localisation_params = localisation_params
        self.space = pymunk.Space()
        self.space.gravity = (0.0, 0.0)
        self.space.collision_slop = 0.0005  # m; pymunk's default 0.1 suits pixels
        self.space.iterations = 20
        self.robots: dict[str, SimRobot] = {}
        self.boxes: dict[str, pymunk.Shape] = {}
        self._steps = 0
        self._acc = 0.0
        self._next_group = 1
        self._discs: tuple[int, np.ndarray, np.ndarray] | None = None   # (step, discs, groups) for the lidars
        self._box_bbs = np.zeros((0, 4))
        self._xy: tuple[int, list] | None = None      # (step, the robots' positions after it)

        occ = np.asarray(occupancy_map.occupancy)
        self.resolution = float(occupancy_map.resolution)
        origin = tuple(float(v) for v in occupancy_map.origin)
        self.origin = origin
        h, w = occ.shape
        #: Static wall rectangles in pixel coordinates (see :mod:`.walls`).
        self.wall_rects: list[PixelRect] = merge_rectangles(blocked_mask(occ))
        #: World bounds (x0, y0, x1, y1), m, of the map image.
        self.bounds = (origin[0], origin[1], origin[0] + w * self.resolution,
                       origin[1] + h * self.resolution)
        shapes = []
        static = self.space.static_body
        for rect in self.wall_rects:
            shapes.append(pymunk.Poly.create_box_bb(
                static, pymunk.BB(*rect_to_world(rect, h, self.resolution, origin))))
        x0, y0, x1, y1 = self.bounds
        t = 1.0  # border thickness, m, outside the image
        for bb in ((x0 - t, y0 - t, x1 + t, y0), (x0 - t, y1, x1 + t, y1 + t),
                   (x0 - t, y0, x0, y1), (x1, y0, x1 + t, y1)):
            shapes.append(pymunk.Poly.create_box_bb(static, pymunk.BB(*bb)))
        for s in shapes:
            s.friction = 0.0
            s.elasticity = 0.0
        self.space.add(*shapes)
        self._caster = RayCaster(self.wall_rects, (h, w), self.resolution, origin)

    # -- contents ------------------------------------------------------------
    @property
    def time(self) -> float:
        """Simulated time, s (a whole number of substeps)."""
        return self._steps * self.substep

    def add_robot(self, robot_id: str, x: float, y: float, yaw: float = 0.0) -> SimRobot:
        """Spawn a robot at (x m, y m, yaw rad); its noise is seeded from the
        world seed and ``robot_id`` (so it does not depend on spawn order)."""
        if robot_id in self.robots:
            raise ValueError(f"robot {robot_id!r} already exists")
        rng = np.random.default_rng([self.seed, zlib.crc32(str(robot_id).encode())])
        robot = SimRobot(robot_id, self.space, x, y, yaw, group=self._next_group,
                         rng=rng, params=self.robot_params,
                         lidar_params=self.lidar_params,
                         odometry_noise=self.odometry_noise,
                         localisation_params=self.localisation_params,
                         ray_caster=self.cast_rays)
        self._next_group += 1
        self.robots[robot_id] = robot
        self._discs = self._xy = None
        return robot

    def remove_robot(self, robot_id: str) -> None:
        """Take a robot out of the world (KeyError if unknown)."""
        robot = self.robots.pop(robot_id)
        self.space.remove(robot.body, robot.shape)
        self._discs = self._xy = None

    def add_box(self, box_id: str, x: float, y: float, width: float, height: float) -> None:
        """Place a static axis-aligned box obstacle centred at (x, y), ``width`` m
        wide (along x) and ``height`` m tall (along y); replaces a box of the same
        id.  A box dropped onto a robot pushes the robot out of it."""
        if box_id in self.boxes:
            self.remove_box(box_id)
        bb = (x - width / 2.0, y - height / 2.0, x + width / 2.0, y + height / 2.0)
        shape = pymunk.Poly.create_box_bb(self.space.static_body, pymunk.BB(*bb))
        shape.bb_world = bb  # type: ignore[attr-defined]
        shape.friction = 0.0
        shape.elasticity = 0.0
        shape.box_id = box_id  # type: ignore[attr-defined]
        self.space.add(shape)
        self.boxes[box_id] = shape
        self._update_box_bbs()

    def remove_box(self, box_id: str) -> bool:
        """Remove a box; returns False if there was none with that id."""
        shape = self.boxes.pop(box_id, None)
        if shape is None:
            return False
        self.space.remove(shape)
        self._update_box_bbs()
        return True

    def _update_box_bbs(self) -> None:
        self._box_bbs = np.array([s.bb_world for s in self.boxes.values()], dtype=np.float64).reshape(-1, 4)

    # -- time ------------------------------------------------------------------
    def step(self, dt: float) -> int:
        """Advance ``dt`` seconds of simulated time in fixed substeps (the
        remainder carries over to the next call).  Returns substeps taken."""
        if dt < 0:
            raise ValueError("dt must be >= 0")
        self._acc += dt
        n = int(math.floor(self._acc / self.substep + 1e-9))
        self._acc = max(0.0, self._acc - n * self.substep)
        robots = list(self.robots.values())
        h = self.substep
        for _ in range(n):
            for r in robots:
                r._pre_step(h)
            self.space.step(h)
            xy = [r._post_step(h) for r in robots]
            self._steps += 1
            self._xy = (self._steps, xy)
        return n

    def _positions(self) -> np.ndarray:
        """(N, 2) float64: the robots' positions, m, in ``self.robots``' order (as the last step left them)."""
        if self._xy is None or self._xy[0] != self._steps or len(self._xy[1]) != len(self.robots):
            self._xy = (self._steps, [tuple(r.body.position) for r in self.robots.values()])
        return np.array(self._xy[1], dtype=np.float64).reshape(-1, 2)

    # -- observation ---------------------------------------------------------
    def cast_rays(self, x: float, y: float, ex: np.ndarray, ey: np.ndarray, range_max: float,
                  group: int = 0) -> np.ndarray:
        """What ``Space.segment_query_first`` finds on each segment from (x, y) m to (ex[i], ey[i])
        m (each ``range_max`` m long) among the walls, boxes and robots, the robot of shape filter
        ``group`` left out (0: none): (n,) float64 ranges, m, inf where nothing is hit
        (:mod:`.raycast`; the robots where they stood after the last step)."""
        if self._discs is None or self._discs[0] != self._steps:
            rs = list(self.robots.values())
            discs = np.column_stack((self._positions(), [r.shape.radius for r in rs])).reshape(-1, 3)
            groups = np.array([r.shape.filter.group for r in rs], dtype=np.int64)
            self._discs = (self._steps, discs, groups)
        _, discs, groups = self._discs
        return self._caster.cast(x, y, ex, ey, range_max, self._box_bbs, discs, groups, group)

    def min_pair_distance(self) -> float:
        """Smallest centre-to-centre distance between two robots, m (inf with
        fewer than two).  Robots overlap when this is < 2 * radius."""
        if len(self.robots) < 2:
            return math.inf
        p = self._positions()
        d = np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1])
        d[np.diag_indices(len(p))] = np.inf
        return float(d.min())

    def is_free(self, x: float, y: float, radius: float = 0.0) -> bool:
        """True if a disc of ``radius`` m at (x, y) touches no wall, box or robot."""
        if radius <= 0:
            return not self.space.point_query((x, y), 0.0, pymunk.ShapeFilter())
        body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        probe = pymunk.Circle(body, radius)
        body.position = (x, y)
        return not self.space.shape_query(probe)
