"""Lifelong planning by whole plans: LaCAM to the current goals, planned again at every arrival.

On a map of a few cells, one-cell corridors and dead ends are a few cells apart, and a planner
that looks one step (PIBT) or a few steps (EPIBT) ahead can hold robots in each other's way for
good, or send them back and forth (docs/lifelong.md, "Maps never run before, and dead ends").
There a complete one-shot solver is cheap: LaCAM (:func:`~.lacam.solve_lacam`; Okumura,
AAAI-23) finds a plan that brings every robot to its goal, and LNS shortens it while the step's
time lasts (:func:`~.refine.refine_lns`). The plan is executed under MAPF_T's turns by an action
dependency graph (:class:`~.adg.PlanExecution`) until a robot's goal changes (an errand reached,
a task given), then planned again from where the robots stand.

Every plan brings the robots to their goals, so before it ends some robot reaches its errand:
no livelock, whatever the map. Two robots may share a goal (two tasks with an errand on one
cell) and a robot without a task has none: one-shot MAPF needs a distinct goal per robot, so the
robot nearest a shared goal keeps it and the others, and the robots without a task, stay where
they stand or take the nearest cell no one else has (they make way and wait there). Where LaCAM
finds no plan in time (or none exists, or a goal lies in a part of the map its robot cannot reach),
the fallback planner answers the step
(:class:`~.pibt.PIBTPlanner`), and LaCAM tries again at the next step.
"""
from __future__ import annotations

import time
from collections import deque

import numpy as np

from .adg import PlanExecution
from .distances import DistanceCache
from .grid import LifelongGrid
from .lacam import solve_lacam
from .refine import refine_lns

__all__ = ["SCORED_CELLS", "ReplanPlanner", "distinct_goals"]

SCORED_CELLS = 20_000   # plans of more (steps x robots) are taken as found, not scored by executing them


def distinct_goals(grid: LifelongGrid, pos: np.ndarray, goals: np.ndarray, dist: DistanceCache) -> np.ndarray:
    """One-shot goals (n,) int64, one distinct free cell per robot, from lifelong ``goals``
    (n,) (-1: no task) and the cells ``pos`` (n,) the robots stand on. A goal that several
    robots share goes to the nearest of them (``dist``'s distances); the others and the robots
    without a goal keep their own cell when no one took it, else the nearest cell (breadth-first)
    no one has."""
    n = pos.shape[0]
    out = np.full(n, -1, dtype=np.int64)
    taken: set[int] = set()
    has = np.flatnonzero(goals >= 0)
    if len(has):
        d = dist.table[dist.slots(goals[has]), pos[has]]
        for a in has[np.argsort(d, kind="stable")].tolist():
            g = int(goals[a])
            if g not in taken:
                out[a] = g
                taken.add(g)
    for a in np.flatnonzero(out < 0).tolist():       # stay, unless that cell is someone's goal
        c = int(pos[a])
        if c not in taken:
            out[a] = c
            taken.add(c)
    for a in np.flatnonzero(out < 0).tolist():       # the nearest cell no one has
        seen, q = {int(pos[a])}, deque([int(pos[a])])
        while q:
            c = q.popleft()
            if c not in taken:
                out[a] = c
                taken.add(c)
                break
            for v in grid.nbr[c]:
                if v >= 0 and int(v) not in seen:
                    seen.add(int(v))
                    q.append(int(v))
        if out[a] < 0:
            raise ValueError(f"robot {a}: no free cell left for it in its part of the map")
    return out


class ReplanPlanner:
    """LaCAM plans executed by an action dependency graph, planned again at every goal change
    (module docstring), for MAPF_T.

    grid: the map; fallback: the planner that answers a step without a plan (a
    :class:`~.pibt.PIBTPlanner`, with ``plan(pos, head, goals, deadline, hard)``); seed: LaCAM's
    and LNS's; tries: plans found (a new seed each) at most per replanning, while the deadline
    lasts; refine: LNS shortens each (sum of costs) for ``refine_share`` of the time then left.
    ``plan`` returns (n,) action codes. ``stats``: replannings that found a plan, plans found in
    them, steps answered from a plan, steps the fallback answered (no plan).
    """

    def __init__(self, grid: LifelongGrid, fallback, seed: int = 0, refine: bool = True, refine_share: float = 0.1,
                 tries: int = 16):
        self.grid, self.fallback, self.seed = grid, fallback, seed
        self.refine, self.refine_share, self.tries = refine, refine_share, tries
        self.cache = DistanceCache(grid, max_bytes=max(64 * 2 ** 20, 2 * grid.n_cells * 64))
        self.execution: PlanExecution | None = None
        self._goals: np.ndarray | None = None
        self.stats = {"replans": 0, "tries": 0, "plan_steps": 0, "fallback_steps": 0}

    def plan(self, pos: np.ndarray, head: np.ndarray, goals: np.ndarray, deadline: float,
             hard: float | None = None) -> np.ndarray:
        """Actions (n,) int64 for one step (class docstring); pos, head, goals (n,) int64 (goal
        -1: none). LaCAM and LNS stop at ``deadline`` (``time.perf_counter()``)."""
        ex = self.execution
        if (ex is None or ex.done or self._goals is None or not np.array_equal(goals, self._goals)
                or not np.array_equal(ex.expected(), pos)):
            ex = self.execution = self._new_plan(pos, head, goals, deadline)
        self._goals = goals.copy()
        if ex is None:
            self.stats["fallback_steps"] += 1
            return self.fallback.plan(pos, head, goals, deadline, hard)
        self.stats["plan_steps"] += 1
        return ex.step(head)

    def _new_plan(self, pos: np.ndarray, head: np.ndarray, goals: np.ndarray,
                  deadline: float) -> PlanExecution | None:
        """The best of the plans found by ``deadline`` (LaCAM with a new seed each, then LNS):
        the least sum, over the robots with a goal, of the steps to their goal executed under
        turns (:meth:`~.adg.PlanExecution.arrivals`). None when LaCAM found none."""
        try:
            target = distinct_goals(self.grid, pos, goals, self.cache)
        except ValueError:                        # goals of robots elsewhere fill a part of the map
            return None
        has = goals >= 0
        best, best_cost, tries = None, None, 0
        while time.perf_counter() < deadline and tries < self.tries:
            self.seed += 1
            tries += 1
            left = deadline - time.perf_counter()
            try:
                res = solve_lacam(self.grid, pos, target, time_limit_s=left, seed=self.seed, cache=self.cache)
            except ValueError:                    # a goal in another part of the map: no plan reaches it
                break
            if not res["solved"]:
                break                             # out of time, or no plan exists: another seed will not do
            paths = res["paths"]
            left = self.refine_share * (deadline - time.perf_counter())
            if self.refine and left > 0 and paths.shape[0] > 2:
                paths = refine_lns(self.grid, paths, target, left, seed=self.seed, cache=self.cache)["paths"]
            ex = PlanExecution(self.grid.nbr, paths)
            if paths.size > SCORED_CELLS:          # a large plan: scoring it would take the step's time
                best = ex
                break
            cost = int(ex.arrivals(head)[has].sum())
            if best_cost is None or cost < best_cost:
                best, best_cost = ex, cost
        if best is not None:
            self.stats["replans"] += 1
            self.stats["tries"] += tries
        return best
