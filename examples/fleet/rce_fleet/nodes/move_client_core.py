"""The move_client node's logic, sans-I/O: a cell path, its clearance and cancelGoal from the
global planner and the robot's pose in; goals and cancels for the robot's local
navigation and progress reports out.

One move_client runs per robot (namespace ``RobotN``) in the fleet container. It turns
the path ``/RobotN/goalNodesList`` into metric waypoints at cell centres and sends them,
one cell ahead, as ``geometry_msgs/PoseStamped`` on ``/RobotN/move_base_simple/goal``:

* the waypoint of path index k+1 is sent only when ``/RobotN/clearance`` allows k+1, so a
  robot that is slowed down or stopped never makes another one collide with it (the
  planner clears a cell only after every robot planned through it earlier has left);
* it is sent once the robot is in cell k and either near its centre (``switch_radius``)
  or driving straight on (cells k-1, k, k+1 in a line), so the robot does not stop at
  every cell centre but never cuts a corner through a cell that is not on its path;
* ``/RobotN/cancelGoal`` True: the robot is stopped at once (``/RobotN/move_base/cancel``,
  ``actionlib_msgs/GoalID`` with an empty id: cancel all) and the old plan is dropped;
  the robot waits for the new path and its clearance;
* a new path without cancelGoal (the planner re-planned around something else): the
  waypoint the robot is driving to is kept when it is the new path's next cell (the
  planner keeps such a committed move), otherwise the robot is stopped first.

Messages of one plan carry its id (``goalNodesList.layout.dim[0].label`` is ``"plan <id>"``,
``fleet/Clearance.plan``); a clearance for another plan is ignored. The planner publishes
cancelGoal before the new path on one link, so they arrive in that order.
"""
from __future__ import annotations

import math
from ..maps.geometry import GridGeometry, quaternion_from_yaw
from .common import Out
from .tracking import CellTracker

__all__ = ["MoveClientCore", "plan_id_of"]


def plan_id_of(layout_label: str) -> int:
    """Plan id from a goalNodesList ``layout.dim[0].label`` (``"plan 12"`` -> 12; 0 if none)."""
    parts = str(layout_label or "").split()
    if len(parts) == 2 and parts[0] == "plan" and parts[1].isdigit():
        return int(parts[1])
    return 0


class MoveClientCore:
    """See the module docstring.

    ``switch_radius``: m from a cell's centre at which the next waypoint is sent on a turn
    (default 30 % of the smaller cell side); ``arrive_tol``: m from the goal centre at
    which the robot counts as arrived."""

    def __init__(self, robot: str, geometry: GridGeometry, *, switch_radius: float | None = None,
                 arrive_tol: float = 0.2):
        self.robot = robot
        self.geo = geometry
        self.switch_radius = 0.3 * geometry.cell_size_m if switch_radius is None else float(switch_radius)
        self.arrive_tol = float(arrive_tol)
        self.tracker = CellTracker(geometry)
        self.pose: tuple[float, float, float] | None = None
        self.plan = 0
        self.cancelled_plan = 0
        self.cells: list[int] = []
        self.cleared = -1
        self.index = 0
        self.target = -1
        self.waypoints = 0
        self.cancels = 0
        self.stamp = 0.0
        self._cancelled = False

    @property
    def goal_topic(self) -> str:
        """Where the robot's waypoints go (``geometry_msgs/PoseStamped``)."""
        return f"/{self.robot}/move_base_simple/goal"

    @property
    def cancel_topic(self) -> str:
        """Where the robot's cancels go (``actionlib_msgs/GoalID``)."""
        return f"/{self.robot}/move_base/cancel"

    # -- inputs -------------------------------------------------------------------------------
    def on_path(self, plan: int, cells: list[int]) -> list[Out]:
        """``/RobotN/goalNodesList``: plan id and cells (repeats of the current plan are no-ops)."""
        plan = int(plan)
        cells = [int(c) for c in cells]
        if plan <= self.plan or not cells or not all(self.geo.valid(c) for c in cells):
            return []
        out: list[Out] = []
        old_target = self.cells[self.target] if 0 <= self.target < len(self.cells) else None
        self.plan, self.cells, self.cleared = plan, cells, -1
        self._cancelled = False
        here = self.tracker.cell
        self.index = 1 if len(cells) > 1 and here == cells[1] else 0
        if old_target is not None:
            if old_target in cells[self.index:self.index + 2]:
                self.target = cells.index(old_target, self.index)
            else:
                self.target = -1
                out.append(self._cancel())
        else:
            self.target = -1
        return out + self._advance()

    def on_clearance(self, plan: int, index: int) -> list[Out]:
        """``/RobotN/clearance``: the robot may drive up to ``cells[index]`` of plan ``plan``."""
        if int(plan) != self.plan or self.plan <= self.cancelled_plan:
            return []
        self.cleared = min(int(index), len(self.cells) - 1)
        out: list[Out] = []
        if self.target > self.cleared:       # never happens within a plan; be safe
            self.target = -1
            out.append(self._cancel())
        return out + self._advance()

    def on_cancel(self, flag: bool) -> list[Out]:
        """``/RobotN/cancelGoal``: True stops the robot and drops the current plan."""
        if not flag:
            return []
        self.cancels += 1
        self.cancelled_plan = self.plan
        self._cancelled = True
        self.cleared = -1
        self.target = -1
        return [self._cancel()]

    def on_pose(self, x: float, y: float, yaw: float, stamp: float | None = None) -> list[Out]:
        """The robot's pose estimate (``/RobotN/amcl_pose``)."""
        self.pose = (float(x), float(y), float(yaw))
        if stamp is not None:
            self.stamp = stamp
        cell = self.tracker.update(x, y)
        if self.cells and cell is not None:
            hi = max(self.target, self.index + 1)
            for j in range(self.index, min(hi, len(self.cells) - 1) + 1):
                if self.cells[j] == cell:
                    self.index = j
                    break
        return self._advance()

    # -- outputs ---------------------------------------------------------------------------------
    def _cancel(self) -> Out:
        return Out(self.cancel_topic, "actionlib_msgs/GoalID", {"id": ""})

    def _goal(self, index: int) -> Out:
        x, y = self.geo.center(self.cells[index])
        if index > 0:
            px, py = self.geo.center(self.cells[index - 1])
            yaw = math.atan2(y - py, x - px)
        else:
            yaw = self.pose[2] if self.pose else 0.0
        secs = self.stamp
        return Out(self.goal_topic, "geometry_msgs/PoseStamped",
                   {"header": {"stamp": {"secs": int(secs), "nsecs": int((secs % 1) * 1e9)}, "frame_id": "map"},
                    "pose": {"position": {"x": x, "y": y, "z": 0.0}, "orientation": quaternion_from_yaw(yaw)}})

    def _straight(self, index: int) -> bool:
        """True when cells k-1, k, k+1 lie in one row or one column."""
        if index < 1 or index + 1 >= len(self.cells):
            return False
        (r0, c0), (r1, c1), (r2, c2) = (self.geo.rc(self.cells[j]) for j in (index - 1, index, index + 1))
        return (r0 == r1 == r2) or (c0 == c1 == c2)

    def _dist_to(self, index: int) -> float:
        if self.pose is None:
            return math.inf
        x, y = self.geo.center(self.cells[index])
        return math.hypot(x - self.pose[0], y - self.pose[1])

    def _advance(self) -> list[Out]:
        if not self.cells or self.cleared < 0 or self.pose is None or self._cancelled:
            return []
        last = len(self.cells) - 1
        if self.target < 0:
            if self.index < self.cleared:
                # the segment from anywhere in cell k to the centre of k+1 stays in those two cells
                self.target = self.index + 1
            elif self.index == self.cleared and self._dist_to(self.index) > self.arrive_tol:
                self.target = self.index          # settle at the centre of the cell it holds
            else:
                return []
            self.waypoints += 1
            return [self._goal(self.target)]
        k = self.target
        if k < last and k + 1 <= self.cleared and self.index >= k and \
                (self._straight(k) or self._dist_to(k) <= self.switch_radius):
            self.target = k + 1
            self.waypoints += 1
            return [self._goal(self.target)]
        return []

    # -- progress --------------------------------------------------------------------------------
    @property
    def state(self) -> str:
        """``no_pose``, ``cancelled``, ``idle``, ``driving``, ``waiting`` (for clearance) or ``arrived``."""
        if self.pose is None:
            return "no_pose"
        if self._cancelled:
            return "cancelled"
        if not self.cells:
            return "idle"
        last = len(self.cells) - 1
        if last == 0:
            return "idle" if self.cleared < 0 or self._dist_to(0) > self.arrive_tol else "arrived"
        if self.index == last and self.target == last and self._dist_to(last) <= self.arrive_tol:
            return "arrived"
        if self.target > self.index or (self.target == self.index and self._dist_to(self.target) > self.arrive_tol):
            return "driving"
        return "waiting"

    def distance_left(self) -> float:
        """Metres from the robot along its path to the goal (0 without a path or pose)."""
        if not self.cells or self.pose is None:
            return 0.0
        last = len(self.cells) - 1
        if self.index >= last:
            return self._dist_to(last)
        return self._dist_to(self.index + 1) + self.geo.path_length(self.cells[self.index + 1:])

    def progress(self) -> dict:
        """The ``fleet/MoveProgress`` message (JSON form)."""
        s = self.stamp
        return {"header": {"stamp": {"secs": int(s), "nsecs": int((s % 1) * 1e9)}, "frame_id": "map"},
                "robot": self.robot, "plan": self.plan,
                "cell": -1 if self.tracker.cell is None else int(self.tracker.cell),
                "goal": self.cells[-1] if self.cells else -1, "index": self.index, "target": self.target,
                "cleared": self.cleared, "distance_left": float(self.distance_left()), "state": self.state,
                "waypoints": self.waypoints, "cancels": self.cancels}
