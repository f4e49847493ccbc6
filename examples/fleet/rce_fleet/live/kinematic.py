"""The live fleet's control loop without physics and without the engine, sans-I/O: the global
planner core, one move_client core per robot and unicycle robots that turn in place and drive
at the robots' speed, in simulated time.

:class:`KinematicFleet` routes the cores' messages to each other by topic, as the engine
does, with no delay and no loss. Each robot drives to the waypoint its move_client sent: it
turns in place at ``turn_rads`` until it faces the waypoint (within ``FACE_RAD``), then
drives at ``speed_ms``, slowing near the waypoint as the simulated robots' local planner
does (:class:`rce_fleet.sim.local_nav.NavParams`: ``slowdown_gain`` x distance, at least
``min_approach_speed``). Poses go to both cores every ``dt`` (the robots' ``amcl_pose``
rate) and the planner ticks every ``tick_s`` (its 5 Hz over the run's real-time factor).

:func:`run_stream` runs a generated task stream (:class:`rce_fleet.live.task_stream.TaskStream`)
through it: what the live system's planning and dispatch deliver when the robots move as
planned, so a live run's losses split into control (this, against the lifelong planner's
offline prediction) and physics and transport (the live run against this).
"""
from __future__ import annotations

import math
import time
from typing import Any

from ..operations.dispatcher import CHARGING, IDLE, PARKING, TASK, UNKNOWN
from ..maps.geometry import GridGeometry
from ..nodes.global_planner_core import GlobalPlannerCore
from ..nodes.move_client_core import MoveClientCore, plan_id_of
from ..nodes.common import Out
from ..sim.local_nav import NavParams

__all__ = ["KinematicFleet", "run_stream"]

#: What a robot does in a step (:meth:`KinematicFleet.doing`): no task (idle, parked or on
#: its way to parking); turning or driving (to an errand, a waiting spot or a charger); standing
#: because the dependency graph holds it for a robot planned into its next cell before it;
#: standing beside a station another robot is at or nearer to; standing on its task's errand
#: (until the planner's next tick moves the task on); charging; anything else (no path:
#: unreachable or deferred, or a path not yet driven).
TIME_SPLIT = ("no_task", "driving", "held_by_order", "waiting_for_station", "at_errand", "charging", "no_path")
FACE_RAD = 0.3             # rad: a robot drives once it faces its waypoint this closely (turns in place before)
NAV = NavParams()


class KinematicFleet:
    """See the module docstring. ``starts``: robot -> cell; ``speed_ms`` m/s; ``turn_rads``
    rad/s; ``dt``: s per step (pose rate); ``tick_s``: s between planner ticks; other keyword
    arguments go to :class:`~rce_fleet.nodes.global_planner_core.GlobalPlannerCore`."""

    def __init__(self, geo: GridGeometry, starts: dict[str, int], *, speed_ms: float = NAV.max_linear,
                 turn_rads: float = NAV.max_angular, dt: float = 0.2, tick_s: float = 0.5, **core_kw: Any):
        self.geo, self.speed, self.turn, self.dt, self.tick_s = geo, float(speed_ms), float(turn_rads), dt, tick_s
        self.t = 0.0
        self.core = GlobalPlannerCore(geo, list(starts), clock=lambda: self.t, **core_kw)
        self.mc = {r: MoveClientCore(r, geo) for r in starts}
        self.pose = {r: (*geo.center(c), 0.0) for r, c in starts.items()}
        self.waypoint: dict[str, tuple[float, float] | None] = {r: None for r in starts}
        self.distance = {r: 0.0 for r in starts}
        self.drive_s = 0.0                    # robot-seconds spent turning or driving to a waypoint
        self.visited = {r: [c] for r, c in starts.items()}
        self.cancels = {r: 0 for r in starts}
        self.shared_cells = 0                 # steps x cells in which two robots' centres stood (0: safe)
        self.time_split = dict.fromkeys(TIME_SPLIT, 0.0)   # robot-s by what the robots did (:meth:`doing`)
        self._next_tick = 0.0
        for r in starts:
            self.route(self.mc[r].on_pose(*self.pose[r], stamp=0.0))
            self.route(self.core.on_pose(r, *self.pose[r], stamp=0.0))

    def route(self, outs: list[Out]) -> None:
        """Deliver the cores' messages (by topic) to their receivers."""
        for o in outs:
            robot, _, leaf = o.topic.strip("/").partition("/")
            if leaf == "goalNodesList":
                self.route(self.mc[robot].on_path(plan_id_of(o.msg["layout"]["dim"][0]["label"]), o.msg["data"]))
            elif leaf == "clearance":
                self.route(self.mc[robot].on_clearance(o.msg["plan"], o.msg["index"]))
            elif leaf == "cancelGoal":
                self.cancels[robot] += 1
                self.route(self.mc[robot].on_cancel(o.msg["data"]))
            elif leaf == "move_base_simple/goal":
                p = o.msg["pose"]["position"]
                self.waypoint[robot] = (p["x"], p["y"])
            elif leaf == "move_base/cancel":
                self.waypoint[robot] = None

    def _drive(self, r: str) -> None:
        g = self.waypoint[r]
        if g is None:
            return
        x, y, yaw = self.pose[r]
        dx, dy = g[0] - x, g[1] - y
        dist = math.hypot(dx, dy)
        if dist < 1e-3:
            self.waypoint[r] = None
            return
        err = math.remainder(math.atan2(dy, dx) - yaw, math.tau)
        dt = self.dt
        self.drive_s += dt
        if abs(err) > FACE_RAD:
            turn = min(abs(err), self.turn * dt)
            self.pose[r] = (x, y, yaw + math.copysign(turn, err))
            return
        v = min(self.speed, max(NAV.min_approach_speed, NAV.slowdown_gain * dist))
        s = min(dist, v * dt)
        self.pose[r] = (x + dx / dist * s, y + dy / dist * s, math.atan2(dy, dx))
        self.distance[r] += s
        c = self.geo.cell_of(*self.pose[r][:2])
        if c is not None and self.visited[r][-1] != c:
            self.visited[r].append(c)

    def doing(self, r: str) -> str:
        """What robot ``r`` does now, one of :data:`TIME_SPLIT`."""
        fp, w = self.core.fp, self.core.dispatcher.robots[r]
        if w.activity in (IDLE, PARKING, UNKNOWN):
            return "no_task"
        if self.waypoint[r] is not None:
            return "driving"
        if fp.held(r):
            return "held_by_order"
        if w.activity == TASK and w.spot is not None and fp.positions.get(r) == w.spot:
            return "waiting_for_station"
        if w.activity == TASK and w.task is not None and fp.positions.get(r) == w.task.task.goal:
            return "at_errand"
        if w.activity == CHARGING:
            return "charging"
        return "no_path"

    def s_per_cell(self) -> float:
        """Seconds the robots took per cell while they drove (turns and slowing included; inf
        before a robot changed cells)."""
        cells = sum(len(v) - 1 for v in self.visited.values())
        return self.drive_s / cells if cells else math.inf

    def step(self) -> None:
        """One ``dt``: the robots move, report their poses and progress; the planner ticks when due."""
        self.t += self.dt
        for r in self.mc:
            self._drive(r)
            self.route(self.mc[r].on_pose(*self.pose[r], stamp=self.t))
            self.route(self.core.on_pose(r, *self.pose[r], stamp=self.t))
            self.core.on_progress(r, self.mc[r].progress())
            self.time_split[self.doing(r)] += self.dt
        cells = [self.geo.cell_of(*p[:2]) for p in self.pose.values()]
        self.shared_cells += len(cells) - len(set(cells))
        if self.t >= self._next_tick:
            self._next_tick = self.t + self.tick_s
            self.route(self.core.tick())


def run_stream(geo: GridGeometry, places, starts: dict[str, int], stream: list[tuple[float, list[str]]],
               duration_s: float, **kw: Any) -> dict:
    """Run ``stream`` ((s, errands) pairs) for ``duration_s`` simulated s on a
    :class:`KinematicFleet` (keyword arguments go to it; idle robots park). Returns
    ``tasks_done``, ``per_hour``, ``mean_s`` (creation to done), ``refused``, ``distance_m``
    (all robots), ``s_per_cell`` (:meth:`KinematicFleet.s_per_cell`), ``plan_ms`` (mean, max
    per re-plan), ``replans`` and ``stale_replans`` (those for robots held by a stale order),
    ``shared_cells`` (:attr:`KinematicFleet.shared_cells`: steps x cells holding two robots'
    centres, 0 when nobody collided), ``time_split`` (share of the robots' time by
    :data:`TIME_SPLIT`) and ``wall_s``."""
    t0 = time.perf_counter()
    f = KinematicFleet(geo, starts, places=places, park_idle=True, **kw)
    nxt, refused = 0, 0
    while f.t < duration_s:
        while nxt < len(stream) and stream[nxt][0] <= f.t:
            f.route(f.core.on_task({"request": f"g{nxt}", "errands": list(stream[nxt][1]), "source": "stream"}))
            refused += not f.core.book.answers[-1]["ok"]
            nxt += 1
        f.step()
    st = f.core.book.stats()
    times = f.core.plan_times or [0.0]
    return {"tasks_done": st["done"], "per_hour": round(st["done"] * 3600.0 / duration_s, 2),
            "mean_s": round(st["mean_s"], 2), "refused": refused, "failed": st["failed"],
            "distance_m": round(sum(f.distance.values()), 1), "s_per_cell": round(f.s_per_cell(), 3),
            "shared_cells": f.shared_cells,
            "time_split": {k: round(v / max(sum(f.time_split.values()), 1e-9), 4) for k, v in f.time_split.items()},
            "plan_ms": {"mean": round(1e3 * sum(times) / len(times), 2), "max": round(1e3 * max(times), 2)},
            "replans": f.core.replans, "stale_replans": f.core.stale_replans,
            "wall_s": round(time.perf_counter() - t0, 2)}
