"""A simulated TurtleBot3-burger-like differential-drive robot in a pymunk space.

The robot is a dynamic circle body (radius 0.105 m, 1 kg) driven kinematically:
every physics step its velocity is SET (in the body's pymunk ``velocity_func``,
i.e. just before the contact solver) to the acceleration-limited command,
``(v cos yaw, v sin yaw)`` and angular velocity ``w``.  Because the body stays
dynamic, the contact solver still stops it at walls, boxes and other robots:
it can push but never pass through.  Its moment of inertia is infinite so
contacts cannot spin it; its heading changes only by the commanded ``w``.

Limits follow the ROBOTIS TurtleBot3 burger: 0.22 m/s, 2.84 rad/s, and the
``acc_lim_x`` 2.5 m/s^2 / ``acc_lim_theta`` 3.2 rad/s^2 of its navigation
package's local planner parameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pymunk

from .lidar import Lidar, LidarParams, RayCast
from .localisation import LocalisationModel, LocalisationParams, wrap_angle
from .odometry import Odometry, OdometryNoise


@dataclass(frozen=True)
class RobotParams:
    """radius m; max_linear m/s; max_angular rad/s; max_linear_accel m/s^2;
    max_angular_accel rad/s^2; mass kg."""

    radius: float = 0.105
    max_linear: float = 0.22
    max_angular: float = 2.84
    max_linear_accel: float = 2.5
    max_angular_accel: float = 3.2
    mass: float = 1.0


def _approach(current: float, target: float, max_delta: float) -> float:
    if target > current + max_delta:
        return current + max_delta
    if target < current - max_delta:
        return current - max_delta
    return target


class SimRobot:
    """One simulated robot.  Create through :meth:`SimWorld.add_robot`.

    Sensors: :meth:`scan` (lidar), :meth:`odom` (wheel odometry),
    :meth:`localisation` (AMCL stand-in); actuator: :meth:`cmd_vel`.
    """

    def __init__(self, robot_id: str, space: pymunk.Space, x: float, y: float,
                 yaw: float, *, group: int, rng: np.random.Generator,
                 params: RobotParams | None = None,
                 lidar_params: LidarParams | None = None,
                 odometry_noise: OdometryNoise | None = None,
                 localisation_params: LocalisationParams | None = None,
                 ray_caster: RayCast | None = None) -> None:
        self.robot_id = robot_id
        self.params = p = params or RobotParams()
        self.space = space
        self.body = pymunk.Body(p.mass, math.inf)
        self.body.position = (float(x), float(y))
        self.body.angle = float(yaw)
        self.body._rce_vel = (0.0, 0.0)  # type: ignore[attr-defined]
        self.body.velocity_func = SimRobot._velocity_func
        self.shape = pymunk.Circle(self.body, p.radius)
        self.shape.friction = 0.0
        self.shape.elasticity = 0.0
        self.shape.filter = pymunk.ShapeFilter(group=group)
        self.shape.robot_id = robot_id  # type: ignore[attr-defined]
        space.add(self.body, self.shape)
        rngs = rng.spawn(3)
        self.lidar = Lidar(space, lidar_params, rngs[0], caster=ray_caster)
        self._odom = Odometry(x, y, yaw, rngs[1], odometry_noise)
        self._loc = LocalisationModel(rngs[2], localisation_params)
        self._cmd = (0.0, 0.0)  # target (v, w)
        self._vel = (0.0, 0.0)  # current, acceleration-limited (v, w)
        self._prev = (float(x), float(y), float(yaw))

    # -- actuation -----------------------------------------------------------
    def cmd_vel(self, linear: float, angular: float) -> None:
        """Command ``linear`` m/s and ``angular`` rad/s (clipped to the
        limits; reached under the acceleration limits), like ``cmd_vel``
        (``geometry_msgs/Twist``)."""
        p = self.params
        linear = 0.0 if not math.isfinite(linear) else max(-p.max_linear, min(p.max_linear, float(linear)))
        angular = 0.0 if not math.isfinite(angular) else max(-p.max_angular, min(p.max_angular, float(angular)))
        self._cmd = (linear, angular)

    @property
    def command(self) -> tuple[float, float]:
        """The last commanded (v m/s, w rad/s) after clipping."""
        return self._cmd

    def _pre_step(self, dt: float) -> None:
        # ``_prev``, the pose before the step, is the pose the last step left (only
        # Space.step moves a body)
        if self._vel != self._cmd:
            p = self.params
            v = _approach(self._vel[0], self._cmd[0], p.max_linear_accel * dt)
            w = _approach(self._vel[1], self._cmd[1], p.max_angular_accel * dt)
            self._vel = (v, w)
            self.body._rce_vel = self._vel  # type: ignore[attr-defined]

    @staticmethod
    def _velocity_func(body: pymunk.Body, gravity, damping, dt) -> None:
        # Called by pymunk inside Space.step AFTER positions were integrated
        # with the previous, contact-solved velocity and BEFORE the contact
        # solver runs: the command becomes the velocity the solver then
        # constrains, so a robot pushing into a wall never sinks into it.
        v, w = body._rce_vel  # type: ignore[attr-defined]
        yaw = body.angle
        body.velocity = (v * math.cos(yaw), v * math.sin(yaw))
        body.angular_velocity = w

    def _post_step(self, dt: float) -> tuple[float, float]:
        """Odometry and localisation after a physics step; returns the position (x, y), m."""
        x0, y0, yaw0 = self._prev
        x, y = self.body.position
        yaw1 = self.body.angle
        self._prev = (x, y, yaw1)
        dyaw = yaw1 - yaw0
        mid = yaw0 + 0.5 * dyaw
        ds = (x - x0) * math.cos(mid) + (y - y0) * math.sin(mid)
        self._odom.update(ds, dyaw, dt)
        self._loc.step(dt)
        return x, y

    # -- state and sensors -------------------------------------------------
    def pose(self) -> tuple[float, float, float]:
        """Ground-truth (x m, y m, yaw rad in [-pi, pi))."""
        pos = self.body.position
        return pos.x, pos.y, wrap_angle(self.body.angle)

    def velocity(self) -> tuple[float, float]:
        """Ground-truth (forward speed m/s, yaw rate rad/s) of the body."""
        yaw = self.body.angle
        vel = self.body.velocity
        return vel.x * math.cos(yaw) + vel.y * math.sin(yaw), self.body.angular_velocity

    def odom(self) -> tuple[float, float, float, float, float]:
        """Wheel odometry ``(x m, y m, yaw rad, v m/s, w rad/s)``; see
        :mod:`.odometry`."""
        return self._odom.as_tuple()

    def scan(self) -> np.ndarray:
        """One lidar revolution from the robot centre: (360,) float32 ranges,
        m, beam 0 ahead, counter-clockwise; see :mod:`.lidar`."""
        x, y, yaw = self.pose()
        return self.lidar.scan(x, y, yaw, self.shape.filter)

    def localisation(self) -> tuple[float, float, float, list[float]]:
        """AMCL stand-in ``(x m, y m, yaw rad, covariance)``; covariance is the
        6x6 row-major list of 36 floats of ``PoseWithCovariance``."""
        return self._loc.estimate(*self.pose())
