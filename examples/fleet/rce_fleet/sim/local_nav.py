"""The robot's own local navigation: drive to a goal pose, avoid what the lidar sees.

Plays the part of move_base's local planner on each simulated robot.  It is a
Dynamic Window Approach (Fox, Burgard, Thrun, "The Dynamic Window Approach to
Collision Avoidance", IEEE RAM 1997): sample (v, w) pairs, roll each out as a
circular arc over ``horizon`` seconds, drop those whose arc comes closer than
``safety_margin`` to any lidar hit (the robot is a disc, so turning in place is
always safe), and score the rest by heading to the goal, progress toward it,
clearance and speed, plus a small smoothness term.  The samples span the
whole velocity range (0..max_linear x -max_angular..max_angular, capped near
the goal); the robot's own acceleration limits (2.5 m/s^2, 3.2 rad/s^2) then
smooth the command, since at a 10 Hz control rate the dynamic window already
covers nearly all of it.

Plain DWA stalls in front of an obstacle lying across the straight line to the
goal (heading and progress both favour creeping at it).  So the arcs are
scored against a sub-goal: the goal itself while the corridor to it (robot
width plus margin) is free, otherwise a point ``lookahead`` metres out along
the free corridor closest in angle to the goal direction, a one-step version
of the Vector Field Histogram's valley choice (Borenstein and Koren 1991), with
hysteresis and a preference for passing on the right.  Because an arc that would
hit anything within the horizon is never chosen, the robot creeps ever slower
toward an obstacle in its way and stops short of it; it never drives into a
wall, box or robot that its lidar sees.

States: ``idle`` (no goal), ``driving``, ``reached`` (within ``xy_tolerance``
and, if a goal yaw was given, ``yaw_tolerance``), ``blocked`` (no progress of
``progress_epsilon`` for ``blocked_after`` seconds; the navigator keeps trying
and goes back to ``driving`` when it progresses again, so whoever sent the
goal decides whether to cancel).

Sans-I/O: the caller passes ``dt`` and the latest scan and pose estimate.
"""

from __future__ import annotations

import math
from typing import Iterable

import numpy as np

from .clearance import arc_clearance, closest_approach, corridor_free, robot_frame
from .lidar import LidarParams, scan_to_points
from .localisation import wrap_angle
from .nav_params import NavParams
from .obstacles import ObstacleDetector, detected_obstacles as _detected


class LocalNavigator:
    """Per-robot local planner (DWA, see module doc).

    Use: ``set_goal(x, y, yaw=None)``; then every control period
    ``v, w = nav.update(pose, dt, scan)`` and send ``(v, w)`` to the robot's
    ``cmd_vel``.  ``pose`` is the pose estimate (x m, y m, yaw rad), e.g. the
    localisation output; ``scan`` a (n,) lidar scan taken at ``pose`` (omit it
    between scans: the last scan's hits are kept in world coordinates and
    re-projected, so control can run faster than the lidar).
    """

    def __init__(self, params: NavParams | None = None, *,
                 lidar_params: LidarParams | None = None,
                 obstacle_detector: ObstacleDetector | None = None) -> None:
        self.params = p = params or NavParams()
        self.lidar_params = lidar_params or LidarParams()
        self.obstacle_detector = obstacle_detector
        self.goal: tuple[float, float, float | None] | None = None
        self.state = "idle"
        self._points = np.zeros((0, 2))  # last scan's hits, world frame
        self._last_cmd = (0.0, 0.0)
        self._best_dist = math.inf
        self._stall_time = 0.0
        self._at_position = False
        self._detour: float | None = None  # world angle of the current detour
        # Sample grid and arc time stamps (fixed, precomputed).
        v = np.linspace(0.0, 1.0, p.v_samples)
        w = np.linspace(-1.0, 1.0, p.w_samples)
        self._vs, self._ws = (a.ravel() for a in np.meshgrid(v, w, indexing="ij"))
        k = max(1, int(round(p.horizon / p.sim_dt)))
        self._t = np.arange(1, k + 1) * (p.horizon / k)
        self._arc_cache: tuple[float, tuple[np.ndarray, ...]] | None = None

    # -- goals ---------------------------------------------------------------
    def set_goal(self, x: float, y: float, yaw: float | None = None) -> None:
        """Drive to (x m, y m) and, if ``yaw`` (rad) is given, turn to it."""
        self.goal = (float(x), float(y), None if yaw is None else float(yaw))
        self.state = "driving"
        self._best_dist = math.inf
        self._stall_time = 0.0
        self._at_position = False
        self._detour = None

    def cancel(self) -> None:
        """Drop the goal and stop (state ``idle``)."""
        self.goal = None
        self.state = "idle"
        self._last_cmd = (0.0, 0.0)

    # -- sensing ---------------------------------------------------------------
    def set_scan(self, scan: np.ndarray, pose: tuple[float, float, float]) -> None:
        """Store a scan's hits (world frame) taken at ``pose`` (x, y, yaw)."""
        self._points = scan_to_points(scan, pose, self.lidar_params,
                                      include_too_close=True)

    def detected_obstacles(self, scan: np.ndarray, pose: tuple[float, float, float],
                           exclude: Iterable[tuple[float, float, float]] = ()
                           ) -> list[tuple[float, float]]:
        """Lidar hits (x m, y m) in world coordinates not explained by the
        static map (when the navigator has an ``obstacle_detector``; all hits
        otherwise), minus hits inside ``exclude`` discs (x, y, r)."""
        return _detected(scan, pose, self.obstacle_detector, exclude)

    # -- control -------------------------------------------------------------
    def update(self, pose: tuple[float, float, float], dt: float,
               scan: np.ndarray | None = None) -> tuple[float, float]:
        """One control step: returns (v m/s, w rad/s) for ``cmd_vel``."""
        if scan is not None:
            self.set_scan(scan, pose)
        if self.goal is None or self.state in ("idle", "reached"):
            self._last_cmd = (0.0, 0.0)
            return 0.0, 0.0
        p = self.params
        x, y, yaw = (float(c) for c in pose)
        gx, gy, gyaw = self.goal
        dist = math.hypot(gx - x, gy - y)

        # Position reached (with hysteresis): only the final turn remains.
        if dist < p.xy_tolerance:
            self._at_position = True
        elif dist > 2.0 * p.xy_tolerance:
            self._at_position = False
        if self._at_position:
            if gyaw is None:
                return self._finish()
            err = wrap_angle(gyaw - yaw)
            if abs(err) < p.yaw_tolerance:
                return self._finish()
            w = max(-p.max_angular, min(p.max_angular, 2.0 * err))
            if abs(w) < 0.3:
                w = math.copysign(0.3, err)
            self._progress(dist, dt, moving=True)
            self._last_cmd = (0.0, w)
            return 0.0, w

        v, w = self._dwa(x, y, yaw, gx, gy, dist)
        self._progress(dist, dt, moving=False)
        self._last_cmd = (v, w)
        return v, w

    def _finish(self) -> tuple[float, float]:
        self.state = "reached"
        self._last_cmd = (0.0, 0.0)
        return 0.0, 0.0

    def _progress(self, dist: float, dt: float, moving: bool) -> None:
        # ``moving``: the final turn in place, which is progress by itself.
        p = self.params
        if moving or dist < self._best_dist - p.progress_epsilon:
            if not moving:
                self._best_dist = dist
            self._stall_time = 0.0
            self.state = "driving"
            return
        self._stall_time += max(0.0, dt)
        if self._stall_time >= p.blocked_after:
            self.state = "blocked"

    def _dwa(self, x: float, y: float, yaw: float, gx: float, gy: float,
             dist: float) -> tuple[float, float]:
        p = self.params
        c, s = math.cos(yaw), math.sin(yaw)
        # Goal and obstacles in the robot frame.
        dxg, dyg = gx - x, gy - y
        goal_r = (c * dxg + s * dyg, -s * dxg + c * dyg)
        reach = max(p.max_linear * p.horizon + p.radius + p.clearance_cap,
                    p.lookahead + p.radius + p.safety_margin + 0.1)
        local, nearest = robot_frame(self._points, x, y, yaw, reach)

        target, dist_t = self._subgoal(local, goal_r, dist, yaw)
        v_cap = min(p.max_linear, max(p.min_approach_speed, p.slowdown_gain * dist))
        vs, ws, wt, ax, ay = self._arcs(v_cap)

        if len(local):
            d_now = nearest - p.radius
            # clearances from clearance_cap on all score alike: look no further
            clearance = arc_clearance(ax, ay, local, p.radius + p.clearance_cap) - p.radius
            # Admissible: keeps the margin, or (if already inside it) gets no closer.
            floor = min(p.safety_margin, d_now - 1e-3)
            ok = (clearance >= floor) | (vs == 0.0)
        else:
            clearance = np.full(len(vs), np.inf)
            ok = np.ones(len(vs), dtype=bool)

        ex, ey, eth = ax[:, -1], ay[:, -1], wt[:, -1]
        tx, ty = target
        # Closest approach along the arc counts, so arcs that pass the target
        # are not punished for where they would be after it.
        along = closest_approach(ax, ay, tx, ty)
        progress = (dist_t - along) / (p.max_linear * p.horizon)
        bearing = np.arctan2(ty - ey, tx - ex) - eth
        heading_err = np.abs(np.arctan2(np.sin(bearing), np.cos(bearing)))
        heading = 1.0 - heading_err / math.pi
        clear_score = np.minimum(clearance, p.clearance_cap) / p.clearance_cap
        vel_score = vs / p.max_linear
        smooth = np.abs(ws - self._last_cmd[1]) / (2.0 * p.max_angular)
        # Tie-break: prefer turning right (pass others on the right).
        right = 0.01 * (ws < 0)
        score = (p.w_heading * heading + p.w_progress * progress
                 + p.w_clearance * clear_score + p.w_velocity * vel_score
                 - p.w_smooth * smooth + right)
        score = np.where(ok, score, -np.inf)
        i = int(np.argmax(score))
        if not np.isfinite(score[i]):
            return 0.0, 0.0
        v, w = float(vs[i]), float(ws[i])
        if v < 1e-3:
            v = 0.0
        return v, w

    def _arcs(self, v_cap: float) -> tuple[np.ndarray, ...]:
        """The sampled (v, w) and their arcs rolled out from the origin, for speeds up to
        ``v_cap`` m/s: vs, ws (N,), wt, ax, ay (N, K) (kept for the last ``v_cap``: the robots
        drive at the full speed cap except near their goals)."""
        if self._arc_cache is not None and self._arc_cache[0] == v_cap:
            return self._arc_cache[1]
        vs = self._vs * v_cap
        ws = self._ws * self.params.max_angular
        t = self._t
        wt = np.outer(ws, t)
        straight = np.abs(ws) < 1e-6
        safe_w = np.where(straight, 1.0, ws)
        ax = np.where(straight[:, None], np.outer(vs, t),
                      (vs / safe_w)[:, None] * np.sin(wt))
        ay = np.where(straight[:, None], 0.0,
                      (vs / safe_w)[:, None] * (1.0 - np.cos(wt)))
        self._arc_cache = (v_cap, (vs, ws, wt, ax, ay))
        return vs, ws, wt, ax, ay

    def _free_distance(self, local: np.ndarray, angles: np.ndarray) -> np.ndarray:
        """Free length, m, of a straight corridor of half-width radius +
        safety_margin from the robot along each robot-frame angle (rad)."""
        p = self.params
        free = np.full(len(angles), np.inf)
        if not len(local):
            return free
        return corridor_free(np.cos(angles), np.sin(angles), local, p.radius + p.safety_margin)

    def _subgoal(self, local: np.ndarray, goal_r: tuple[float, float], dist: float,
                 yaw: float) -> tuple[tuple[float, float], float]:
        """Robot-frame point to steer for, and its distance (see module doc)."""
        p = self.params
        goal_dir = math.atan2(goal_r[1], goal_r[0])
        need = min(dist, p.lookahead)
        n = int(p.max_detour // p.detour_step)
        offsets = np.arange(-n, n + 1) * p.detour_step
        free = self._free_distance(local, goal_dir + offsets)
        if free[n] >= need:
            self._detour = None
            return goal_r, dist
        ok = free >= need
        if not ok.any():
            self._detour = None
            return goal_r, dist
        cost = np.abs(offsets) - 1e-3 * (offsets < 0)  # ties: pass on the right
        if self._detour is not None:
            world = yaw + goal_dir + offsets
            cost = cost + 0.5 * np.abs(np.arctan2(np.sin(world - self._detour),
                                                  np.cos(world - self._detour)))
        i = int(np.argmin(np.where(ok, cost, np.inf)))
        ang = goal_dir + float(offsets[i])
        self._detour = yaw + ang
        return (p.lookahead * math.cos(ang), p.lookahead * math.sin(ang)), p.lookahead
