"""Anytime refinement of a one-shot MAPF solution by large neighbourhood search (Li, Chen,
Harabor, Stuckey & Koenig, "Anytime multi-agent path finding via large neighborhood search",
IJCAI-21): repeatedly take a few agents' paths out, re-plan them one by one with space-time
A* around everybody else's (vertex and swap conflicts, agents parked at their goals), and
keep the new paths when their sum of costs is lower.

Neighbourhoods: an agent that arrives late together with the agents that stand on its goal
after it could have arrived (the usual cause of a late arrival in PIBT and LaCAM solutions:
being pushed off its goal), or a random handful. The space-time A* is compiled (numba).
"""
from __future__ import annotations

import heapq
import time

import numpy as np
from numba import njit

from .distances import DistanceCache
from .grid import LifelongGrid

__all__ = ["refine_lns", "warm_up"]


@njit(cache=True)
def _st_astar(nbr, h, start, goal, occ, ready, stamp, sid, parent, max_expand):
    """Space-time A* on (t, cell) for one agent: 4-neighbour moves or wait, never into a cell
    ``occ[t + 1]`` holds nor swapping with its holder; done at ``goal`` at a time >= ``ready``
    (after the last other agent leaves it). occ: (H, cells) int32 agent ids (-1 free).
    Returns the path as an int64 array of cells (index = time), or an empty array (none, or
    more than ``max_expand`` expansions)."""
    H, ncell = occ.shape
    # f = max(t + h, ready): waiting for the goal to clear costs what it costs; ties go deeper
    # and nearer, so the search dives to the goal and waits there instead of flooding space-time
    heap = [(np.int64(max(h[start], ready)), np.int64(0), np.int64(h[start]), np.int64(start))]
    stamp[start] = sid
    parent[start] = -1
    expanded = 0
    while heap:
        expanded += 1
        if expanded > max_expand:
            break
        f, negt, hu, u = heapq.heappop(heap)
        t = -negt
        if u == goal and t >= ready:
            n = t + 1
            path = np.empty(n, np.int64)
            key = t * ncell + u
            for k in range(n - 1, -1, -1):
                path[k] = key % ncell
                key = parent[key]
            return path
        if t + 1 >= H:
            continue
        base = (t + 1) * ncell
        for d in range(5):
            v = u if d == 4 else nbr[u, d]
            if v < 0:
                continue
            if occ[t + 1, v] >= 0:
                continue
            j = occ[t, v]
            if j >= 0 and v != u and occ[t + 1, u] == j:
                continue
            key = base + v
            if stamp[key] == sid:
                continue
            stamp[key] = sid
            parent[key] = t * ncell + u
            heapq.heappush(heap, (np.int64(max(t + 1 + h[v], ready)), np.int64(-(t + 1)), np.int64(h[v]),
                                  np.int64(v)))
    return np.empty(0, np.int64)


def _arrival(path: np.ndarray, goal: int) -> int:
    off = np.flatnonzero(path != goal)
    return int(off[-1]) + 1 if len(off) else 0


def refine_lns(grid: LifelongGrid, paths: np.ndarray, goals: np.ndarray, time_limit_s: float, seed: int = 0,
               cache: DistanceCache | None = None, max_group: int = 12, slack: int = 64,
               max_expand: int = 20_000) -> dict:
    """Improve a conflict-free solution ``paths`` ((T+1, n) cells, last row the goals) within
    ``time_limit_s`` wall seconds. Returns a dict: ``paths`` ((T'+1, n), conflict-free, every
    agent ends on its goal), ``sum_of_costs`` (last arrivals summed), ``makespan``,
    ``iterations``, ``accepted``. Never worse than the input. Raises ValueError when the
    last row is not ``goals``."""
    t0 = time.perf_counter()
    goals = np.asarray(goals, dtype=np.int64)
    if not (paths[-1] == goals).all():
        raise ValueError("refine_lns needs a solution: the last configuration must be the goals")
    n = goals.shape[0]
    ncell = grid.n_cells
    H = paths.shape[0] + slack
    cache = cache or DistanceCache(grid, max_bytes=2 * ncell * (n + 16))
    hrows = np.array([cache.slot(int(g)) for g in goals], dtype=np.int64)
    table = cache.table
    agent_paths = []
    arrival = np.empty(n, dtype=np.int64)
    for a in range(n):
        arrival[a] = _arrival(paths[:, a], int(goals[a]))
        agent_paths.append(paths[: arrival[a] + 1, a].copy())
    lb = table[hrows, paths[0]].astype(np.int64)
    occ = np.full((H, ncell), -1, dtype=np.int32)

    def place(a: int, p: np.ndarray) -> None:
        occ[np.arange(len(p)), p] = a
        occ[len(p):, goals[a]] = a

    def remove(a: int, p: np.ndarray) -> None:
        occ[np.arange(len(p)), p] = -1
        occ[len(p):, goals[a]] = -1

    for a in range(n):
        place(a, agent_paths[a])
    stamp = np.zeros(H * ncell, dtype=np.int32)
    parent = np.empty(H * ncell, dtype=np.int64)
    sid = 0
    rng = np.random.default_rng(seed)
    it = acc = 0
    while time.perf_counter() - t0 < time_limit_s:
        it += 1
        delay = arrival - lb
        if delay.sum() == 0:
            break
        if rng.random() < 0.8:
            w = delay.astype(float)
            i = int(rng.choice(n, p=w / w.sum()))
            col = occ[lb[i]:, goals[i]]
            group = [i] + [int(j) for j in np.unique(col[(col >= 0) & (col != i)])]
        else:
            group = [int(x) for x in rng.choice(n, size=min(max_group, n), replace=False)]
        if len(group) > max_group:
            group = group[:1] + [int(x) for x in rng.choice(group[1:], max_group - 1, replace=False)]
        rng.shuffle(group)
        old = {a: agent_paths[a] for a in group}
        for a in group:
            remove(a, old[a])
        new = {}
        ok = True
        for a in group:
            g = int(goals[a])
            col = occ[:, g]
            busy = np.flatnonzero(col >= 0)
            ready = int(busy[-1]) + 1 if len(busy) else 0
            if ready >= H - 1:
                ok = False
                break
            sid += 1
            if sid == np.iinfo(np.int32).max:
                stamp[:] = 0
                sid = 1
            p = _st_astar(grid.nbr, table[hrows[a]], int(old[a][0]), g, occ, ready, stamp, sid, parent, max_expand)
            if len(p) == 0:
                ok = False
                break
            new[a] = p
            place(a, p)
        if ok and sum(len(p) - 1 for p in new.values()) < sum(len(p) - 1 for p in old.values()):
            for a, p in new.items():
                agent_paths[a] = p
                arrival[a] = len(p) - 1
            acc += 1
            continue
        for a, p in new.items():
            remove(a, p)
        for a in group:
            place(a, old[a])
    T = int(arrival.max())
    out = np.empty((T + 1, n), dtype=np.int64)
    for a in range(n):
        p = agent_paths[a]
        out[: len(p), a] = p
        out[len(p):, a] = goals[a]
    return {"paths": out, "sum_of_costs": int(arrival.sum()), "makespan": T, "iterations": it, "accepted": acc,
            "time_s": time.perf_counter() - t0}


def warm_up() -> None:
    """Compile (or load from numba's cache) the space-time A* on a 2 x 2 grid."""
    g = LifelongGrid(np.ones((2, 2), dtype=bool))
    occ = np.full((4, 4), -1, dtype=np.int32)
    h = np.array([2, 1, 1, 0], dtype=np.uint16)
    _st_astar(g.nbr, h, 0, 3, occ, 0, np.zeros(16, np.int32), 1, np.empty(16, np.int64), 100)
