"""The fleet planner: all robots planned together on the cell grid, re-planned when cells
are blocked or robots stray, and their moves cleared in plan order.

What the seed paper does (section IV-A): Dijkstra on the grid of cells, one robot at a
time; a blocked cell triggers re-planning and a ``cancelGoal`` for the robots whose paths
crossed it. What this adds:

* **collision-free multi-robot plans** (:mod:`.paths`), by prioritized planning
  (:mod:`.prioritized`);
* **re-planning**: after a block only the robots whose remaining paths cross the cell are
  re-planned (with the robots standing on their goals, which may yield to them), around the
  others' kept remaining paths. Robots run ahead of or behind the plan's timing (the order
  of execution holds, the steps drift), so kept paths, each taken from where its robot
  stands, may no longer fit together in plan time: then everybody is re-planned while that
  is cheap (:data:`FULL_REPLAN_SHARE`), else a few of those robots (a greedy cover
  of the conflicts, :func:`_conflict_cover`) are re-planned too, not the whole fleet, and
  so are kept robots whose paths cross a re-planned robot that has to hold its cell (up to
  :data:`MAX_WIDENINGS` times); if the plan still does not fit, everybody is re-planned.
  A robot already cleared into its next cell keeps that move (it may be driving), so
  re-plans never pull a cell from under a moving robot;
* **execution in plan order under delays** (:mod:`.adg`); robots that order holds for a robot
  still far from the shared cell (the order went stale) are found by :meth:`FleetPlanner.stale_waits`
  and re-planned by :meth:`FleetPlanner.replan` to go first where they can;
* **clear failure reasons**: a goal that is not a free cell, blocked, walled off, taken by
  another robot, occupied by a parked robot, or not plannable.

Sans-I/O: plain classes, no sockets, no asyncio. Units: cells are integers
``r * cols + c``; steps are plan time steps (one cell move or one wait).
"""
from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from .adg import ActionDependencyGraph
from .dijkstra import DistanceTable
from .graph import GridGraph
from .paths import check_conflicts, compress
from . import sipp_kernel
from .prioritized import Fleet, ReplanAbandoned, SearchLimits, plan_prioritized

__all__ = ["PlannerError", "UnreachableGoal", "PlanResult", "FleetPlanner"]

#: Times a partial re-plan may take in the kept robots whose paths its result still crosses
#: (a robot of the re-planned set that cannot move holds its cell) before everybody is re-planned.
MAX_WIDENINGS = 2

#: Kept paths that drifted apart are resolved by re-planning everybody while the last full
#: re-plan took at most this share of the re-plan bound (it re-orders every robot's priority
#: and drops waits for robots that no longer come: 110 against 99 tasks over five task
#: streams at 20 robots), by re-planning a cover of the drifted robots otherwise (26 against
#: 141 ms per re-plan at 100 robots, the same tasks done).
FULL_REPLAN_SHARE = 0.25


class PlannerError(ValueError):
    """A request the planner cannot take: unknown robot, cell outside the grid."""


class UnreachableGoal(PlannerError):
    """Raised by ``FleetPlanner.set_goal(..., strict=True)``: ``robot``'s ``goal`` cannot be
    reached, ``reason`` says why."""

    def __init__(self, robot: str, goal: int, reason: str):
        super().__init__(f"robot {robot}: goal cell {goal} unreachable: {reason}")
        self.robot, self.goal, self.reason = robot, goal, reason



@dataclass
class PlanResult:
    """Outcome of a (re)plan.

    paths: every robot's current path (index 0 = its cell when planned).
    changed: robots whose cell sequence changed (send them the new path).
    unreachable: robot -> reason, for robots that are not moving towards their goal.
    cancelled: robots whose old path crossed a newly blocked cell (``cancelGoal``).
    full: True when all robots were re-planned (False: only some, others kept).
    elapsed_s: planning time in seconds.
    clearance: robot -> path index it may move up to now.
    deferred: robots the re-plan did not reach within its wall-time bound (they keep their
        current plan or hold their cell; the next re-plan serves them first).
    abandoned: True when the bounded re-plan changed nothing (every robot kept its plan).
    """

    paths: dict[str, list[int]]
    changed: set[str] = field(default_factory=set)
    unreachable: dict[str, str] = field(default_factory=dict)
    cancelled: set[str] = field(default_factory=set)
    full: bool = True
    elapsed_s: float = 0.0
    clearance: dict[str, int] = field(default_factory=dict)
    deferred: set[str] = field(default_factory=set)
    abandoned: bool = False

    @property
    def ok(self) -> bool:
        """True when every robot with a goal got a path to it."""
        return not self.unreachable


def _conflict_cover(paths: dict[str, list[int]]) -> set[str]:
    """Robots whose removal leaves ``paths`` free of conflicts (:func:`.paths.check_conflicts`,
    starts ignored): greedily the robot in the most conflicts first (ties by name), checked
    again until none is left. Empty when ``paths`` fit together."""
    out: set[str] = set()
    rest = dict(paths)
    while True:
        conflicts = check_conflicts(rest, ignore_start=True)
        if not conflicts:
            return out
        while conflicts:
            count: dict[str, int] = {}
            for c in conflicts:
                for r in c.robots:
                    count[r] = count.get(r, 0) + 1
            r = min(count, key=lambda robot: (-count[robot], robot))
            out.add(r)
            del rest[r]
            conflicts = [c for c in conflicts if r not in c.robots]


class FleetPlanner:
    """Plans all robots together on a CellGrid (or any GridGraph), and clears their moves.

    Typical use (the global planner node is a thin shell around this)::

        fp = FleetPlanner(grid)
        fp.set_position("Robot1", 9); fp.set_position("Robot2", 14)
        fp.set_goal("Robot1", 54)                  # -> PlanResult, paths to publish
        fp.block(26)                               # -> robots to cancelGoal; re-planned
        fp.advance("Robot1", 10)                   # robot reports its cell -> new clearances
        fp.clearance("Robot1")                     # it may drive along paths[r][:k+1]

    State (read-only from outside): ``positions`` robot -> cell; ``goals``
    robot -> cell or None; ``paths`` robot -> list of cells (space-time: one
    cell per step, waits repeat a cell; index 0 = the robot's cell at the last
    re-plan); ``blocked`` cell -> source; ``unreachable`` robot -> reason;
    ``replans`` robot -> number of times its path changed; ``last_result``;
    ``deferred``: robots the last re-plan did not reach within its bound (served first by the
    next one, :meth:`serve_deferred`); ``bounded_replans``, ``abandoned_replans``,
    ``deferred_robots_total``: re-plans that passed the bound, those of them that kept every
    plan, robots deferred, since the start.

    A robot without a goal, or whose goal cannot be reached, is parked: it
    stays in its cell and other robots plan around it.

    Args:
        grid: a :class:`rce_fleet.maps.grid.CellGrid` or :class:`GridGraph`.
        max_restarts, time_budget_s (s), expansion_factor, min_expansions, weight: how hard
            a (re)plan tries, see :class:`.prioritized.SearchLimits`.
        replan_bound_s: hard wall-time bound of one re-plan, s (default ``math.inf``: none;
            the global planner node's is :data:`.prioritized.REPLAN_BOUND_S`). A re-plan
            after a cell is blocked, or with a robot found off its plan or new, is not bounded:
            those robots are in no safe plan yet;
            see :mod:`.prioritized`. Raises ValueError unless > 0.
    """

    def __init__(self, grid, *, max_restarts: int = SearchLimits.max_restarts,
                 time_budget_s: float = SearchLimits.time_budget_s,
                 expansion_factor: int = SearchLimits.expansion_factor,
                 min_expansions: int = SearchLimits.min_expansions, weight: float = SearchLimits.weight,
                 replan_bound_s: float = SearchLimits.bound_s):
        self.graph = grid if isinstance(grid, GridGraph) else GridGraph.from_cellgrid(grid)
        self.grid = grid
        if not replan_bound_s > 0:
            raise ValueError(f"replan_bound_s must be > 0 s (math.inf: no bound), got {replan_bound_s!r}")
        self.limits = SearchLimits(max_restarts=max_restarts, time_budget_s=time_budget_s, bound_s=replan_bound_s,
                                   expansion_factor=expansion_factor, min_expansions=min_expansions, weight=weight)
        self.positions: dict[str, int] = {}
        self.goals: dict[str, int | None] = {}
        self._goal_seq: dict[str, int] = {}
        self._seq = 0
        self.paths: dict[str, list[int]] = {}
        self.blocked: dict[int, str] = {}
        self.unreachable: dict[str, str] = {}
        self.replans: dict[str, int] = {}
        self.last_result: PlanResult | None = None
        self._adg = ActionDependencyGraph({})
        self._dirty: set[str] = set()
        self._distances = DistanceTable(self.graph)
        sipp_kernel.warm_up()      # compile or load the search now, not in the first re-plan
        self.deferred: set[str] = set()
        self._full_s = 0.0             # wall time of the last full re-plan, s
        self.bounded_replans = 0
        self.abandoned_replans = 0
        self.deferred_robots_total = 0

    # -- validation ---------------------------------------------------------
    def _check_cell(self, cell: int, what: str = "cell") -> int:
        if isinstance(cell, bool) or not isinstance(cell, (int, np.integer)):
            raise PlannerError(f"{what} must be an integer cell number, got {cell!r}")
        cell = int(cell)
        if not 0 <= cell < self.graph.n_cells:
            raise PlannerError(f"{what} {cell} is outside the {self.graph.rows}x{self.graph.cols} grid "
                               f"(cells 0..{self.graph.n_cells - 1})")
        return cell

    def _check_robot(self, robot: str) -> None:
        if robot not in self.positions:
            raise PlannerError(f"unknown robot {robot!r}: set_position first")

    # -- distances -------------------------------------------------------------
    def distance(self, start: int, goal: int) -> float:
        """Steps of the shortest path from ``start`` to ``goal`` ignoring other robots (inf if none)."""
        return self._distances.distance(start, goal, self.blocked)

    def _plan_round(self, todo: list[str], fixed: dict[str, list[int]], commit: dict[str, int | None],
                    t_start: float, current: dict[str, list[int]], limits: SearchLimits
                    ) -> tuple[dict[str, list[int]], dict[str, str], set[str]]:
        """Plan ``todo`` around the ``fixed`` paths (:func:`.prioritized.plan_prioritized`)."""
        fleet = Fleet(self.graph, self._distances, self.positions, self.goals, self._goal_seq, self.blocked,
                      self.unreachable)
        return plan_prioritized(fleet, limits, todo, fixed, commit, t_start, current, frozenset(self.deferred))

    # -- robots ---------------------------------------------------------------
    def set_position(self, robot: str, cell: int) -> None:
        """Register ``robot`` in ``cell``, or update its cell (e.g. after re-localisation).

        On its planned path (current or a cleared cell) this is :meth:`advance`.
        A new robot, or one found off its plan, is re-planned at once (others
        whose paths now run into it too); the outcome is in ``last_result``
        (publish the paths of ``last_result.changed``).
        Raises PlannerError for a cell outside the grid.
        """
        cell = self._check_cell(cell)
        if robot in self.positions and robot in self._adg.visits and robot not in self._dirty:
            if self._adg.locate(robot, cell) is not None:
                self.advance(robot, cell)
                return
        if robot not in self.positions:
            self.goals.setdefault(robot, None)
            self.replans.setdefault(robot, 0)
        self.positions[robot] = cell
        self._dirty.add(robot)
        self._replan(self._dirty | set(self.unreachable))

    def remove_robot(self, robot: str) -> None:
        """Forget ``robot`` (disconnected). Others keep their paths; call :meth:`plan` to use the freed cells."""
        self._check_robot(robot)
        for d in (self.positions, self.goals, self._goal_seq, self.paths, self.unreachable, self.replans):
            d.pop(robot, None)
        self._dirty.discard(robot)
        progress = dict(self._adg.progress)
        self._adg = ActionDependencyGraph(self.paths)
        for r in self._adg.progress:
            self._adg.progress[r] = progress.get(r, 0)

    def set_goal(self, robot: str, cell: int, *, strict: bool = False) -> PlanResult:
        """Give ``robot`` a goal cell and re-plan it (others keep their paths when possible).

        Returns the PlanResult; an unreachable goal is reported in
        ``result.unreachable[robot]`` (and ``self.unreachable``) with the reason,
        and the robot is parked. With ``strict`` it raises UnreachableGoal
        instead (the goal stays set; it is retried on later re-plans).
        Raises PlannerError for an unknown robot or a cell outside the grid.
        """
        self._check_robot(robot)
        cell = self._check_cell(cell, "goal cell")
        self.goals[robot] = cell
        self._seq += 1
        self._goal_seq[robot] = self._seq
        result = self._replan({robot} | self._dirty | set(self.unreachable))
        if strict and robot in result.unreachable:
            raise UnreachableGoal(robot, cell, result.unreachable[robot])
        return result

    def set_goals(self, goals: Mapping[str, int], *, strict: bool = False) -> PlanResult:
        """Set several goals at once and plan them together (one re-plan instead of many).

        Earlier entries win when two robots want the same cell. Errors as :meth:`set_goal`;
        with ``strict`` raises UnreachableGoal for the first robot that cannot reach its goal.
        """
        checked = {}
        for robot, cell in goals.items():
            self._check_robot(robot)
            checked[robot] = self._check_cell(cell, "goal cell")
        for robot, cell in checked.items():
            self.goals[robot] = cell
            self._seq += 1
            self._goal_seq[robot] = self._seq
        result = self._replan(set(checked) | self._dirty | set(self.unreachable))
        if strict:
            for robot in checked:
                if robot in result.unreachable:
                    raise UnreachableGoal(robot, checked[robot], result.unreachable[robot])
        return result

    def clear_goal(self, robot: str) -> PlanResult:
        """Drop ``robot``'s goal: it parks in its current cell."""
        self._check_robot(robot)
        self.goals[robot] = None
        self._goal_seq.pop(robot, None)
        return self._replan({robot} | self._dirty)

    # -- cells ------------------------------------------------------------------
    def block(self, cell: int, source: str = "operator") -> set[str]:
        """Block ``cell`` (operator, or an obstacle a robot's lidar saw) and re-plan.

        Returns the robots whose remaining paths crossed the cell (or ended in
        it): they must get ``cancelGoal`` and their new path
        (``self.paths``; all changes are in ``self.last_result``). A robot
        standing in the blocked cell may leave it; nobody enters it.
        Raises PlannerError for a cell outside the grid.
        """
        cell = self._check_cell(cell)
        if cell in self.blocked:
            self.blocked[cell] = source
            return set()
        self.blocked[cell] = source
        hit = {r for r in self.paths if r not in self._dirty and cell in self._adg.future_cells(r)}
        hit |= {r for r, g in self.goals.items() if g == cell and r in self.positions and r not in self.unreachable
                and self.positions[r] != cell}
        result = self._replan(hit | self._dirty | set(self.unreachable), bounded=False)
        result.cancelled = set(hit)
        return set(hit)

    def unblock(self, cell: int) -> PlanResult:
        """Unblock ``cell`` and re-plan the robots that were parked as unreachable."""
        cell = self._check_cell(cell)
        self.blocked.pop(cell, None)
        return self._replan(set(self.unreachable) | self._dirty)

    # -- planning ---------------------------------------------------------------
    def plan(self) -> dict[str, list[int]]:
        """Re-plan every robot from its current cell; returns robot -> path (all robots)."""
        self._replan(set(self.positions), full=True)
        return {r: list(p) for r, p in self.paths.items()}

    def _rebased(self, robot: str) -> list[int]:
        """The robot's remaining path from its current visit (dropping waits already cleared)."""
        adg = self._adg
        k = adg.progress[robot]
        c, a, lv = adg.visits[robot][k]
        start = lv if adg.cleared_visit(robot) > k else a
        return list(self.paths[robot][start:])

    def _commitment(self, robot: str) -> int | None:
        """The next cell ``robot`` has been cleared into (it may be driving there), if any."""
        adg = self._adg
        if robot not in adg.visits or robot in self._dirty:
            return None
        k = adg.progress[robot]
        if adg.cleared_visit(robot) > k:
            nxt = adg.visits[robot][k + 1][0]
            if nxt not in self.blocked:
                return nxt
        return None

    def held(self, robot: str) -> bool:
        """True when ``robot`` has a next cell on its plan that the dependency graph does not
        clear yet (a robot planned there before it has not left it)."""
        adg = self._adg
        if robot not in adg.visits or robot in self._dirty:
            return False
        k = adg.progress[robot]
        return k + 1 < len(adg.visits[robot]) and adg.cleared_visit(robot) == k

    def stale_waits(self, min_gap: int = 2) -> set[str]:
        """Robots the dependency graph holds for a robot planned into their next cell before
        them that is still at least ``min_gap`` cells (visits) short of it: the plan's order
        there went stale as robots ran ahead of or behind its timing (:meth:`replan` them)."""
        adg = self._adg
        out = set()
        for r in adg.visits:
            if not self.held(r):
                continue
            p = adg.pred[r][adg.progress[r] + 1]
            if p is not None and p[1] - adg.progress[p[0]] >= min_gap:
                out.add(r)
        return out

    def replan(self, robots: set[str]) -> PlanResult:
        """Re-plan ``robots`` from where they stand around the others' kept paths (drift handled
        as for any re-plan: module docstring), under the re-plan bound. Unknown names are ignored."""
        return self._replan({r for r in robots if r in self.positions} | self._dirty | set(self.unreachable))

    def serve_deferred(self) -> PlanResult | None:
        """Re-plan the robots the last re-plan deferred (its wall-time bound passed before it
        reached them), first in the order; None when there are none."""
        if not self.deferred:
            return None
        return self._replan(set(self.deferred) | self._dirty | set(self.unreachable))

    def _replan(self, subset: set[str], full: bool = False, bounded: bool = True) -> PlanResult:
        t_start = time.perf_counter()
        # a robot off its plan (or new) is in nobody's plan: it must be planned now, as must the
        # robots whose paths cross a newly blocked cell (``bounded`` False)
        limits = self.limits if bounded and not self._dirty else replace(self.limits, bound_s=math.inf)
        subset = {r for r in subset | self.deferred if r in self.positions}
        planned = {r for r in self.positions if r in self.paths and r in self._adg.visits and r not in self._dirty}
        old = {r: compress(self._rebased(r)) if r in planned else None for r in self.positions}
        commit = {r: self._commitment(r) for r in self.positions}
        # current cells
        for r in planned:
            self.positions[r] = self._adg.cell(r)
        if subset:      # robots standing on their goal are planned again too: they may yield (.prioritized)
            subset |= {r for r in self.positions if self.goals.get(r) == self.positions[r]
                       and r not in self.unreachable and len(set(self._rebased(r) if r in planned else [0, 1])) == 1}
        # what a robot the bound leaves unreached keeps: the rest of its plan, unless it enters a blocked cell
        current = {r: p for r in planned if not set((p := self._rebased(r))[1:]) & self.blocked.keys()}
        result = None
        try:
            if not full and len(subset) < len(self.positions):
                fixed = {r: self._rebased(r) for r in planned if r not in subset}
                subset |= set(self.positions) - set(fixed)
                if self._full_s <= FULL_REPLAN_SHARE * limits.bound_s and check_conflicts(fixed, ignore_start=True):
                    drifted = set(fixed)          # a full re-plan is cheap enough: take it
                else:
                    drifted = _conflict_cover(fixed)
                subset |= drifted
                for r in drifted:
                    del fixed[r]
                for _ in range(MAX_WIDENINGS + 1):
                    if len(subset) >= len(self.positions):
                        break
                    paths, unreachable, deferred = self._plan_round(sorted(subset), fixed, commit, t_start, current,
                                                                    limits)
                    allp = {**fixed, **paths}
                    hit = {r for c in check_conflicts(allp, ignore_start=True) for r in c.robots}
                    if not hit:
                        result = (allp, unreachable, False, deferred)
                        break
                    if deferred:        # no time left to widen: every robot keeps its plan
                        raise ReplanAbandoned(sorted(subset))
                    # a robot of the subset that cannot move (no goal, or no path) holds its cell,
                    # which kept paths may cross: those robots are re-planned with the subset
                    if not hit & set(fixed):
                        break
                    subset |= hit
                    fixed = {r: p for r, p in fixed.items() if r not in hit}
            if result is None:
                paths, unreachable, deferred = self._plan_round(sorted(self.positions), {}, commit, t_start, current,
                                                                limits)
                if deferred and check_conflicts(paths, ignore_start=True):
                    raise ReplanAbandoned(sorted(self.positions))
                result = (paths, unreachable, True, deferred)
                subset = set(self.positions)
        except ReplanAbandoned as e:
            return self._abandon(e.robots, t_start)
        allp, unreachable, was_full, deferred = result
        if was_full:
            self._full_s = time.perf_counter() - t_start
        for r in subset - deferred:
            self.unreachable.pop(r, None)
        self.unreachable.update(unreachable)
        if deferred:
            self.bounded_replans += 1
            self.deferred_robots_total += len(deferred)
        self.deferred = set(deferred)
        changed = set()
        for r, p in allp.items():
            if old.get(r) != compress(p):
                changed.add(r)
                self.replans[r] = self.replans.get(r, 0) + 1
        self.paths = allp
        self._dirty.clear()
        self._adg = ActionDependencyGraph(self.paths)
        for r in self.paths:
            self.positions[r] = self.paths[r][0]
        res = PlanResult(paths={r: list(p) for r, p in allp.items()}, changed=changed,
                         unreachable={r: self.unreachable[r] for r in self.unreachable},
                         full=was_full, elapsed_s=time.perf_counter() - t_start,
                         clearance={r: self._adg.clearance(r) for r in allp}, deferred=set(deferred))
        self.last_result = res
        return res

    def _abandon(self, robots: list[str], t_start: float) -> PlanResult:
        """A bounded re-plan that changes nothing: every robot keeps its plan (and the
        execution its progress); ``robots`` are deferred to the next re-plan."""
        self.bounded_replans += 1
        self.abandoned_replans += 1
        self.deferred = set(robots) & set(self.positions)
        self.deferred_robots_total += len(self.deferred)
        res = PlanResult(paths={r: list(p) for r, p in self.paths.items()}, changed=set(),
                         unreachable=dict(self.unreachable), full=False, elapsed_s=time.perf_counter() - t_start,
                         clearance={r: self._adg.clearance(r) for r in self._adg.visits}, deferred=set(self.deferred),
                         abandoned=True)
        self.last_result = res
        return res

    # -- execution ------------------------------------------------------------------
    def advance(self, robot: str, cell: int) -> dict[str, int]:
        """``robot`` reports it is now in ``cell``.

        On its path (current or a cleared later cell) its progress moves on;
        other robots waiting for it may get more clearance. Elsewhere (it left
        its plan, or moved without clearance) it is re-planned from ``cell``
        (``self.last_result`` holds that re-plan). A report of the previous
        cell is ignored (pose jitter at a cell border; filter it in the node).
        Returns robot -> new clearance for every robot whose clearance changed.
        Raises PlannerError for an unknown robot or a cell outside the grid.
        """
        self._check_robot(robot)
        cell = self._check_cell(cell)
        adg = self._adg
        if robot not in adg.visits or robot in self._dirty:
            self.positions[robot] = cell
            self._dirty.add(robot)
            return {}
        before = {r: adg.clearance(r) for r in adg.visits}
        k = adg.locate(robot, cell)
        if k is None:
            prog = adg.progress[robot]
            if prog > 0 and adg.visits[robot][prog - 1][0] == cell:
                return {}
            self.positions[robot] = cell
            self._dirty.add(robot)
            res = self._replan({robot} | set(self.unreachable))
            return {r: c for r, c in res.clearance.items() if before.get(r) != c or r in res.changed}
        adg.progress[robot] = k
        self.positions[robot] = cell
        after = {r: adg.clearance(r) for r in adg.visits}
        return {r: c for r, c in after.items() if before.get(r) != c}

    def clearance(self, robot: str) -> int:
        """Index into ``paths[robot]`` up to which the robot may move now (its current index if it must wait)."""
        self._check_robot(robot)
        if robot not in self._adg.visits:
            return 0
        return self._adg.clearance(robot)

    def progress(self, robot: str) -> int:
        """Index into ``paths[robot]`` of the step at which the robot entered its current cell."""
        self._check_robot(robot)
        if robot not in self._adg.visits:
            return 0
        return self._adg.position_index(robot)

    def cleared_cells(self, robot: str) -> list[int]:
        """Distinct cells the robot may drive through now, after its current one (the goals to send)."""
        p = self.paths.get(robot)
        if not p:
            return []
        return compress(p[self.progress(robot):self.clearance(robot) + 1])[1:]

