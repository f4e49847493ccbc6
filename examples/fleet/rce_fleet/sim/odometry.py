"""Wheel odometry: dead reckoning of the robot's measured motion with seeded noise.

Each physics step the robot reports how far it really moved forward (``ds``,
m, the body displacement projected on its heading: wheels that do not slip
measure exactly that) and how much it turned (``dyaw``, rad).  The odometry
adds zero-mean Gaussian noise whose VARIANCE grows linearly with the motion
(a random walk per metre / radian, after the odometry motion model of Thrun,
Burgard, Fox, *Probabilistic Robotics*, 2005, ch. 5.4), so the drift does not
depend on the step size, and integrates the result with the midpoint rule.

The odometry frame starts at the robot's spawn pose, so ``odom`` equals the
map pose until drift accumulates (the ``map -> odom`` transform starts as
identity).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .localisation import wrap_angle
from .noise import NormalBlock


@dataclass(frozen=True)
class OdometryNoise:
    """Noise variances: ``ds_per_m`` m^2 of distance error per m driven;
    ``yaw_per_rad`` rad^2 of heading error per rad turned; ``yaw_per_m``
    rad^2 of heading error per m driven.  Defaults give ~1 cm and ~0.5 deg
    standard deviation after 1 m."""

    ds_per_m: float = 1e-4
    yaw_per_rad: float = 1e-4
    yaw_per_m: float = 1e-4


class Odometry:
    """Integrated noisy wheel motion: ``(x m, y m, yaw rad, v m/s, w rad/s)``.

    The pose drifts; the velocities are the last step's measured wheel speeds
    (encoder rates are precise, their integral is what drifts)."""

    def __init__(self, x: float, y: float, yaw: float, rng: np.random.Generator,
                 noise: OdometryNoise | None = None) -> None:
        self.noise = noise or OdometryNoise()
        self.rng = rng
        self._normals = NormalBlock(rng, 2)
        self.x, self.y, self.yaw = float(x), float(y), float(yaw)
        self.v = 0.0
        self.w = 0.0
        self.distance = 0.0  # total |ds| integrated, m

    def update(self, ds: float, dyaw: float, dt: float) -> None:
        """Integrate one step: ``ds`` m forward, ``dyaw`` rad, over ``dt`` s."""
        n = self.noise
        if dt > 0:
            self.v = ds / dt
            self.w = dyaw / dt
        var_ds = n.ds_per_m * abs(ds)
        var_yaw = n.yaw_per_rad * abs(dyaw) + n.yaw_per_m * abs(ds)
        if var_ds > 0 or var_yaw > 0:
            e0, e1 = self._normals.next()
            ds = ds + e0 * math.sqrt(var_ds)
            dyaw = dyaw + e1 * math.sqrt(var_yaw)
        mid = self.yaw + 0.5 * dyaw
        self.x += ds * math.cos(mid)
        self.y += ds * math.sin(mid)
        self.yaw = wrap_angle(self.yaw + dyaw)
        self.distance += abs(ds)

    def as_tuple(self) -> tuple[float, float, float, float, float]:
        """``(x, y, yaw, v, w)`` in m, m, rad, m/s, rad/s."""
        return self.x, self.y, self.yaw, self.v, self.w
