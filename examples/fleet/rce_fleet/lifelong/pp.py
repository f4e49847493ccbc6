"""One-shot MAPF by prioritized planning (PP): the agents one after another, each by the
space-time A* of :mod:`.spacetime` around the agents planned before it, every agent held on
its goal from its arrival on (Silver, "Cooperative pathfinding", AIIDE 2005; Erdmann &
Lozano-Perez 1987). When an agent finds no path, it moves to the front of the order and the
plan starts again (the priority search of Bennewitz, Burgard & Thrun, "Finding and optimizing
solvable priority schemes for decoupled path planning techniques for teams of mobile
robots", RAS 2002, in its simplest form), until the time is up.

The order: first the agents whose goals are on open floor (all eight neighbours free: parked
there, they wall off nothing), then the agents whose goals lie deepest in an aisle
(breadth-first steps from the goal to the nearest cell with three or more free neighbours),
each group the longest distance first. On maps of one-cell aisles the usual failure of PP is
a goal walled off by agents parked on both sides of it, or a way across the aisles walled off
by agents parked in them; this order plans the agents that cross the map while the aisles
are empty and fills each aisle from its middle out. Measured on the MovingAI
warehouse-10-20-10-2-1 (random-1): at 400 agents 1 restart (by distance alone 43 - 69, in a
random order 49); at 1000 agents the first plan fails after 280 agents (after 210 by
distance alone) and the restarts do not converge within 10 s. PP is not complete; callers keep
a complete solver as the fallback (:func:`~.oneshot.plan_one_shot`).
"""
from __future__ import annotations

import time

import numpy as np

from .distances import DistanceCache, one_shot_distances
from .grid import LifelongGrid
from .kernels import bfs_multi
from .spacetime import SpaceTimeTable

__all__ = ["aisle_depth", "open_cells", "solve_pp"]


def open_cells(grid: LifelongGrid) -> np.ndarray:
    """(cells,) bool: free cells whose eight neighbours are all free (open floor, where an
    agent parked on its goal walls off nothing)."""
    pad = np.pad(grid.free, 1)
    rows, cols = grid.free.shape
    out = grid.free.copy()
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            out &= pad[1 + dr: 1 + dr + rows, 1 + dc: 1 + dc + cols]
    return out.ravel()


def aisle_depth(grid: LifelongGrid) -> np.ndarray:
    """(cells,) int64: breadth-first steps from each cell to the nearest free cell with three or
    more free neighbours (0 there and in open areas; high deep in a one-cell aisle or a dead
    end; -1 for cells that reach none, obstacles included)."""
    deg = (grid.nbr >= 0).sum(axis=1)
    src = np.flatnonzero(grid.flat & (deg >= 3)).astype(np.int64)
    return bfs_multi(grid.nbr, src)


def solve_pp(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray, time_limit_s: float = 1.0, seed: int = 0,
             cache: DistanceCache | None = None, max_expand: int = 300_000, horizon: int | None = None,
             clock=time.perf_counter) -> dict:
    """Solve one-shot MAPF (4-neighbour moves) by prioritized planning with restarts.

    starts, goals: (n,) cells. ``horizon``: the last step a path may use (default twice the
    longest distance + 64); ``max_expand``: states one agent's search may expand. Returns a
    dict as :func:`~.lacam.solve_lacam`: ``paths`` ((T+1, n) cells; when ``solved`` the
    last row is the goals and no two agents share a cell or exchange cells; when not, the
    agents planned so far and the others standing on their starts), ``solved``,
    ``sum_of_costs`` (each agent's last arrival, summed; of the planned agents when not
    solved), ``makespan``, ``time_s``, plus ``planned`` (agents with a path),
    ``restarts`` and ``expanded`` (states, all searches). Stops unsolved at ``time_limit_s``
    seconds of ``clock``. Raises ValueError for a goal that cannot be reached from its
    start or two agents on one start or goal.
    """
    t0 = clock()
    starts, goals, cache, hrow, lb = one_shot_distances(grid, starts, goals, cache)
    n, lb = starts.shape[0], lb.astype(np.int64)
    max_h = int(lb.max()) if n else 0
    H = horizon or 2 * max_h + 64
    rng = np.random.default_rng(seed)
    depth = aisle_depth(grid)[goals]
    order = np.lexsort((-lb + rng.random(n), -depth, ~open_cells(grid)[goals])).astype(np.int64)
    res = SpaceTimeTable(n, grid.n_cells, H, max_h + 1)
    done = restarts = 0
    while True:
        done += res.plan(grid.nbr, cache.table, hrow, starts, goals, order[done:], max_expand)
        if done == n or clock() - t0 >= time_limit_s:
            break
        restarts += 1                          # the agent without a path goes first; plan again
        failed = order[done]
        res.remove(goals, order[:done])
        order = np.concatenate(([failed], np.delete(order, done)))
        done = 0
    planned = order[:done]
    arrival = np.zeros(n, dtype=np.int64)
    arrival[planned] = res.lengths[planned] - 1
    T = int(arrival.max()) if n else 0
    paths = np.repeat(starts[None, :], T + 1, axis=0)
    for a in planned:
        paths[: arrival[a] + 1, a] = res.paths[a, : arrival[a] + 1]
        paths[arrival[a] + 1:, a] = goals[a]
    return {"paths": paths, "solved": done == n, "sum_of_costs": int(arrival.sum()), "makespan": T,
            "time_s": clock() - t0, "planned": int(done), "restarts": restarts, "expanded": int(res.stats[0])}
