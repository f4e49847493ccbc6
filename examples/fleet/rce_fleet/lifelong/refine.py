"""Anytime refinement of a one-shot MAPF solution by large neighbourhood search (Li, Chen,
Harabor, Stuckey & Koenig, "Anytime multi-agent path finding via large neighborhood search",
IJCAI-21): repeatedly take a few agents' paths out, re-plan them one by one around everybody
else's (:mod:`.spacetime`: vertex and swap conflicts, agents parked at their goals), and keep
the new paths when their sum of costs is not higher.

The re-plans search by safe intervals (SIPP, as MAPF-LNS2 re-plans, Li et al. AAAI-22; the
same arrivals as the space-time A*, ``sipp=False``): measured at 1000 agents on the MovingAI
warehouse from one LaCAM solution (1.88x the lower bound), 3.5 CPU-s of LNS end at 1.639x
against 1.665 - 1.669x with the A* (200 uncapped re-plans: 1.1 M expansions and 0.6 CPU-s
against 5.1 M and 3.4 CPU-s).

Neighbourhoods, in this order:

- sweeps of single agents, every agent once, most delayed first: each is re-planned alone
  around all the others. Its old path is one of the paths the search may return, so the new
  arrival is never later; after a first solution by PIBT, much of the cost is agents that
  were pushed off their goals by others and came back, which a single re-plan removes once
  the pusher is gone. Agents without delay are re-planned too: their new path (as short, but
  diving to the goal and waiting near it) often clears the way for others (measured at 1000
  agents on the MovingAI warehouse: 2.5 CPU-s of LNS from one solution end at 1.852 - 1.853x
  the lower bound against 1.868 - 1.887x with only the delayed agents). A sweep is repeated
  (up to ``max_sweeps``) while the one before cut the delays by 1 %. A sweep's re-plans
  search up to ``max_expand`` states; those cut short keep their old paths and are searched
  again at the end of the sweep with up to ``single_expand`` (200,000). Such a re-plan cannot
  fail for want of a path (the old path is one), and the long searches are those of agents
  whose goals stay busy long after they could arrive, worth most to re-plan: at 1000 agents on
  the MovingAI warehouse ~20 % of a sweep's searches pass 5,000 states (most under 100,000),
  and the first sweep from a LaCAM solution (1.88x the lower bound) cuts 10,662 steps without
  a cap against 6,890 with 5,000. Deferred to the end of the sweep, they do not hold up the
  quick ones (docs/lifelong.md, "One-shot", for the measurements);
- then, until the time is up: an agent with a delay (drawn in proportion to it) together with
  the agents that stand on its goal after it could have arrived (the usual cause of a late
  arrival), or a random handful (the random and agent-based neighbourhoods of the paper).
"""
from __future__ import annotations

import time

import numpy as np

from .distances import DistanceCache
from .grid import LifelongGrid
from .spacetime import SpaceTimeTable
from .spacetime import warm_up as _warm_spacetime

__all__ = ["Refiner", "refine_lns", "warm_up"]


def _arrivals(paths: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """(n,) each agent's last arrival at its goal in ``paths`` ((T+1, n))."""
    off = paths != goals[None, :]
    return np.where(off.any(axis=0), paths.shape[0] - np.argmax(off[::-1], axis=0), 0).astype(np.int64)


class Refiner:
    """The state of anytime LNS on one conflict-free solution: the reservation table of every
    agent's path, the sweep in progress and the random stream. :meth:`improve` re-plans
    neighbourhoods of the agents in ``own`` only (all by default), so that several refiners on
    copies of one solution, each owning other agents, can run side by side and
    :meth:`replay` each other's changes (:mod:`.parallel`).

    paths: (T+1, n) cells whose last row is ``goals``. Raises ValueError otherwise."""

    def __init__(self, grid: LifelongGrid, paths: np.ndarray, goals: np.ndarray, seed: int = 0,
                 cache: DistanceCache | None = None, max_group: int = 8, slack: int = 64,
                 max_expand: int = 5_000, max_sweeps: int = 8, sipp: bool = True, single_expand: int = 200_000):
        goals = np.asarray(goals, dtype=np.int64)
        paths = np.asarray(paths, dtype=np.int64)
        if paths.ndim != 2 or paths.shape[1] != goals.shape[0] or not (paths[-1] == goals).all():
            raise ValueError("refine_lns needs a solution: (T+1, n) cells whose last row is the goals")
        n = goals.shape[0]
        ncell = grid.n_cells
        if cache is None:                      # an empty cache is falsy (len 0) but is the one to use
            cache = DistanceCache(grid, max_bytes=2 * ncell * (n + 16))
        self.goals, self.nbr, self.table = goals, grid.nbr, cache.table
        self.hrows = cache.slots(goals)
        self.lb = self.table[self.hrows, paths[0]].astype(np.int64)
        self.res = SpaceTimeTable(n, ncell, paths.shape[0] + slack, int(self.lb.max()) + 1)
        self.res.paths[:, : paths.shape[0]] = paths.T
        self.res.lengths[:] = _arrivals(paths, goals) + 1
        self.res.place(goals, np.arange(n, dtype=np.int64))
        self.starts = paths[0].copy()
        self.max_group, self.max_expand, self.single_expand, self.sipp = max_group, max_expand, single_expand, sipp
        self.rng = np.random.default_rng(seed)
        self.own = np.ones(n, dtype=bool)
        self.sweeps, self.sweep_from = max_sweeps, np.inf
        self.queue: list[int] = []
        self.deferred: list[int] = []
        self.cap = min(max_expand, single_expand)   # of the single re-plans queued
        self.iterations = self.accepted = 0
        self.log: list | None = None           # accepted changes, for :meth:`replay` elsewhere

    def improve(self, time_limit_s: float, clock=time.perf_counter) -> None:
        """Re-plan neighbourhoods of owned agents for ``time_limit_s`` seconds of ``clock``
        (wall time; ``time.process_time`` for this process's CPU), keeping each whose sum of
        costs is not higher."""
        t0 = clock()
        res, goals, lb, rng, n = self.res, self.goals, self.lb, self.rng, self.goals.shape[0]
        owned = np.flatnonzero(self.own)
        while clock() - t0 < time_limit_s:
            delay = np.where(self.own, res.lengths - 1 - lb, 0)
            if delay.sum() == 0:
                break
            if not self.queue and self.deferred:                       # the cut searches, further
                self.queue, self.deferred, self.cap = self.deferred[::-1], [], self.single_expand
            if not self.queue and self.sweeps and delay.sum() < 0.99 * self.sweep_from:   # the last sweep helped
                self.cap = min(self.max_expand, self.single_expand)     # cut searches are deferred
                self.sweeps -= 1
                self.sweep_from = delay.sum()
                order = np.argsort(-delay[owned], kind="stable")
                self.queue = owned[order][::-1].tolist()                  # popped from the end
            cap, swept = self.max_expand, bool(self.queue)
            if swept:
                a = self.queue.pop()
                if not self.own[a]:
                    continue                   # another refiner's since the sweep began
                group = np.array([a], dtype=np.int64)
                cap = self.cap
            elif rng.random() < 0.8:
                w = delay.astype(float)
                i = int(rng.choice(n, p=w / w.sum()))
                col = res.occ[goals[i], lb[i]:]
                others = np.unique(col[(col >= 0) & (col != i)]).astype(np.int64)
                others = others[self.own[others]]
                if len(others) > self.max_group - 1:
                    others = rng.choice(others, self.max_group - 1, replace=False)
                group = np.concatenate(([i], others)).astype(np.int64)
            else:
                group = rng.choice(owned, size=min(self.max_group, len(owned)), replace=False).astype(np.int64)
            self.iterations += 1
            rng.shuffle(group)
            before = res.lengths[group].sum()
            if res.replan(self.nbr, self.table, self.hrows, self.starts, goals, group, cap, self.sipp):
                self.accepted += int(res.lengths[group].sum() < before)
                if self.log is not None:
                    self.log.append((group, res.paths[group].astype(np.int32), res.lengths[group].copy()))
            elif swept and cap < self.single_expand:     # cut short: its old path is an answer
                self.deferred.append(int(group[0]))

    def replay(self, log: list) -> int:
        """Apply another refiner's accepted changes ``log`` (:attr:`log`: (agents, their paths
        (k, H), their lengths (k,)) each, in the order they were made, each planned around that
        refiner's paths at the time) in order, each only when all its paths fit this refiner's
        (no vertex or swap conflict, goals free from the arrival on) and its sum of costs is
        not higher than these agents' here. Returns how many changes were applied."""
        res, goals = self.res, self.goals
        applied = 0
        for agents, paths, lengths in log:
            if lengths.sum() > res.lengths[agents].sum():
                continue
            old_paths, old_len = res.paths[agents].copy(), res.lengths[agents].copy()
            res.remove(goals, agents)
            k = 0
            while k < len(agents) and res.fits(paths[k], lengths[k], goals[agents[k]]):
                res.paths[agents[k]], res.lengths[agents[k]] = paths[k], lengths[k]
                res.place(goals, agents[k: k + 1])
                k += 1
            if k == len(agents):
                applied += 1
                continue
            res.remove(goals, agents[:k])
            res.paths[agents], res.lengths[agents] = old_paths, old_len
            res.place(goals, agents)
        return applied

    def sync(self, agents: np.ndarray, paths: np.ndarray, lengths: np.ndarray) -> None:
        """Set ``agents``' paths ((k,); ``paths`` (k, H) cells by step, ``lengths`` (k,) arrival
        + 1) to another refiner's, without a check: the caller sends a whole solution's
        changes."""
        res = self.res
        res.remove(self.goals, agents)
        res.paths[agents], res.lengths[agents] = paths, lengths
        res.place(self.goals, agents)

    def solution(self) -> dict:
        """``paths`` ((T+1, n), conflict-free, every agent on its goal from its last arrival on),
        ``sum_of_costs``, ``makespan``."""
        arrival = self.res.lengths - 1
        T = int(arrival.max())
        out = self.res.paths[:, : T + 1].T.copy()
        for a in np.flatnonzero(arrival < T):
            out[arrival[a] + 1:, a] = self.goals[a]
        return {"paths": out, "sum_of_costs": int(arrival.sum()), "makespan": T}


def refine_lns(grid: LifelongGrid, paths: np.ndarray, goals: np.ndarray, time_limit_s: float, seed: int = 0,
               cache: DistanceCache | None = None, max_group: int = 8, slack: int = 64,
               max_expand: int = 5_000, max_sweeps: int = 8, sipp: bool = True, single_expand: int = 200_000,
               clock=time.perf_counter) -> dict:
    """Improve a conflict-free solution ``paths`` ((T+1, n) cells, last row the goals) within
    ``time_limit_s`` seconds of ``clock`` (wall time; ``time.process_time`` for this process's
    CPU). ``max_expand``: states one re-plan may expand (safe intervals with ``sipp``, else
    (step, cell) states); ``single_expand``: a sweep's re-plan cut short at ``max_expand``,
    searched again at the end of the sweep. Returns a dict: ``paths`` ((T'+1, n),
    conflict-free, every agent ends on its goal), ``sum_of_costs`` (last arrivals summed),
    ``makespan``, ``iterations``, ``accepted``, ``expanded``, ``time_s``. Never worse than the
    input (sum of costs, and no agent's arrival beyond the input's makespan + ``slack``).
    Raises ValueError when the last row is not ``goals``."""
    t0 = clock()
    ref = Refiner(grid, paths, goals, seed, cache, max_group, slack, max_expand, max_sweeps, sipp, single_expand)
    ref.improve(time_limit_s - (clock() - t0), clock)
    return {**ref.solution(), "iterations": ref.iterations, "accepted": ref.accepted,
            "expanded": int(ref.res.stats[0]), "time_s": clock() - t0}


def warm_up() -> None:
    """Compile (or load from numba's cache) the space-time kernels."""
    _warm_spacetime()
