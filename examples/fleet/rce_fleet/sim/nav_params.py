"""The local planner's parameters (:class:`rce_fleet.sim.local_nav.LocalNavigator`), apart from the
planner, so that a node that only reads them (a move_client's robot speed) imports no simulator."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class NavParams:
    """Local planner parameters (SI units: m, s, rad).

    radius: robot radius, m; max_linear m/s; max_angular rad/s (the planner's,
    below the robot's 2.84); xy_tolerance m, yaw_tolerance rad;
    safety_margin: minimum gap kept between the robot's edge and any lidar
    hit along a chosen arc, m; horizon: arc length in time, s; sim_dt: arc
    sampling step, s; v_samples x w_samples: velocity samples;
    slowdown_gain: near the goal the speed is capped at gain * distance, 1/s;
    lookahead: length of the free corridor a detour direction needs, m;
    max_detour: largest detour angle off the goal direction, rad;
    detour_step: angular step of the detour search, rad;
    min_approach_speed m/s; clearance_cap: clearances beyond this score
    alike, m; blocked_after s, progress_epsilon m: see module doc;
    weights: heading, progress, clearance, velocity, smoothness.
    """

    radius: float = 0.105
    max_linear: float = 0.22
    max_angular: float = 1.5
    xy_tolerance: float = 0.08
    yaw_tolerance: float = 0.1
    safety_margin: float = 0.05
    horizon: float = 1.5
    sim_dt: float = 0.1
    v_samples: int = 8
    w_samples: int = 21
    slowdown_gain: float = 0.8
    min_approach_speed: float = 0.05
    clearance_cap: float = 0.4
    lookahead: float = 0.8
    max_detour: float = 1.75
    detour_step: float = 0.0873
    blocked_after: float = 3.0
    progress_epsilon: float = 0.05
    w_heading: float = 1.0
    w_progress: float = 2.0
    w_clearance: float = 0.4
    w_velocity: float = 0.2
    w_smooth: float = 0.05
