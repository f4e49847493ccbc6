"""The global planner node's logic, sans-I/O: robot poses, operator goals and blocks and
lidar obstacles in; cell paths, cancelGoal, execution clearances and the fleet state out.

The node (``packages/fleet/global_planner``) is a thin shell: it subscribes the topics,
feeds each message to :class:`GlobalPlannerCore` and publishes the :class:`Out` items it
returns, in order. Planning itself is :class:`rce_fleet.planning.FleetPlanner`.

Topics (per robot N; docs/design.md, section 6.2, and the seed paper, section III-C):

=============================  ===================================  ==============================
topic                          type                                 meaning
=============================  ===================================  ==============================
``/RobotN/amcl_pose``          geometry_msgs/PoseWithCovarianceStamped  robot pose (in)
``/RobotN/obstacles``          geometry_msgs/PoseArray              lidar points not on the map (in)
``/RobotN/progress``           fleet/MoveProgress                   its move_client's progress (in)
``/fleet/goal``                fleet/RobotGoal                      operator goal (in)
``/fleet/block``               fleet/CellBlock                      operator block/unblock (in)
``/fleet/task``                fleet/Task                           operator task (in)
``/fleet/task_cancel``         fleet/TaskCancel                     operator cancel (in)
``/RobotN/battery``            sensor_msgs/BatteryState             robot battery (in)
``/fleet/tasks``               fleet/TaskList                       tasks, answers, robots' work (out)
``/RobotN/goalNodesList``      std_msgs/Int32MultiArray             the cell path (out)
``/RobotN/cancelGoal``         std_msgs/Bool                        True: drop the old path (out)
``/RobotN/clearance``          fleet/Clearance                      how far it may drive (out)
``/fleet/state``               fleet/FleetState                     everything, ~5 Hz (out)
=============================  ===================================  ==============================

Plans. ``goalNodesList.data`` is the robot's remaining cell path (its current cell first,
consecutive cells distinct); ``layout.dim[0].label`` is ``"plan <id>"``. A ``Clearance``
names the plan it refers to and an index into that list: the robot may drive up to and
into that cell. When the planner re-plans and a robot's remaining cells are unchanged it
keeps its plan id (clearance indices keep counting in the list it already has); a robot
whose cells change gets a new plan id and list. Only robots whose paths crossed a newly
blocked cell get ``cancelGoal`` (True), before their new path, as the paper describes.

Tasks. The operators' tasks (:class:`rce_fleet.operations.tasks_api.TaskBook`) are dispatched at every
tick by :class:`rce_fleet.operations.dispatcher.Dispatcher` (the lifelong allocator, batteries, parking),
whose goals the FleetPlanner drives like operator goals. Fleet time is the robots' clock: the
newest ``amcl_pose`` stamp.
"""
from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..operations.battery import BatteryParams
from ..operations.dispatcher import Dispatcher, RobotView
from ..maps.geometry import GridGeometry, components
from ..lifelong import LifelongGrid
from .common import Out
from ..operations.places import Places
from ..planning import FleetPlanner, GridGraph, PlannerError, compress, compressed_index
from ..planning.prioritized import REPLAN_BOUND_S
from ..operations.tasks_api import TaskBook
from .tracking import CellTracker, ObstacleFilter

__all__ = ["GlobalPlannerCore"]

MAX_ERRORS = 20            # errors kept for the fleet state (the oldest are dropped)
CLEARANCE_REPEAT_S = 0.5   # clearances are repeated this often (lost or reordered messages heal)
PATH_REPEAT_S = 2.0        # paths are repeated this often (a move_client that starts late gets one)
RETRY_S = 1.0              # robots parked for want of a collision-free path are retried this often
SLOW_REPLAN_S = 0.05       # a re-plan that takes longer than this is logged
TASKS_REPEAT_S = 0.5       # /fleet/tasks is published this often (wall s), and after every change
STALE_WAIT_S = 2.0        # fleet s a robot waits for one planned before it still far off before it is re-planned
STALE_EVERY_S = 1.0       # fleet s between re-plans of robots held by a stale order (bounds their CPU)
STALE_GAP = 2              # cells that robot is still short of the shared cell for the wait to count as stale
POSE_WAIT_S = 60.0         # s without a robot's first pose after which the ones still without are taken to be away
ROBOT_SPEED_MS = 0.15      # m/s a robot makes good along cells (turns and stops included): the task clock's step


@dataclass
class _Robot:
    name: str
    tracker: CellTracker
    pose: tuple[float, float, float] | None = None
    pose_stamp: float = 0.0                           # header stamp of ``pose``, s (0: unknown)
    pending_goal: int | None = None
    plan: int = 0
    cells: list[int] = field(default_factory=list)   # the path last sent (goalNodesList.data)
    base: int = 0                                     # index in ``cells`` of the planner's paths[r][0]
    at: int = 0                                       # index in ``cells`` of the robot's cell at the last sync
    cleared: int = -1                                 # last clearance index sent
    cancels: int = 0
    progress: dict = field(default_factory=dict)
    obstacles_seen: int = 0


class GlobalPlannerCore:
    """See the module docstring. ``robots``: robot IDs served; ``clock``: monotonic seconds
    (for repeats and obstacle confirmation); ``places``: named places for tasks (None: none);
    ``battery``: the robots' battery parameters (None: not planned for); ``park_idle``: idle
    robots drive to parking places; planner keyword arguments go to FleetPlanner (its re-plan
    bound ``replan_bound_s`` defaults to :data:`~rce_fleet.planning.prioritized.REPLAN_BOUND_S`
    here)."""

    def __init__(self, geometry: GridGeometry, robots: list[str] = (), *, clock: Callable[[], float] = time.monotonic,
                 lidar_blocking: bool = True, obstacle_filter: ObstacleFilter | None = None,
                 log: Callable[..., None] | None = None, places: Places | None = None,
                 battery: BatteryParams | None = None, park_idle: bool = False, **planner_kw: Any):
        self.geo = geometry
        free = np.array(geometry.free, dtype=bool).reshape(geometry.rows, geometry.cols)
        self.graph = GridGraph(free, [geometry.neighbours(c) for c in range(geometry.n_cells)])
        self.fp = FleetPlanner(self.graph, **{"replan_bound_s": REPLAN_BOUND_S, **planner_kw})
        self.clock = clock
        self.lidar_blocking = lidar_blocking
        self.obstacles = obstacle_filter or ObstacleFilter(geometry)
        self.obstacle_reports_held = 0      # lidar reports not used: a served robot had no pose yet
        self._unplaced = 0                  # robots served without a pose yet
        self._first_pose_at = clock()       # s: when the last robot got its first pose (or the planner started)
        self.log = log or (lambda msg, **kw: None)
        self.robots: dict[str, _Robot] = {}
        self.errors: deque[str] = deque(maxlen=MAX_ERRORS)
        self.errors_dropped = 0             # errors pushed out of ``errors`` by newer ones
        self.replans = 0
        self.plan_times: list[float] = []   # seconds per re-plan
        self._seen_result = None
        self._plan_ids = 0
        self._seq = 0
        self._last_clear_repeat = -math.inf
        self._last_path_repeat = -math.inf
        self._last_retry = -math.inf
        self._stale_since: dict[str, float] = {}   # robot -> fleet time it began a stale wait
        self.stale_replans = 0
        self._last_stale = -math.inf
        self.stamp = 0.0                    # fleet time: the newest pose stamp, s
        self.places = places or Places([], geometry)
        self.part = {c: i for i, p in enumerate(components(geometry)) for c in p}
        self.book = TaskBook(self.places, self._usable, step_s=geometry.cell_size_m / ROBOT_SPEED_MS)
        self.dispatcher = Dispatcher(self.book, LifelongGrid(free), chargers=self.places.cells("charger"),
                                     parking=self.places.cells("parking"), battery=battery,
                                     cell_m=geometry.cell_size_m, park_idle=park_idle, places=self.places.by_cell)
        self._tasks_seq = 0
        self._last_tasks = -math.inf
        for r in robots:
            self.add_robot(r)

    # -- robots ---------------------------------------------------------------------------
    def add_robot(self, robot: str) -> bool:
        """Serve ``robot`` (no-op if known). Returns True when it is new."""
        if robot in self.robots:
            return False
        self.robots[robot] = _Robot(robot, CellTracker(self.geo))
        self._unplaced += 1
        self._first_pose_at = self.clock()      # a robot coming up: the wait for poses starts again
        self.dispatcher.add_robot(robot)
        return True

    def _error(self, text: str, **fields) -> None:
        if len(self.errors) == self.errors.maxlen:
            self.errors_dropped += 1
        self.errors.append(text)
        self.log("error", text=text, **fields)

    # -- inputs -----------------------------------------------------------------------------
    def on_pose(self, robot: str, x: float, y: float, yaw: float, stamp: float = 0.0) -> list[Out]:
        """A pose estimate (``/RobotN/amcl_pose``; ``stamp``: its header stamp, s, the fleet clock)."""
        rec = self.robots.get(robot)
        if rec is None:
            return []
        self.stamp = max(self.stamp, float(stamp))
        if rec.pose is None:
            self._unplaced -= 1
            self._first_pose_at = self.clock()
        rec.pose = (float(x), float(y), float(yaw))
        rec.pose_stamp = float(stamp)
        before = rec.tracker.cell
        cell = rec.tracker.update(x, y)
        if cell is None or cell == before:
            return []
        try:
            self.fp.set_position(robot, cell)
        except PlannerError as e:
            self._error(f"{robot}: {e}", robot=robot)
            return []
        out = []
        if rec.pending_goal is not None:
            goal, rec.pending_goal = rec.pending_goal, None
            out += self._set_goals({robot: goal})
        return out + self._sync()

    def on_goal(self, robot: str, cell: int) -> list[Out]:
        """An operator goal (``/fleet/goal``); ``cell`` -1 drops the goal."""
        return self.on_goals({robot: cell})

    def on_goals(self, goals: dict[str, int], operator: bool = True) -> list[Out]:
        """Several goals at once (planned together: one re-plan). ``operator``: they come from an
        operator (``/fleet/goal``), so the robots leave the dispatcher's hands until they arrive."""
        ok: dict[str, int] = {}
        out: list[Out] = []
        for robot, cell in goals.items():
            rec = self.robots.get(robot)
            if rec is None:
                self._error(f"goal for unknown robot {robot!r} refused (robots: {', '.join(sorted(self.robots))})",
                            robot=robot)
                continue
            cell = int(cell)
            if operator:
                self.dispatcher.on_operator_goal(robot, cell, self.stamp)
            if cell < 0:
                if robot in self.fp.positions:
                    self.fp.clear_goal(robot)
                rec.pending_goal = None
                self.log("goal cleared", robot=robot)
                continue
            if not self.geo.valid(cell):
                self._error(f"{robot}: goal cell {cell} is outside the {self.geo.rows}x{self.geo.cols} grid "
                            f"(cells 0..{self.geo.n_cells - 1})", robot=robot)
                continue
            if robot not in self.fp.positions:
                rec.pending_goal = cell
                self.log("goal pending until the robot's first pose", robot=robot, goal=cell)
                continue
            ok[robot] = cell
        if ok:
            out += self._set_goals(ok)
        return out + self._sync()

    def _set_goals(self, goals: dict[str, int]) -> list[Out]:
        try:
            res = self.fp.set_goals(goals)
        except PlannerError as e:
            self._error(str(e))
            return []
        for r, g in goals.items():
            self.log("goal", robot=r, goal=g, start=self.fp.positions.get(r))
            if r in res.unreachable:
                self._error(f"{r}: goal cell {g} unreachable: {res.unreachable[r]}", robot=r, goal=g)
        return []

    def on_block(self, cell: int, blocked: bool = True, source: str = "operator") -> list[Out]:
        """Block (or unblock) ``cell`` (``/fleet/block`` or a lidar sighting). Re-plans at once;
        the robots whose paths crossed the cell get cancelGoal before their new path. After an
        unblock, lidar reports do not block the cell again for ``ObstacleFilter.clear_hold_s``."""
        cell = int(cell)
        source = source or "operator"
        if not self.geo.valid(cell):
            self._error(f"cannot {'block' if blocked else 'unblock'} cell {cell}: outside the "
                        f"{self.geo.rows}x{self.geo.cols} grid", cell=cell)
            return []
        if blocked:
            if cell in self.fp.blocked:
                return []
            t0 = time.perf_counter()
            self.dispatcher.on_block(cell, source, self.stamp)
            hit = self.fp.block(cell, source)
            self.log("cell blocked", cell=cell, source=source, cancelled=sorted(hit),
                     replan_ms=round((time.perf_counter() - t0) * 1e3, 2))
            return self._sync(cancelled=hit)
        if cell not in self.fp.blocked:
            return []
        self.fp.unblock(cell)
        self.obstacles.clear(cell, self.clock())      # scans from before the unblock do not block it again
        self.log("cell unblocked", cell=cell)
        return self._sync()

    def on_obstacles(self, robot: str, points: list[tuple[float, float]], stamp: float = 0.0) -> list[Out]:
        """Lidar points of ``robot`` not explained by the static map (``/RobotN/obstacles``;
        ``stamp``: its header stamp, s, the fleet clock; 0: unknown). Not used (counted in
        ``obstacle_reports_held``) while a robot the planner serves has no pose yet: it stands
        somewhere unknown, and the others' lidars would see it as an obstacle (the live fleet's
        robots connect one after the other, so the first ones see the rest long before those
        report a pose). Once :data:`POSE_WAIT_S` pass without a robot's first pose, the robots
        still without one are taken to be away, and the reports are used again."""
        rec = self.robots.get(robot)
        if rec is None or not self.lidar_blocking:
            return []
        rec.obstacles_seen += 1
        if self._unplaced and self.clock() - self._first_pose_at < POSE_WAIT_S:
            # a robot not yet localised stands somewhere unknown: its body reads as an obstacle. The fleet is
            # still coming up while robots keep reporting their first poses; POSE_WAIT_S without one, the
            # robots still without a pose are taken to be away, and the reports count again
            self.obstacle_reports_held += 1
            if self.obstacle_reports_held == 1:
                unplaced = [r for r, v in self.robots.items() if v.pose is None]
                self.log("lidar reports not used until every robot has a pose", waiting_for=unplaced[:10],
                         robots_without_pose=len(unplaced), at_most_s=POSE_WAIT_S)
            return []
        poses = {r: (v.pose[0], v.pose[1]) for r, v in self.robots.items() if v.pose is not None}
        ages = {r: stamp - v.pose_stamp for r, v in self.robots.items()
                if v.pose is not None and stamp > 0 and v.pose_stamp > 0}
        cells = self.obstacles.update(poses.get(robot), points, self.clock(), poses,
                                      set(self.fp.positions.values()), self.fp.blocked, ages)
        out: list[Out] = []
        for c in cells:
            out += self.on_block(c, True, f"lidar:{robot}")
        return out

    def on_progress(self, robot: str, progress: dict) -> None:
        """A move_client's ``/RobotN/progress`` (kept for the fleet state)."""
        rec = self.robots.get(robot)
        if rec is not None:
            rec.progress = progress

    # -- tasks ------------------------------------------------------------------------------------
    def _usable(self, cell: int) -> str | None:
        """Why an errand cannot use ``cell`` now (None: it can)."""
        if cell in self.fp.blocked:
            return f"is blocked (by {self.fp.blocked[cell]})"
        parts = {self.part.get(c) for c in self.fp.positions.values()}
        if parts and self.part.get(cell) not in parts:
            return "cannot be reached from any robot (walled off)"
        return None

    def on_task(self, msg: dict) -> list[Out]:
        """A ``fleet/Task`` (``/fleet/task``): queued or refused; the answer goes out at once."""
        a = self.book.request_add(msg, self.stamp)
        self.log("task" if a["ok"] else "task refused", **{k: v for k, v in a.items() if v != ""})
        return [self.tasks_msg()]

    def on_task_cancel(self, msg: dict) -> list[Out]:
        """A ``fleet/TaskCancel`` (``/fleet/task_cancel``); the robot drops the task at the next tick."""
        a = self.book.request_cancel(msg, self.stamp)
        self.log("task cancel" if a["ok"] else "task cancel refused", **{k: v for k, v in a.items() if v != ""})
        return [self.tasks_msg()] + self.dispatch()

    def on_battery(self, robot: str, fraction: float) -> None:
        """A ``sensor_msgs/BatteryState`` percentage (0..1) of ``robot``."""
        self.dispatcher.on_battery(robot, fraction)

    def robot_view(self, r: str) -> RobotView:
        """What the dispatcher needs of robot ``r`` (cell, goal, arrived, permanently stuck)."""
        fp, rec = self.fp, self.robots[r]
        cell, goal = fp.positions.get(r), fp.goals.get(r)
        p = rec.progress
        arrived = (goal is not None and cell == goal and p.get("state") == "arrived"
                   and int(p.get("goal", goal)) == goal)
        stuck = fp.unreachable.get(r, "") if r in fp.unreachable and self._permanent(r) else ""
        return RobotView(cell, goal, arrived, stuck)

    def dispatch(self) -> list[Out]:
        """Run the dispatcher (tasks, batteries, parking) and plan the goals it changes."""
        goals = self.dispatcher.update(self.stamp, {r: self.robot_view(r) for r in self.robots})
        if not goals:
            return []
        for r, g in goals.items():
            self.log("dispatch", robot=r, goal=g, activity=self.dispatcher.robots[r].activity,
                     task=getattr(self.dispatcher.robots[r].task, "id", ""))
        return self.on_goals(goals, operator=False)

    def tasks_msg(self) -> Out:
        """The ``/fleet/tasks`` message (``fleet/TaskList``)."""
        self._tasks_seq += 1
        self._last_tasks = self.clock()
        return Out("/fleet/tasks", "fleet/TaskList",
                   self.book.message(self._tasks_seq, self.stamp, self.dispatcher.robot_messages(self.stamp)))

    def tasks_due(self) -> list[Out]:
        """``/fleet/tasks`` when something changed or ``TASKS_REPEAT_S`` passed (the node calls it
        with :meth:`tick`)."""
        if self.book.changed or self.clock() - self._last_tasks >= TASKS_REPEAT_S:
            return [self.tasks_msg()]
        return []

    def tick(self) -> list[Out]:
        """Periodic work: dispatch tasks, plan the robots the last re-plan's wall-time bound
        deferred, re-plan robots held by a stale order (:meth:`_replan_stale`), retry robots
        parked for want of a collision-free path, repeat paths and clearances (so a lost or
        late message never stalls a robot)."""
        now = self.clock()
        out: list[Out] = self.dispatch()
        if self.fp.last_result is not None and self.fp.last_result.deferred:
            self.fp.serve_deferred()         # robots the last re-plan's wall-time bound left for this round
            out += self._sync()
        out += self._replan_stale()
        if now - self._last_retry >= RETRY_S:
            self._last_retry = now
            retry = {r: self.fp.goals[r] for r in self.fp.unreachable
                     if self.fp.goals.get(r) is not None and not self._permanent(r)}
            if retry:
                self.fp.set_goals(retry)
                out += self._sync()
        if now - self._last_path_repeat >= PATH_REPEAT_S:
            self._last_path_repeat = now
            out += [self._path_msg(r) for r, rec in self.robots.items() if rec.plan]
        if now - self._last_clear_repeat >= CLEARANCE_REPEAT_S:
            self._last_clear_repeat = now
            out += [self._clear_msg(r) for r, rec in self.robots.items() if rec.plan and rec.cleared >= 0]
        return out

    def _replan_stale(self) -> list[Out]:
        """Re-plan robots that have waited ``STALE_WAIT_S`` for a robot planned into their next
        cell before them that is still ``STALE_GAP`` cells or more short of it (the plan's order
        went stale: robots run ahead of or behind its timing); the re-plan lets them go first
        where they can. At most one such re-plan per ``STALE_EVERY_S``."""
        stale = self.fp.stale_waits(STALE_GAP)
        since = self._stale_since = {r: self._stale_since.get(r, self.stamp) for r in stale}
        due = {r for r, t in since.items() if self.stamp - t >= STALE_WAIT_S}
        if not due or self.stamp - self._last_stale < STALE_EVERY_S:
            return []
        self._last_stale = self.stamp
        for r in due:
            since[r] = self.stamp
        self.stale_replans += 1
        self.fp.replan(due)
        return self._sync()

    # -- outputs ------------------------------------------------------------------------------
    def _path_msg(self, robot: str) -> Out:
        rec = self.robots[robot]
        return Out(f"/{robot}/goalNodesList", "std_msgs/Int32MultiArray",
                   {"layout": {"dim": [{"label": f"plan {rec.plan}", "size": len(rec.cells), "stride": len(rec.cells)}],
                               "data_offset": 0},
                    "data": list(rec.cells)})

    def _clear_msg(self, robot: str) -> Out:
        rec = self.robots[robot]
        return Out(f"/{robot}/clearance", "fleet/Clearance", {"plan": rec.plan, "index": rec.cleared})

    def _sync(self, cancelled: set[str] = frozenset()) -> list[Out]:
        """Publish what the planner's last re-plan changed: cancels, paths, clearances."""
        fp = self.fp
        out: list[Out] = []
        res = fp.last_result
        replanned = res is not None and res is not self._seen_result
        if replanned:
            self._seen_result = res
            self.replans += 1
            self.plan_times.append(res.elapsed_s)
            if res.deferred:
                self.log("bounded re-plan", ms=round(res.elapsed_s * 1e3, 1), deferred=sorted(res.deferred),
                         abandoned=res.abandoned)
            replanned = not res.abandoned      # an abandoned re-plan changed nobody's plan
            if res.elapsed_s > SLOW_REPLAN_S:
                self.log("slow re-plan", ms=round(res.elapsed_s * 1e3, 1), full=res.full, changed=sorted(res.changed),
                         unreachable=sorted(res.unreachable))
            if res.unreachable:
                for r, why in res.unreachable.items():
                    if r in (res.changed | set(cancelled)):
                        self.log("unreachable", robot=r, goal=fp.goals.get(r), reason=why)
        for r in cancelled:
            rec = self.robots[r]
            rec.cancels += 1
            out.append(Out(f"/{r}/cancelGoal", "std_msgs/Bool", {"data": True}))
        for r, path in fp.paths.items():
            rec = self.robots.get(r)
            if rec is None:
                continue
            new = compress(path)
            if replanned or not rec.plan:
                # unchanged cells: the new path is the tail of the list the robot has from where it
                # stands (a path may pass a cell twice, as a robot that yields and comes back does:
                # only the robot's own place in the list counts)
                cur, keep = 0, False
                if rec.plan and r not in cancelled:
                    i = next((i for i in range(rec.at, len(rec.cells)) if rec.cells[i] == new[0]), None)
                    if i is not None and rec.cells[i:] == new:
                        cur, keep = i, True
                if keep:
                    rec.base = cur
                else:
                    self._plan_ids += 1
                    rec.plan, rec.cells, rec.base, rec.at, rec.cleared = self._plan_ids, new, 0, 0, -1
                    out.append(self._path_msg(r))
                    self.log("path", robot=r, plan=rec.plan, cells=new, goal=fp.goals.get(r))
            k = fp.clearance(r)
            rec.at = rec.base + compressed_index(path, fp.progress(r))
            idx = rec.base + compressed_index(path, k)
            if idx != rec.cleared:
                rec.cleared = idx
                out.append(self._clear_msg(r))
        return out

    # -- state ------------------------------------------------------------------------------
    def _permanent(self, robot: str) -> bool:
        """True when ``robot``'s goal cannot be reached until the map or the blocked cells change."""
        fp = self.fp
        g = fp.goals.get(robot)
        if g is None:
            return False
        if not self.graph.is_free(g) or g in fp.blocked:
            return True
        pos = fp.positions.get(robot)
        return pos is not None and pos != g and fp.distance(pos, g) == math.inf

    def robot_state(self, robot: str) -> dict:
        """``robot``'s entry of the fleet state (``fleet/RobotState``, JSON form)."""
        fp, rec = self.fp, self.robots[robot]
        cell = fp.positions.get(robot, rec.tracker.cell if rec.tracker.cell is not None else -1)
        goal = fp.goals.get(robot)
        if goal is None:
            goal = rec.pending_goal
        path = rec.cells[rec.base:] if rec.plan else []
        if robot in fp.positions and rec.plan:
            # index of the robot's current cell in the remaining path
            cur = compressed_index(fp.paths[robot], fp.progress(robot)) if robot in fp.paths else 0
            path = rec.cells[rec.base + cur:]
            cleared = max(rec.cleared - rec.base - cur, 0)
        else:
            cleared = 0
        if robot not in fp.positions:
            state = "unknown"
        elif robot in fp.unreachable:
            state = "unreachable"
        elif goal is None:
            state = "idle"
        elif cell == goal and len(path) <= 1:
            state = "arrived"
        elif cleared > 0:
            state = "moving"
        else:
            state = "waiting"
        x, y, yaw = rec.pose if rec.pose is not None else (math.nan, math.nan, math.nan)
        p = rec.progress
        return {"robot": robot, "cell": int(cell), "goal": -1 if goal is None else int(goal),
                "x": x, "y": y, "yaw": yaw, "path": [int(c) for c in path], "plan": rec.plan,
                "cleared": int(cleared), "replans": int(fp.replans.get(robot, 0)), "cancels": rec.cancels,
                "state": state, "error": fp.unreachable.get(robot, ""),
                "error_permanent": state == "unreachable" and self._permanent(robot),
                "client_state": str(p.get("state", "")), "distance_left": float(p.get("distance_left", 0.0))}

    def state(self, stamp: float | None = None) -> dict:
        """The ``fleet/FleetState`` message (JSON form)."""
        self._seq += 1
        geo = self.geo
        gx, gy = geo.grid_corner()
        stamp = time.time() if stamp is None else stamp
        blocked = sorted(self.fp.blocked)
        times = self.plan_times
        return {"header": {"stamp": {"secs": int(stamp), "nsecs": int((stamp % 1) * 1e9)}, "frame_id": "map"},
                "seq": self._seq, "rows": geo.rows, "cols": geo.cols, "cell_w": geo.cell_w_m, "cell_h": geo.cell_h_m,
                "grid_x": gx, "grid_y": gy, "map_resolution": geo.resolution,
                "map_origin": {"x": geo.origin[0], "y": geo.origin[1], "theta": geo.origin[2]},
                "free": "".join("1" if f else "0" for f in geo.free),
                "blocked": blocked, "blocked_by": [self.fp.blocked[c] for c in blocked],
                "robots": [self.robot_state(r) for r in sorted(self.robots)],
                "errors": list(self.errors), "replans": self.replans,
                "last_plan_ms": times[-1] * 1e3 if times else 0.0,
                "max_plan_ms": max(times) * 1e3 if times else 0.0,
                "replan_bound_ms": self.fp.limits.bound_s * 1e3 if math.isfinite(self.fp.limits.bound_s) else 0.0,
                "replans_bounded": self.fp.bounded_replans, "replans_abandoned": self.fp.abandoned_replans,
                "robots_deferred": len(self.fp.deferred), "robots_deferred_total": self.fp.deferred_robots_total}
