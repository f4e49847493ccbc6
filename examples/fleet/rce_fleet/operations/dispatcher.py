"""Who does what next in the live fleet, sans-I/O: tasks, charging and parking turned into
one goal cell per robot, which the global planner's :class:`~rce_fleet.planning.FleetPlanner`
then drives collision-free.

Each call of :meth:`Dispatcher.update` (the global planner's tick, ~5 Hz) at fleet time ``now``:

1. fails open tasks past their deadline (:meth:`TaskBook.expire`);
2. advances the tasks of robots standing on their next errand (the move_client says
   ``arrived`` there): the first errand opens the task (``active``, never reassigned), the
   last one makes it ``done``;
3. batteries (when the robots report ``sensor_msgs/BatteryState`` and the fleet has
   :class:`~rce_fleet.operations.battery.BatteryParams`): a robot below ``threshold`` without an opened
   task drops its unopened task (back to the queue) and drives to the nearest free charger;
   it charges there until ``recharge``;
4. allocation by the lifelong allocator (:class:`rce_fleet.lifelong.GreedyScheduler`: an
   auction on finish time; an unopened task may go to a robot that finishes it sooner) over
   the robots that are free or hold an unopened task. A robot never takes a task whose
   energy (to the first errand, through the last, and on to the nearest charger, plus a 5 %
   reserve) is more than its battery holds: it goes to charge instead;
5. idle robots drive to the nearest free parking place (``park_idle``, or once they have
   done a task), out of the aisles and off the stations; one that has had no task yet waits
   :data:`PARK_AFTER_S` where it stands first (a fleet that starts gets its first tasks there, not
   on the way to parking);
6. a goal cell another robot heads to is not sent yet (the planner refuses two robots one
   goal): the robot waits on the free cell nearest to it (within ``WAIT_RADIUS`` steps; no
   place, no other robot's goal or cell), not where it stands (often the station it just
   served, which the next robot needs), until that one has a new goal. So several robots
   may hold tasks at one station: they queue beside it, as the lifelong planner's robots do.
   Of the robots that want one cell, the nearest heads there (the one sent there keeps it
   unless another is ``SWAP_STEPS`` nearer); a waiting spot stays while robots only pass it.

A robot that an operator sends somewhere (``/fleet/goal``) is the operator's until it
arrives or its goal is dropped: it takes no task, and an unopened task it held goes back to
the queue.

Stalls. A robot that holds work (a task, or the way to a charger or a parking place) and makes no
progress (enters no new cell and does not reach its goal) for :data:`STALL_S` fleet seconds is
*stalled*: something the fleet does not know holds it (an obstacle its lidar cannot see, a goal it
cannot be planned to, a jam). That is an alert (``stalled_s``, ``stalls`` and ``alert`` in its
``fleet/RobotTask``; :attr:`Dispatcher.alerts`), and the fleet recovers, one step per
:data:`STALL_S` while the robot stays where it is:

- an unopened task goes back to the queue for another robot, and the stalled robot is offered no
  task for :data:`BENCH_S` unless it moves (the task is re-assigned);
- a charger or parking place it cannot reach is given up for another one (another cell);
- an opened task (the robot carries its load) is re-planned first: its goal is dropped and set
  again, so the planner plans it afresh from where it stands; when the robot is still held after
  that, the task fails with the reason, instead of staying active unseen.
"""
from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from .battery import BatteryParams
from ..lifelong import DistanceCache, GreedyScheduler, LifelongGrid, TaskState
from .tasks_api import TaskBook, TaskRecord

__all__ = ["Dispatcher", "RobotView"]

BUSY = 2 ** 62              # allocator's task id for a robot busy with no task (charging, the operator's)
RESERVE = 0.05              # share of the capacity a task must leave besides the way to a charger
SCHEDULE_BUDGET_S = 0.02    # wall s the allocator may spend per call on new distance maps
UNREACHABLE = 65535
WAIT_RADIUS = 3            # steps from a taken station within which a robot waits for it
SWAP_STEPS = 3             # steps nearer to a station by which a robot takes it from the one sent there
START_HORIZON_STEPS = 20    # tasks whose earliest start is further ahead than this are not offered yet
STALL_S = 60.0              # fleet s a robot holding work may make no progress before it counts as stalled
BENCH_S = 120.0             # fleet s a robot that stalled on a task is offered none (unless it moves meanwhile)
MAX_ALERTS = 100            # alerts kept in Dispatcher.alerts (the oldest go first; alerts_dropped counts them)
PARK_AFTER_S = 30.0         # fleet s a robot that has had no task yet stands idle before it drives to parking

IDLE, PARKING, TASK, TO_CHARGER, CHARGING, OPERATOR, UNKNOWN = (
    "idle", "parking", "task", "to_charger", "charging", "operator", "unknown")


@dataclass
class RobotView:
    """What the planner knows of a robot now: its ``cell`` (None: no pose yet), its planner
    ``goal`` (None: none), whether it ``arrived`` at that goal (move_client says so), and
    whether that goal is permanently unreachable (``stuck``)."""

    cell: int | None
    goal: int | None = None
    arrived: bool = False
    stuck: str = ""


@dataclass
class _Work:
    name: str
    index: int
    activity: str = UNKNOWN
    task: TaskRecord | None = None
    target: int | None = None      # charger / parking cell
    sent: int | None = None        # last goal the dispatcher gave it (None: none)
    battery: float = -1.0          # 0..1, -1 unknown
    busy_s: float = 0.0
    since: float | None = None
    charges: int = 0
    tasks_done: int = 0
    worked: bool = False           # it has had a task (then it parks when idle)
    spot: int | None = None        # where it waits for a goal another robot holds
    still: tuple | None = None     # (cell, goal) it held work at without progress since ``still_since``
    still_since: float = 0.0
    stall_cell: int | None = None  # where it stalled (the alert ends when it leaves that cell)
    stall_start: float = 0.0       # fleet time it stopped making progress there
    stall_rounds: int = 0          # recovery steps taken there
    stalls: int = 0                # stalls so far (alerts raised)
    alert: str = ""                # the current stall alert ("" while it makes progress)
    benched_until: float = -1.0    # fleet time until which it is offered no task (it stalled on one)
    avoid: set[int] | None = None  # chargers / parking places it could not reach (chosen last)
    replan: bool = False           # drop its goal at the next step and set it again (a fresh plan)


class Dispatcher:
    """See the module docstring. ``book``: the task book; ``grid``: the free-cell grid
    (:class:`~rce_fleet.lifelong.LifelongGrid`); ``chargers``/``parking``: cells;
    ``battery``: the robots' battery parameters (None: batteries are not planned for);
    ``cell_m``: metres per cell step (energy estimates); ``park_idle``: send idle robots to
    parking."""

    def __init__(self, book: TaskBook, grid: LifelongGrid, *, chargers: list[int] = (), parking: list[int] = (),
                 battery: BatteryParams | None = None, cell_m: float = 1.0, park_idle: bool = False,
                 places: Iterable[int] = ()):
        self.book, self.grid = book, grid
        self.chargers, self.parking = list(chargers), list(parking)
        self.battery, self.cell_m, self.park_idle = battery, float(cell_m), park_idle
        self.cache = DistanceCache(grid, max_bytes=64 * 2 ** 20)
        self.sched = GreedyScheduler(self.cache)
        self.places = set(places)
        self._near: dict[int, list[int]] = {}
        self.robots: dict[str, _Work] = {}
        self.names: list[str] = []
        self.last_now: float | None = None
        self.schedule_ms: list[float] = []
        self.alerts: deque[dict] = deque(maxlen=MAX_ALERTS)   # stall alerts: t, robot, cell, activity, task, text
        self.alerts_dropped = 0

    # -- inputs -------------------------------------------------------------------------------------
    def add_robot(self, name: str) -> None:
        """Dispatch to ``name`` too (no-op if known)."""
        if name not in self.robots:
            self.robots[name] = _Work(name, len(self.names))
            self.names.append(name)

    def on_battery(self, name: str, fraction: float) -> None:
        """A ``sensor_msgs/BatteryState`` percentage (0..1) of robot ``name``."""
        w = self.robots.get(name)
        if w is not None:
            w.battery = float(fraction)

    def on_operator_goal(self, name: str, cell: int, now: float) -> None:
        """An operator sent ``name`` to ``cell`` (-1: dropped its goal): it is the operator's
        (module docstring). An unopened task goes back to the queue; an opened one fails."""
        w = self.robots.get(name)
        if w is None:
            return
        if w.task is not None:
            if w.task.task.opened:
                self.book.close(w.task, TaskState.FAILED, f"{name} was sent elsewhere by an operator", now)
            else:
                self.book.unassign(w.task, now)
            w.task = None
        w.activity, w.target = (OPERATOR if cell >= 0 else IDLE), None
        w.sent = None

    def on_block(self, cell: int, source: str, now: float) -> None:
        """``cell`` was blocked: fail the tasks with an errand still to do there; robots
        heading to a charger or parking there choose again."""
        for r in self.book.fail_on_cell(cell, f"was blocked ({source})", now):
            self._drop_task(r)
        for w in self.robots.values():
            if w.target == cell and w.activity in (TO_CHARGER, PARKING):
                self._give_up_target(w)

    def _drop_task(self, rec: TaskRecord) -> None:
        for w in self.robots.values():
            if w.task is rec:
                w.task = None
                w.activity = IDLE

    # -- the step ------------------------------------------------------------------------------------
    def update(self, now: float, view: dict[str, RobotView]) -> dict[str, int]:
        """One dispatch step at fleet time ``now`` (s). Returns the goals to set: robot -> cell
        (-1: drop its goal), only where they change."""
        dt = 0.0 if self.last_now is None else max(0.0, now - self.last_now)
        self.last_now = now
        book = self.book
        for r in book.expire(now):
            self._drop_task(r)
        for name, w in self.robots.items():
            v = view.get(name)
            if v is None or v.cell is None:
                continue
            if w.since is None:
                w.since = now
                w.activity = IDLE if w.activity == UNKNOWN else w.activity
            if w.activity == TASK:
                w.busy_s += dt
            if w.task is not None and not w.task.open:      # cancelled or failed meanwhile
                w.task, w.activity = None, IDLE
            self._progress(w, v, now)
            self._watch_stall(w, v, now)
        self._batteries(view, now)
        self._allocate(view, now)
        return self._goals(view, now)

    def _progress(self, w: _Work, v: RobotView, now: float) -> None:
        at = v.arrived and v.goal is not None and v.goal == v.cell
        if w.activity == OPERATOR:
            if at or v.goal is None:
                w.activity = IDLE
            return
        if w.activity == TASK and w.task is not None:
            rec = w.task
            if v.stuck and v.goal == rec.task.goal:
                self.book.close(rec, TaskState.FAILED, f"{w.name} cannot reach cell {v.goal}: {v.stuck}", now)
                w.task, w.activity = None, IDLE
                return
            while at and rec.open and v.cell == rec.task.goal:
                if self.book.reach(rec, now):
                    w.tasks_done += 1
                    w.task, w.activity = None, IDLE
                    break
            return
        if w.activity == TO_CHARGER and at and v.cell == w.target:
            w.activity = CHARGING
            w.charges += 1
        elif w.activity == CHARGING and self.battery and w.battery >= self.battery.recharge:
            w.activity, w.target = IDLE, None
        elif w.activity in (PARKING, TO_CHARGER) and v.stuck:
            self._give_up_target(w)
        if w.activity in (CHARGING, PARKING) and at and v.cell == w.target:
            w.avoid = None                  # it reached one: every place is worth a try again

    def _watch_stall(self, w: _Work, v: RobotView, now: float) -> None:
        """Stalls (module docstring): how long ``w`` has held work at one cell without progress; an
        alert and a recovery step every :data:`STALL_S` of it. The alert stays until the robot enters
        another cell."""
        if w.alert and v.cell != w.stall_cell:          # it moves again: the stall is over
            w.alert, w.stall_rounds, w.stall_cell, w.benched_until = "", 0, None, -1.0
        if not (w.activity in (TASK, TO_CHARGER, PARKING) and v.goal is not None
                and not (v.arrived and v.cell == v.goal)):
            w.still = None                  # no way to make progress on (no goal, or at it)
            return
        if w.still != (v.cell, v.goal):
            w.still, w.still_since = (v.cell, v.goal), now
            return
        if now - w.still_since < STALL_S:
            return
        if not w.alert:
            w.stall_cell, w.stall_start = v.cell, w.still_since
        w.stall_rounds += 1
        w.stalls += 1
        what = f"task {w.task.id}" if w.activity == TASK and w.task is not None else \
            {TO_CHARGER: "its way to a charger", PARKING: "its way to parking"}.get(w.activity, w.activity)
        action = self._recover(w, now)
        w.alert = (f"{w.name} made no progress for {now - w.stall_start:.0f} s at cell {v.cell} on {what} "
                   f"(goal {v.goal}): {action}")
        if len(self.alerts) == self.alerts.maxlen:
            self.alerts_dropped += 1
        self.alerts.append({"t": now, "robot": w.name, "cell": v.cell, "goal": v.goal, "text": w.alert})
        w.still_since = now                 # the next step after another STALL_S without progress

    def _recover(self, w: _Work, now: float) -> str:
        """One recovery step for stalled ``w`` (module docstring); returns what it did."""
        rec = w.task
        if w.activity == TASK and rec is not None and not rec.task.opened:
            self.book.unassign(rec, now)
            w.task, w.activity, w.benched_until = None, IDLE, now + BENCH_S
            return f"task {rec.id} goes back to the queue for another robot; {w.name} takes none for " \
                   f"{BENCH_S:.0f} s unless it moves"
        if w.activity == TASK and rec is not None:
            if w.stall_rounds == 1:
                w.replan = True
                return f"re-planned (its goal dropped and set again); task {rec.id} stays with it"
            self.book.close(rec, TaskState.FAILED, f"{w.name} made no progress for {now - w.stall_start:.0f} s "
                            f"at cell {w.stall_cell} (stalled)", now)
            w.task, w.activity, w.benched_until = None, IDLE, now + BENCH_S
            return f"task {rec.id} failed (it was opened: its load is on {w.name}; an operator should look)"
        target = w.target
        self._give_up_target(w)
        return f"gives cell {target} up for another one"

    def _give_up_target(self, w: _Work) -> None:
        """``w`` cannot reach its charger or parking place: choose another (that one last)."""
        if w.target is not None:
            w.avoid = (w.avoid or set()) | {w.target}
        w.activity, w.target = IDLE, None

    def _batteries(self, view: dict[str, RobotView], now: float) -> None:
        if self.battery is None:
            return
        for w in self.robots.values():
            if w.battery < 0 or w.battery >= self.battery.threshold or w.activity in (TO_CHARGER, CHARGING, UNKNOWN):
                continue
            if w.task is not None and w.task.task.opened:
                continue                    # it was given the task with the energy to finish it
            self._send_to_charger(w, view, now)

    def _send_to_charger(self, w: _Work, view: dict[str, RobotView], now: float) -> bool:
        cell = view[w.name].cell if w.name in view else None
        if cell is None:
            return False
        c = self._nearest_free(cell, self.chargers, view, w)
        if c is None:
            return False                    # every charger taken: try again next step
        if w.task is not None:
            self.book.unassign(w.task, now)
            w.task = None
        w.activity, w.target = TO_CHARGER, c
        return True

    def _nearest_free(self, cell: int, cells: list[int], view: dict[str, RobotView], me: _Work) -> int | None:
        """The nearest of ``cells`` that no other robot stands on or heads to; those ``me`` could not
        reach before (``me.avoid``) only when no other is free."""
        taken = {w.target for w in self.robots.values() if w is not me and w.target is not None}
        taken |= {v.cell for n, v in view.items() if n != me.name and v.cell is not None}
        avoid = me.avoid or set()
        best, bd = None, (True, UNREACHABLE)
        for c in cells:
            if c in taken:
                continue
            d = (c in avoid, self._dist(cell, c))
            if d < bd:
                best, bd = c, d
        return best

    def _allocate(self, view: dict[str, RobotView], now: float) -> None:
        book = self.book
        step = now / book.step_s
        offer = {r.task.id: r.task for r in book.open_records()
                 if r.task.opened or r.state is not TaskState.QUEUED
                 or r.task.earliest_start <= step + START_HORIZON_STEPS}
        if not any(not t.opened for t in offer.values()):
            return
        n = len(self.names)
        pos = np.zeros(n, dtype=np.int64)
        assignment = np.full(n, BUSY, dtype=np.int64)
        free_cell = int(self.grid.free_cells()[0])
        for i, name in enumerate(self.names):
            w, v = self.robots[name], view.get(name)
            pos[i] = v.cell if v is not None and v.cell is not None else free_cell
            if v is None or v.cell is None or w.activity in (UNKNOWN, OPERATOR, TO_CHARGER, CHARGING):
                continue
            if self.battery and 0 <= w.battery < self.battery.threshold:
                continue
            if w.benched_until > now and w.task is None:
                continue                    # it stalled on a task: the others take the work for a while
            assignment[i] = w.task.task.id if w.task is not None else -1
        if not (assignment < 0).any():
            return
        t0 = time.perf_counter()
        prop = self.sched.schedule(pos, assignment, offer, int(step), t0 + SCHEDULE_BUDGET_S)
        self.schedule_ms.append((time.perf_counter() - t0) * 1e3)
        del self.schedule_ms[:-1000]
        # tasks taken from a robot first, then the new holders
        for i, name in enumerate(self.names):
            w = self.robots[name]
            old = int(assignment[i])
            if old < 0 or old == BUSY or int(prop[i]) == old:
                continue
            rec = book.by_pool.get(old)
            if rec is not None and not rec.task.opened and old not in prop:
                book.unassign(rec, now)
            w.task, w.activity = None, IDLE
        for i, name in enumerate(self.names):
            new = int(prop[i])
            if new < 0 or new == BUSY or new == int(assignment[i]):
                continue
            w, rec = self.robots[name], book.by_pool[new]
            if not self._affordable(w, int(pos[i]), rec):
                holder = self.robots.get(rec.robot)
                if rec.state is not TaskState.QUEUED and (holder is None or holder.task is not rec):
                    book.unassign(rec, now)     # its old robot let it go: back to the queue
                self._send_to_charger(w, view, now)
                continue
            book.assign(rec, name, i, now)
            w.task, w.activity, w.target, w.worked = rec, TASK, None, True

    def _dist(self, src: int, goal: int) -> int:
        """Steps from ``src`` to ``goal`` along the goal's cached distance map (UNREACHABLE if none)."""
        return 0 if src == goal else int(self.cache.table[self.cache.slot(goal), src])

    def _affordable(self, w: _Work, cell: int, rec: TaskRecord) -> bool:
        """Whether ``w`` can do ``rec`` from ``cell`` and still reach a charger with the reserve."""
        b = self.battery
        if b is None or w.battery < 0 or not self.chargers:
            return True
        route = [cell, *rec.task.errands[rec.task.next_errand:]]
        steps = sum(self._dist(a, c) for a, c in zip(route, route[1:], strict=False))
        back = min(self._dist(route[-1], c) for c in self.chargers)
        steps += back
        if steps >= UNREACHABLE:
            return False
        metres = steps * self.cell_m
        need = b.energy_wh(metres, steps * self.book.step_s) + RESERVE * b.capacity_wh
        return need <= w.battery * b.capacity_wh

    def _goals(self, view: dict[str, RobotView], now: float) -> dict[str, int]:
        out: dict[str, int] = {}
        held = {n: w.sent for n, w in self.robots.items() if w.sent is not None}
        held.update({n: v.goal for n, v in view.items() if v.goal is not None and n not in held})
        wants: dict[str, int | None] = {}
        for name, w in self.robots.items():
            v = view.get(name)
            if v is None or v.cell is None or w.activity in (OPERATOR, UNKNOWN):
                continue
            ready = w.worked or (self.park_idle and w.since is not None and now - w.since >= PARK_AFTER_S)
            if w.activity == IDLE and ready and self.parking and v.cell not in self.parking:
                c = self._nearest_free(v.cell, self.parking, view, w)
                if c is not None:
                    w.activity, w.target = PARKING, c
            if w.activity == TASK and w.task is not None:
                wants[name] = w.task.task.goal
            elif w.activity in (TO_CHARGER, CHARGING, PARKING):
                wants[name] = w.target
            else:
                wants[name] = None
        owner = self._owners(wants, held, view)
        for name, want in wants.items():
            w, v = self.robots[name], view[name]
            if w.replan:                    # a stall's re-plan: drop the goal now, set it again at the next step
                w.replan, w.sent = False, None
                if v.goal is not None:
                    out[name] = -1
                    held.pop(name, None)
                    continue
            if want is not None and owner[want] != name:
                # another robot heads there, or is nearer: wait beside it (off the other places) until it is free
                spot = self._waiting_spot(want, v.cell, w, held, view)
                w.spot = spot
                if spot is None or spot == w.sent:
                    continue
                want = spot
            else:
                w.spot = None
            if want != w.sent:
                if want is None and w.sent is None:
                    continue
                out[name] = -1 if want is None else int(want)
                w.sent = want
                if want is None:
                    held.pop(name, None)
                else:
                    held[name] = want
        return out

    def _owners(self, wants: dict[str, int | None], held: dict[str, int],
                view: dict[str, RobotView]) -> dict[int, str]:
        """Which robot may head to each wanted cell now (the planner takes one robot per goal):
        a robot that holds it and is not the dispatcher's (an operator's) keeps it; else the
        robot nearest to it, where the one it was sent to keeps it unless another is
        ``SWAP_STEPS`` steps nearer (so a robot waiting beside a station goes in before one
        still on its way to it)."""
        owner: dict[int, str] = {}
        for n, g in held.items():
            if n not in wants and g is not None:
                owner[g] = n
        by_cell: dict[int, list[str]] = {}
        for n, g in wants.items():
            if g is not None and g not in owner:
                by_cell.setdefault(g, []).append(n)
        for g, names in by_cell.items():
            if len(names) == 1:
                owner[g] = names[0]
                continue
            dist = {n: self._dist(view[n].cell, g) for n in names}
            best = min(names, key=lambda n: (dist[n], self.robots[n].sent != g, n))
            cur = next((n for n in names if self.robots[n].sent == g), None)
            owner[g] = cur if cur is not None and dist[best] + SWAP_STEPS > dist[cur] else best
        return owner

    def _waiting_spot(self, cell: int, here: int, me: _Work, held: dict[str, int],
                      view: dict[str, RobotView]) -> int | None:
        """Where ``me`` waits for ``cell``: the spot it has while that stays free, else the free
        cell nearest to ``cell`` (within ``WAIT_RADIUS`` steps) that is no place, no other
        robot's goal and where no other robot stands; ``here`` (where ``me`` stands) wins ties.
        None when there is none."""
        taken = {g for n, g in held.items() if n != me.name} | self.places
        # a robot without a goal stays where it stands; one passing over the spot does not take it
        taken |= {v.cell for n, v in view.items() if n != me.name and v.cell is not None and v.goal is None}
        if me.spot is not None and me.spot not in taken and me.spot in self.near(cell):
            return me.spot
        taken |= {v.cell for n, v in view.items() if n != me.name and v.cell is not None}
        row = self.cache.table[self.cache.slot(cell)]
        best, bd = None, (WAIT_RADIUS + 1, 1)
        for c in self.near(cell):
            d = (int(row[c]), c != here)
            if c not in taken and d < bd:
                best, bd = c, d
        return best

    def near(self, cell: int) -> list[int]:
        """Cells within ``WAIT_RADIUS`` steps of ``cell`` (itself excluded), cached."""
        got = self._near.get(cell)
        if got is None:
            row = self.cache.table[self.cache.slot(cell)]
            got = self._near[cell] = [int(c) for c in np.flatnonzero((row > 0) & (row <= WAIT_RADIUS))]
        return got

    # -- views ------------------------------------------------------------------------------------------
    def stalled_s(self, name: str, now: float) -> float:
        """Fleet s robot ``name`` has held work without progress, once that is :data:`STALL_S` or more
        (it is stalled); else 0."""
        w = self.robots[name]
        return now - w.stall_start if w.alert else 0.0

    def robot_messages(self, now: float) -> list[dict]:
        """``fleet/RobotTask`` entries (JSON form), by robot name."""
        out = []
        for name in sorted(self.robots):
            w = self.robots[name]
            out.append({"robot": name, "task": w.task.id if w.task else "", "activity": w.activity,
                        "battery_pct": round(w.battery * 100, 2) if w.battery >= 0 else -1.0,
                        "busy_s": w.busy_s, "since_s": (now - w.since) if w.since is not None else 0.0,
                        "charges": w.charges, "tasks_done": w.tasks_done,
                        "stalled_s": self.stalled_s(name, now), "stalls": w.stalls, "alert": w.alert})
        return out
