"""A stand-in for AMCL: ground truth plus small, bounded, slowly varying error.

Running a particle filter per simulated robot would cost far more than the
rest of the simulator.  The fleet only needs what ``amcl`` publishes on
``amcl_pose`` (``geometry_msgs/PoseWithCovarianceStamped``): a pose estimate
that is close to the truth, wanders a little (AMCL's error is correlated in
time, not white), never diverges, and comes with a covariance.  So the error
on x, y and yaw is an Ornstein-Uhlenbeck process (time constant ``tau``)
clipped to ``+-bound_sigmas`` standard deviations, and the published
covariance is the process's stationary variance on the diagonal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .noise import NormalBlock


@dataclass(frozen=True)
class LocalisationParams:
    """sigma_xy: stationary standard deviation of the x and y error, m;
    sigma_yaw: of the yaw error, rad; tau: correlation time, s;
    bound_sigmas: the error is clipped to this many standard deviations."""

    sigma_xy: float = 0.02
    sigma_yaw: float = 0.02
    tau: float = 2.0
    bound_sigmas: float = 3.0


def wrap_angle(angle: float) -> float:
    """Wrap an angle to [-pi, pi), rad."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class LocalisationModel:
    """Per-robot AMCL stand-in.  Call :meth:`step` every physics step, then
    :meth:`estimate` with the ground-truth pose.  ``error``: the current
    (x m, y m, yaw rad) error."""

    def __init__(self, rng: np.random.Generator,
                 params: LocalisationParams | None = None) -> None:
        self.params = p = params or LocalisationParams()
        self.rng = rng
        self._normals = NormalBlock(rng, 3)
        self._sigma = (p.sigma_xy, p.sigma_xy, p.sigma_yaw)
        self._bound = tuple(p.bound_sigmas * s for s in self._sigma)
        self._decay: tuple[float, float, float] | None = None   # (dt, k, sqrt(1 - k^2))
        # Start from the stationary distribution (like amcl after convergence).
        self.error = self._clip(tuple(n * s for n, s in zip(self._normals.next(), self._sigma, strict=True)))

    def _clip(self, error) -> tuple[float, float, float]:
        (e0, e1, e2), (b0, b1, b2) = error, self._bound
        return min(max(e0, -b0), b0), min(max(e1, -b1), b1), min(max(e2, -b2), b2)

    def step(self, dt: float) -> None:
        """Advance the error process by ``dt`` seconds (exact OU discretisation)."""
        if dt <= 0:
            return
        if self._decay is None or self._decay[0] != dt:
            k = math.exp(-dt / self.params.tau)
            self._decay = (dt, k, math.sqrt(1.0 - k * k))
        _, k, f = self._decay
        (n0, n1, n2), (e0, e1, e2), (s0, s1, s2) = self._normals.next(), self.error, self._sigma
        self.error = self._clip((e0 * k + n0 * s0 * f, e1 * k + n1 * s1 * f, e2 * k + n2 * s2 * f))

    def covariance(self) -> list[float]:
        """6x6 row-major covariance over (x, y, z, roll, pitch, yaw), 36 floats
        (m^2, rad^2), as in ``PoseWithCovariance.covariance``."""
        cov = [0.0] * 36
        cov[0] = self.params.sigma_xy ** 2
        cov[7] = self.params.sigma_xy ** 2
        cov[35] = self.params.sigma_yaw ** 2
        return cov

    def estimate(self, x: float, y: float, yaw: float
                 ) -> tuple[float, float, float, list[float]]:
        """``(x m, y m, yaw rad, covariance)`` for the true pose (x, y, yaw)."""
        ex, ey, eyaw = self.error
        return x + ex, y + ey, wrap_angle(yaw + eyaw), self.covariance()
