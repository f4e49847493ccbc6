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
  (up to ``max_sweeps``) while the one before cut the delays by 1 %;
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

__all__ = ["refine_lns", "warm_up"]


def _arrivals(paths: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """(n,) each agent's last arrival at its goal in ``paths`` ((T+1, n))."""
    off = paths != goals[None, :]
    return np.where(off.any(axis=0), paths.shape[0] - np.argmax(off[::-1], axis=0), 0).astype(np.int64)


def refine_lns(grid: LifelongGrid, paths: np.ndarray, goals: np.ndarray, time_limit_s: float, seed: int = 0,
               cache: DistanceCache | None = None, max_group: int = 8, slack: int = 64,
               max_expand: int = 5_000, max_sweeps: int = 8, sipp: bool = True,
               clock=time.perf_counter) -> dict:
    """Improve a conflict-free solution ``paths`` ((T+1, n) cells, last row the goals) within
    ``time_limit_s`` seconds of ``clock`` (wall time; ``time.process_time`` for this process's
    CPU). ``max_expand``: states one re-plan may expand (safe intervals with ``sipp``, else
    (step, cell) states). Returns a dict: ``paths`` ((T'+1, n), conflict-free, every agent
    ends on its goal), ``sum_of_costs`` (last arrivals summed), ``makespan``, ``iterations``,
    ``accepted``, ``expanded``, ``time_s``. Never worse than the input (sum of costs, and no
    agent's arrival beyond the input's makespan + ``slack``). Raises ValueError when the last
    row is not ``goals``."""
    t0 = clock()
    goals = np.asarray(goals, dtype=np.int64)
    paths = np.asarray(paths, dtype=np.int64)
    if paths.ndim != 2 or paths.shape[1] != goals.shape[0] or not (paths[-1] == goals).all():
        raise ValueError("refine_lns needs a solution: (T+1, n) cells whose last row is the goals")
    n = goals.shape[0]
    ncell = grid.n_cells
    H = paths.shape[0] + slack
    cache = cache or DistanceCache(grid, max_bytes=2 * ncell * (n + 16))
    hrows = np.array([cache.slot(int(g)) for g in goals], dtype=np.int64)
    table = cache.table
    lb = table[hrows, paths[0]].astype(np.int64)
    arrival = _arrivals(paths, goals)
    res = SpaceTimeTable(n, ncell, H, int(lb.max()) + 1)
    res.paths[:, : paths.shape[0]] = paths.T
    res.lengths[:] = arrival + 1
    everyone = np.arange(n, dtype=np.int64)
    res.place(goals, everyone)
    starts = paths[0].copy()
    nbr = grid.nbr
    rng = np.random.default_rng(seed)
    it = acc = 0
    sweeps, sweep_from = max_sweeps, np.inf
    queue: list[int] = []
    while clock() - t0 < time_limit_s:
        delay = res.lengths - 1 - lb
        if delay.sum() == 0:
            break
        it += 1
        if not queue and sweeps and delay.sum() < 0.99 * sweep_from:   # the last sweep helped
            sweeps -= 1
            sweep_from = delay.sum()
            queue = np.argsort(-delay, kind="stable")[::-1].tolist()      # popped from the end
        if queue:
            group = np.array([queue.pop()], dtype=np.int64)
        elif rng.random() < 0.8:
            w = delay.astype(float)
            i = int(rng.choice(n, p=w / w.sum()))
            col = res.occ[goals[i], lb[i]:]
            others = np.unique(col[(col >= 0) & (col != i)]).astype(np.int64)
            if len(others) > max_group - 1:
                others = rng.choice(others, max_group - 1, replace=False)
            group = np.concatenate(([i], others)).astype(np.int64)
        else:
            group = rng.choice(n, size=min(max_group, n), replace=False).astype(np.int64)
        rng.shuffle(group)
        old_paths = res.paths[group].copy()
        old_len = res.lengths[group].copy()
        res.remove(goals, group)
        k = res.plan(nbr, table, hrows, starts, goals, group, max_expand, sipp)
        if k == len(group) and res.lengths[group].sum() <= old_len.sum():
            acc += int(res.lengths[group].sum() < old_len.sum())
            continue
        res.remove(goals, group[:k])
        res.paths[group] = old_paths
        res.lengths[group] = old_len
        res.place(goals, group)
    arrival = res.lengths - 1
    T = int(arrival.max())
    out = res.paths[:, : T + 1].T.copy()
    for a in np.flatnonzero(arrival < T):
        out[arrival[a] + 1:, a] = goals[a]
    return {"paths": out, "sum_of_costs": int(arrival.sum()), "makespan": T, "iterations": it, "accepted": acc,
            "expanded": int(res.stats[0]), "time_s": clock() - t0}


def warm_up() -> None:
    """Compile (or load from numba's cache) the space-time kernels."""
    _warm_spacetime()
