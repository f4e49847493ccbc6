"""One (re)plan of a set of robots: prioritized planning with priority bumping (Erdmann &
Lozano-Perez 1987, "On multiple moving objects", Algorithmica 2; Silver 2005,
"Cooperative Pathfinding", AIIDE).

Robots are planned one after another, each by SIPP (:mod:`.sipp`) around the reservations
(:mod:`.reservations`) of the robots planned before it, with the true-distance heuristic
(:mod:`.dijkstra`). Priority: shorter trips first (they park early; long trips route
around them, instead of short trips waiting for a long one to pass their goal). Robots
standing on their goal come first (they stay put; the others route around them) until a
robot cannot be planned even with top priority: then they go last, so the robots planned before may drive through
a standing robot's cell and its own search steps it aside and back in time (it yields,
planned with them) instead of being a wall; one that cannot is bumped to the front and
stays put, as a parked robot would. A robot
that cannot be planned is moved to the front of the order and the plan restarted
(priority bumping); when restarts or the time budget run out, robots that still cannot be
planned are parked where they are, with the reason, so nobody waits for ever on a goal
that will not come.

Goals that cannot be planned at all are refused first, with the reason: not a free cell,
blocked, walled off, the goal of a robot that asked earlier, or occupied by a parked robot.

A re-plan has a hard wall-time bound (:attr:`SearchLimits.bound_s`), looked at before each
robot's search (one search is bounded by its expansions: a few ms compiled). When it has
passed, the robots planned so far keep their new paths and
the robots not reached keep their current plan (the rest of the path they drive) or, without
one or when it no longer fits, hold their cell (after the move they are committed to); a
robot planned this round that would run into a holding robot keeps its current plan or holds
in turn. They are *deferred*: the caller plans them again in the next round. When no
collision-free combination is left that way, the round is *abandoned*
(:class:`ReplanAbandoned`): every robot keeps the plan it has.
"""
from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass

from .dijkstra import DistanceTable, shortest_path
from .graph import GridGraph
from .paths import compress
from .reservations import Reservations
from .sipp import safe_interval_astar

__all__ = ["SearchLimits", "Fleet", "ReplanAbandoned", "plan_prioritized", "REPLAN_BOUND_S", "TIME_BUDGET_S"]

INF = math.inf

#: Wall-clock budget, s, of one (re)plan for priority restarts. The attempt under way always
#: finishes (a plan always ends); robots still failing when it is spent are parked, with the
#: reason, and retried on the next re-plan.
TIME_BUDGET_S = 2.0

#: The global planner node's hard wall-time bound, s, of one (re)plan (module docstring): past it
#: the robots not reached are deferred to the next round. The node is single-threaded, so this
#: bounds how long it answers nothing (robot poses, operators' goals, tasks).
REPLAN_BOUND_S = 0.5


class ReplanAbandoned(Exception):
    """A bounded re-plan found no collision-free way to keep the robots it did not reach on
    their current plans: every robot keeps the plan it has (``robots``: the ones it was to plan)."""

    def __init__(self, robots: list[str]):
        super().__init__(f"re-plan of {len(robots)} robot(s) passed its wall-time bound and was abandoned")
        self.robots = robots


class _Bounded(Exception):
    """Internal: the bound passed before ``unreached[0]`` of an attempt was planned."""

    def __init__(self, res: Reservations, got: dict[str, list[int]], unreached: list[str]):
        super().__init__("re-plan bound passed")
        self.res, self.got, self.unreached = res, got, unreached


@dataclass(frozen=True)
class SearchLimits:
    """How hard one (re)plan tries.

    max_restarts: priority-order restarts before robots that still fail are parked.
    time_budget_s: wall-clock budget, s, per (re)plan for restarts (:data:`TIME_BUDGET_S`).
    bound_s: hard wall-time bound, s, per (re)plan (default none, ``math.inf``; the global
        planner node uses :data:`REPLAN_BOUND_S`): past it the robots not reached are
        deferred (module docstring).
    expansion_factor, min_expansions: SIPP budget per robot,
        ``max(min_expansions, expansion_factor * (distance + 1))`` expansions.
    weight: weighted A* factor (1 = each robot's earliest arrival given the robots before
        it; 1.05: much faster, arrivals within 5 %).
    """

    max_restarts: int = 20
    time_budget_s: float = TIME_BUDGET_S
    bound_s: float = INF
    expansion_factor: int = 60
    min_expansions: int = 4000
    weight: float = 1.05

    def expansions(self, dist: float) -> int:
        """SIPP expansions allowed for a trip of ``dist`` steps (inf: the minimum)."""
        d = 0 if dist == INF else int(dist)
        return max(self.min_expansions, self.expansion_factor * (d + 1))


@dataclass(frozen=True)
class Fleet:
    """What a planning round reads of the planner's state (it changes none of it).

    positions: robot -> cell; goals: robot -> cell or None; goal_seq: robot -> when its
    goal was given (an earlier goal wins a cell two robots want); blocked: cell -> source;
    unreachable: robot -> reason, from the previous plan (those robots are parked).
    """

    graph: GridGraph
    distances: DistanceTable
    positions: Mapping[str, int]
    goals: Mapping[str, int | None]
    goal_seq: Mapping[str, int]
    blocked: Mapping[int, str]
    unreachable: Mapping[str, str]

    def distance(self, start: int, goal: int) -> float:
        """Steps from ``start`` to ``goal`` around the blocked cells, other robots ignored."""
        return self.distances.distance(start, goal, self.blocked)

    def distance_row(self, goal: int) -> list[float]:
        """Steps from every cell to ``goal`` around the blocked cells."""
        return self.distances.row(goal, self.blocked)


def plan_prioritized(fleet: Fleet, limits: SearchLimits, todo: list[str], fixed: Mapping[str, list[int]],
                     commit: Mapping[str, int | None], t_start: float, current: Mapping[str, list[int]] | None = None,
                     first: frozenset[str] = frozenset()
                     ) -> tuple[dict[str, list[int]], dict[str, str], set[str]]:
    """Plan the ``todo`` robots from their positions around the ``fixed`` robots' paths.

    ``commit[robot]``: a cell the robot has been cleared into and may be driving to (its
    path keeps that move when it can). ``t_start``: ``time.perf_counter()`` when the
    re-plan began (for ``limits.time_budget_s`` and ``limits.bound_s``). ``current[robot]``:
    the rest of a ``todo`` robot's current plan from its cell, kept if the bound passes
    before it is reached. ``first``: robots deferred by the previous round, planned first.
    Returns (path of every ``todo`` robot, reason for each robot that is parked instead of
    moving to its goal, the robots deferred to the next round). Raises
    :class:`ReplanAbandoned` (module docstring).
    """
    return _Round(fleet, limits, todo, fixed, commit, t_start, current, first).run()


class _Round:
    """One call of :func:`plan_prioritized`."""

    def __init__(self, fleet: Fleet, limits: SearchLimits, todo: list[str], fixed: Mapping[str, list[int]],
                 commit: Mapping[str, int | None], t_start: float, current: Mapping[str, list[int]] | None,
                 first: frozenset[str]):
        self.f, self.limits = fleet, limits
        self.todo, self.fixed, self.commit, self.t_start = todo, fixed, commit, t_start
        self.current, self.first = current or {}, first
        self.deadline = t_start + limits.bound_s
        self.deferred: set[str] = set()
        self.owner_id = {r: i for i, r in enumerate(sorted(set(todo) | set(fixed)))}
        self.starts = {r: fleet.positions[r] for r in todo}
        self.reasons: dict[str, str] = {}
        self.attempts: dict[str, int] = {}

    def run(self) -> tuple[dict[str, list[int]], dict[str, str], set[str]]:
        """Refuse the goals that cannot be planned, park those robots, plan the others."""
        wanting = self._claim_goals()
        self._refuse_parked_goals(wanting)
        movers = [r for r in wanting if r not in self.reasons]
        parked = [r for r in self.todo if r not in movers]
        base = Reservations(self.f.graph.n_cells)
        for r, p in self.fixed.items():
            base.reserve(p, self.owner_id[r])
        paths: dict[str, list[int]] = {}
        for r in parked:
            base.reserve([self.starts[r]], self.owner_id[r])
            paths[r] = [self.starts[r]]
        got, failed_parked = self._search(movers, base)
        paths.update(got)
        for r in failed_parked:
            paths[r] = [self.starts[r]]
            self.reasons[r] = self._fail_reason(r, paths)
        return paths, self.reasons, self.deferred

    # -- goals that cannot be planned ----------------------------------------------
    def _static_reason(self, start: int, goal: int) -> str | None:
        """Why ``goal`` cannot be reached from ``start`` whatever the other robots do, or None."""
        f = self.f
        if not f.graph.is_free(goal):
            return f"goal cell {goal} is not a free cell of the map"
        if goal in f.blocked:
            return f"goal cell {goal} is blocked (by {f.blocked[goal]})"
        if goal != start and f.distance(start, goal) == INF:
            return (f"goal cell {goal} cannot be reached from cell {start}: walls or blocked cells "
                    f"({sorted(f.blocked) or 'none'}) separate them")
        return None

    def _claim_goals(self) -> list[str]:
        """The robots with a goal, in goal order; refuses the goals that cannot be reached
        and those another robot claimed first."""
        f = self.f
        goal_owner: dict[int, str] = {}
        for r in self.fixed:
            if f.goals.get(r) is not None and r not in f.unreachable:
                goal_owner[f.goals[r]] = r
        wanting = sorted((r for r in self.todo if f.goals.get(r) is not None),
                         key=lambda robot: f.goal_seq.get(robot, 0))
        f.distances.fill((f.goals[r] for r in wanting), f.blocked)
        for r in wanting:
            g = f.goals[r]
            why = self._static_reason(self.starts[r], g)
            if why is None and g in goal_owner:
                why = f"goal cell {g} is already the goal of robot {goal_owner[g]}"
            if why is not None:
                self.reasons[r] = why
            else:
                goal_owner[g] = r
        return wanting

    def _refuse_parked_goals(self, wanting: list[str]) -> None:
        """Refuse goals in which a robot is parked for good (it has no goal, or cannot move);
        a refused robot parks in turn, so repeat until nothing changes."""
        f = self.f
        parked_cells: dict[int, str] = {p[-1]: r for r, p in self.fixed.items()
                                        if len(compress(p)) == 1 and (f.goals.get(r) is None or r in f.unreachable)}
        changed = True
        while changed:
            changed = False
            for r in self.todo:
                if f.goals.get(r) is None or r in self.reasons:
                    parked_cells.setdefault(self.starts[r], r)
            for r in wanting:
                g = f.goals[r]
                if r not in self.reasons and g != self.starts[r] and g in parked_cells and parked_cells[g] != r:
                    o = parked_cells[g]
                    what = "has no goal" if f.goals.get(o) is None else "cannot move (its own goal is unreachable)"
                    self.reasons[r] = f"goal cell {g} is occupied by robot {o}, which is parked there ({what})"
                    changed = True

    # -- the search -------------------------------------------------------------------
    def _prefix(self, robot: str) -> list[int]:
        """The start of ``robot``'s path: its cell, and the cell it is committed to if it can keep it."""
        f, start = self.f, self.starts[robot]
        c = self.commit.get(robot)
        if c is not None and c != start and f.graph.is_free(c) and c not in f.blocked \
                and f.distance_row(f.goals[robot])[c] < INF:
            return [start, c]
        return [start]

    def _search(self, movers: list[str], base: Reservations) -> tuple[dict[str, list[int]], list[str]]:
        """Plan ``movers`` in priority order, bumping a robot that fails to the front and
        restarting. Returns (their paths, the robots parked because they still failed)."""
        prefix = {r: self._prefix(r) for r in movers}
        dist = {r: self.f.distance(self.starts[r], self.f.goals[r]) for r in movers}
        order = sorted(movers, key=lambda robot: (robot not in self.first, dist[robot], robot))
        standing = [r for r in order if dist[r] == 0]
        failed_parked: list[str] = []
        attempts = 0
        while True:
            order_front = order[0] if order else None
            try:
                got, failed = self._attempt(order, prefix, failed_parked, base)
            except _Bounded as b:
                return self._fall_back(b, prefix), failed_parked
            if failed is None:
                return got, failed_parked
            attempts += 1
            lim = self.limits
            out_of_budget = attempts > lim.max_restarts or time.perf_counter() - self.t_start > lim.time_budget_s
            if standing and dist[failed] > 0 and order_front == failed and not out_of_budget:
                # it fails even first: the standing robots yield (planned last, they step aside)
                order = [r for r in order if r not in standing] + standing
                standing = []
                continue
            order.remove(failed)
            if out_of_budget or order_front == failed:
                failed_parked.append(failed)      # fails even with top priority (or no budget left): park it
                self.attempts[failed] = attempts
            else:
                order.insert(0, failed)           # priority bumping: plan it first next time

    def _attempt(self, order: list[str], prefix: dict[str, list[int]], failed_parked: list[str],
                 base: Reservations) -> tuple[dict[str, list[int]], str | None]:
        """Plan ``order`` one after another; returns (the paths, the first robot that failed or None)."""
        owner_id = self.owner_id
        res = base.copy()
        for r in failed_parked:
            res.reserve([self.starts[r]], owner_id[r])
        for r in order:                      # nobody may run into a robot's start (or committed move)
            res.reserve(prefix[r], owner_id[r], park=False)
        got: dict[str, list[int]] = {}
        for i, r in enumerate(order):
            if time.perf_counter() > self.deadline:
                raise _Bounded(res, got, order[i:])
            res.release(prefix[r], owner_id[r])
            p = self._plan_one(r, prefix[r], res)
            if p is None and len(prefix[r]) > 1:     # cannot continue the committed move: plan from the cell
                p = self._plan_one(r, prefix[r][:1], res)
            if p is None:
                return got, r
            res.reserve(p, owner_id[r])
            got[r] = p
        return got, None

    def _fall_back(self, b: _Bounded, prefix: dict[str, list[int]]) -> dict[str, list[int]]:
        """The bound passed (module docstring): the robots not reached keep their current plan
        or hold their cell, robots planned this round in their way too; all of them are
        deferred. Returns the paths of the robots that were being planned. Raises
        ReplanAbandoned when a holding robot would collide with a robot that is not being planned."""
        res, got, oid = b.res, dict(b.got), self.owner_id
        name = {i: r for r, i in oid.items()}
        for r in b.unreached:
            res.release(prefix[r], oid[r])
        queue = list(b.unreached)
        while queue:
            r = queue.pop(0)
            hold = prefix[r]
            cur = self.current.get(r)
            for p in ([cur] if cur else []) + [hold]:
                if not res.blockers(p, oid[r]):
                    break
            else:
                p = hold
                for o in res.blockers(hold, oid[r]):
                    other = name[o]
                    if other not in got:
                        raise ReplanAbandoned(sorted(self.todo))
                    res.release(got.pop(other), o)
                    queue.append(other)
                if res.blockers(hold, oid[r]):
                    raise ReplanAbandoned(sorted(self.todo))
            res.reserve(p, oid[r])
            got[r] = p
            self.deferred.add(r)
        return got

    def _plan_one(self, robot: str, prefix: list[int], res: Reservations) -> list[int] | None:
        """Path for ``robot`` that starts with ``prefix`` (its cell, maybe a committed next cell), or None."""
        f = self.f
        g = f.goals[robot]
        h = f.distance_row(g)
        s = prefix[-1]
        if h[s] == INF:             # starting in a non-free or blocked cell: escape moves only
            h = list(h)
            h[s] = f.distance(s, g)
        p = safe_interval_astar(f.graph.nbrs, s, g, h, res, self.limits.expansions(h[s]), t0=len(prefix) - 1,
                                weight=self.limits.weight)
        return None if p is None else prefix[:-1] + p

    def _fail_reason(self, robot: str, paths: Mapping[str, list[int]]) -> str:
        """Why ``robot`` was parked: parked robots wall its goal off, or the search gave up."""
        f, start = self.f, self.starts[robot]
        g = f.goals[robot]
        parked_by = {}
        for r, p in list(self.fixed.items()) + list(paths.items()):
            if r != robot and len(compress(p)) == 1:
                parked_by[p[-1]] = r
        blocked = set(f.blocked) | set(parked_by)
        if shortest_path(f.graph, start, g, blocked - {start}) is None:
            who = sorted({parked_by[c] for c in parked_by})
            return (f"no collision-free path to goal cell {g}: parked robots ({', '.join(who)}) "
                    f"block the way")
        n = self.attempts.get(robot, 0)
        return (f"no collision-free path to goal cell {g} found in {n} planning attempt(s) (other robots' "
                f"paths or parked robots block it); parked, retried on the next re-plan")
