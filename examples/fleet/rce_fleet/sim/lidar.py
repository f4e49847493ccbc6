"""Simulated 2-D lidar (TurtleBot3 LDS-01-like) by ray casting in the pymunk space.

Each beam finds what ``pymunk.Space.segment_query_first`` from the sensor centre
finds, so walls, boxes and other robots are all seen exactly as the physics has
them.  A robot's lidar casts through its world's compiled ray caster
(:meth:`.world.SimWorld.cast_rays`, :mod:`.raycast`: a 360-beam scan on the
warehouse map in about 0.1 ms, where a chipmunk segment query per beam took
1.2 ms); ``fast=False``, or a lidar without a caster, queries pymunk's public
API beam by beam.

Scan layout follows ``sensor_msgs/LaserScan`` as the LDS-01 driver fills it:
``angle_min = 0``, ``angle_increment = 2*pi/n_beams`` (counter-clockwise,
beam 0 straight ahead), ``angle_max = 2*pi - angle_increment``.  Out-of-range
values follow REP 117: ``+inf`` means no return within ``range_max``,
``-inf`` means an object closer than ``range_min``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pymunk

#: The shape filter that excludes nothing (a lidar on no robot).
ALL_SHAPES = pymunk.ShapeFilter()

#: A world's ray caster: ``(x, y, end_x, end_y, range_max, group) -> ranges`` (m; (n,) float64
#: ends, inf where nothing is hit; robots of shape filter ``group`` left out, 0: none), as
#: :meth:`.world.SimWorld.cast_rays`.
RayCast = Callable[[float, float, np.ndarray, np.ndarray, float, int], np.ndarray]


@dataclass(frozen=True)
class LidarParams:
    """Lidar model parameters (defaults: ROBOTIS LDS-01 on a TurtleBot3 burger).

    n_beams: beams per revolution; range_min / range_max: m;
    noise_std: standard deviation of the additive Gaussian range noise, m
    (the LDS-01 datasheet gives +-15 mm accuracy below 0.5 m);
    rate_hz: nominal scan rate, Hz (the caller decides when to call scan()).
    """

    n_beams: int = 360
    range_min: float = 0.12
    range_max: float = 3.5
    noise_std: float = 0.01
    rate_hz: float = 5.0

    @property
    def angle_min(self) -> float:
        """Angle of beam 0 relative to the robot heading, rad."""
        return 0.0

    @property
    def angle_increment(self) -> float:
        """Angle between consecutive beams, rad (counter-clockwise)."""
        return 2.0 * math.pi / self.n_beams

    @property
    def angle_max(self) -> float:
        """Angle of the last beam, rad."""
        return self.angle_min + (self.n_beams - 1) * self.angle_increment

    def beam_angles(self) -> np.ndarray:
        """(n_beams,) float64 beam angles in the robot frame, rad (read-only, shared)."""
        return _beam_angles(self)


@functools.lru_cache(maxsize=16)
def _beam_angles(p: LidarParams) -> np.ndarray:
    a = p.angle_min + np.arange(p.n_beams) * p.angle_increment
    a.flags.writeable = False
    return a


class Lidar:
    """Ray-casting lidar over a pymunk space.

    ``scan(x, y, yaw, shape_filter)`` returns ``(n_beams,)`` float32 ranges in
    metres for a sensor at world pose (x m, y m, yaw rad); ``shape_filter``
    excludes the sensor's own robot (same non-zero pymunk group).  ``caster``:
    the world's ray caster (:data:`RayCast`), used while ``fast`` is True.
    """

    def __init__(self, space: pymunk.Space, params: LidarParams | None = None,
                 rng: np.random.Generator | None = None, caster: RayCast | None = None) -> None:
        self.space = space
        self.params = params or LidarParams()
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.caster = caster
        self.fast = True
        a = self.params.beam_angles()
        self._cos = np.cos(a)
        self._sin = np.sin(a)

    def true_ranges(self, x: float, y: float, yaw: float,
                    shape_filter: pymunk.ShapeFilter = ALL_SHAPES) -> np.ndarray:
        """Noise-free distances to the first hit per beam, m; ``inf`` if none
        within ``range_max``.  (n_beams,) float64."""
        p = self.params
        c, s = math.cos(yaw), math.sin(yaw)
        # Rotate the unit beam directions by yaw.
        dx = (self._cos * c - self._sin * s) * p.range_max
        dy = (self._sin * c + self._cos * s) * p.range_max
        if self.fast and self.caster is not None:
            return self.caster(x, y, dx + x, dy + y, p.range_max, shape_filter.group)
        start = (x, y)
        out = np.full(p.n_beams, np.inf)
        rmax = p.range_max
        ends = zip((dx + x).tolist(), (dy + y).tolist(), strict=True)
        query = self.space.segment_query_first
        for i, end in enumerate(ends):
            hit = query(start, end, 0.0, shape_filter)
            if hit is not None:
                out[i] = hit.alpha * rmax
        return out

    def scan(self, x: float, y: float, yaw: float,
             shape_filter: pymunk.ShapeFilter = ALL_SHAPES) -> np.ndarray:
        """A noisy scan: (n_beams,) float32 ranges, m, with REP 117 +-inf."""
        p = self.params
        r = self.true_ranges(x, y, yaw, shape_filter)
        hit = np.isfinite(r)
        if p.noise_std > 0:
            r[hit] += self.rng.normal(0.0, p.noise_std, int(hit.sum()))
        r[hit & (r > p.range_max)] = np.inf
        r[hit & (r < p.range_min)] = -np.inf
        return r.astype(np.float32)


def scan_to_points(ranges: np.ndarray, pose: tuple[float, float, float],
                   params: LidarParams | None = None,
                   *, include_too_close: bool = True) -> np.ndarray:
    """Convert a scan to world-frame hit points, (K, 2) float64 metres.

    ``pose`` is the sensor's (x m, y m, yaw rad).  ``+inf``/NaN beams are
    dropped; ``-inf`` beams (closer than range_min) are placed at range_min
    when ``include_too_close``, else dropped.
    """
    p = params or LidarParams()
    r = np.asarray(ranges, dtype=np.float64).copy()
    if len(r) != p.n_beams:
        p = LidarParams(n_beams=len(r), range_min=p.range_min,
                        range_max=p.range_max, noise_std=p.noise_std)
    if include_too_close:
        r[np.isneginf(r)] = p.range_min
    ok = np.isfinite(r)
    a = p.beam_angles()[ok] + pose[2]
    rr = r[ok]
    return np.column_stack((pose[0] + rr * np.cos(a), pose[1] + rr * np.sin(a)))
