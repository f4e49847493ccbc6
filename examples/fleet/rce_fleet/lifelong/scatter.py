"""Space utilisation for one-shot MAPF ("scatter"): one path per agent, each chosen among its
near-shortest paths to meet as few of the others' paths as it can, for PIBT to prefer
(Okumura, "Engineering LaCAM*: towards real-time, large-scale, and near-optimal multi-agent
pathfinding", AAMAS-24, section "space utilization optimization").

Each agent in turn, in a random order, finds a path in space (each cell once) whose length
is at most its distance + ``margin``, lexicographically least in (collisions with the other
agents' current paths, length); step ``t`` of a path is its ``t``-th cell, and an agent
stays on its goal after its last step. Collisions counted: another path on the same cell at
the same step, a cell whose agent is already parked on it, and an exchange of cells with the
agent that stood on the entered cell. Rounds repeat while they cut the collisions (at least
two). The result is a table of each agent's next cell from each cell of its path
(:func:`~.kernels.prefer_table`); :func:`~.kernels.pibt_step` tries that cell first.
"""
from __future__ import annotations

import time

import numpy as np
from numba import njit

from .kernels import NO_PREFER, heap_pop, heap_push, prefer_table
from ..numba_cache import seed

seed(__file__)          # numba's cache entries prepared in the tree (sandboxed nodes)

__all__ = ["scatter"]


@njit(cache=True)
def _enroll(a, paths, lengths, cnt, who, park, sign):
    """Add (sign 1) or take out (sign -1) agent ``a``'s path in the collision tables."""
    L = lengths[a]
    if L == 0:
        return
    for t in range(L):
        c = paths[a, t]
        cnt[t, c] += sign
        if sign > 0:
            who[t, c] = a
        elif who[t, c] == a:
            who[t, c] = -1
    park[paths[a, L - 1]] = L - 1 if sign > 0 else 2 ** 30


@njit(cache=True)
def _collisions(a, paths, lengths, cnt, who, park):
    """Collisions of agent ``a``'s path with the paths in the tables (``a`` not among them)."""
    L = lengths[a]
    k = 0
    for t in range(1, L):
        u = paths[a, t - 1]
        v = paths[a, t]
        k += cnt[t, v]
        if park[v] <= t:
            k += 1
        j = who[t - 1, v]
        if j >= 0 and t < lengths[j] and paths[j, t] == u:
            k += 1
    g = paths[a, L - 1]
    for t in range(L, cnt.shape[0]):
        k += cnt[t, g]
    return k


@njit(cache=True)
def _search(a, nbr, h, start, goal, ub, paths, lengths, cnt, who, park, closed, hk, hv, pv, pp, pg, used):
    """The path of agent ``a`` least in (collisions, length) with length <= ``ub`` + 1 cells,
    into ``paths[a]`` and ``lengths[a]``; returns its collisions, -1 when there is none.
    ``closed`` (cells,) bool left all False; ``hk``, ``hv`` heap scratch and ``pv``, ``pp``,
    ``pg`` (cell, parent push, step of each push) of length >= 4 x cells + 1; ``used``
    (cells,)."""
    T = cnt.shape[0]
    pv[0] = start
    pp[0] = -1
    pg[0] = 0
    npush = 1
    size = heap_push(hk, hv, 0, np.int64(h[start]) << 20, 0)
    nused = 0
    found = -1
    coll = 0
    while size > 0:
        key, q, size = heap_pop(hk, hv, size)
        v = pv[q]
        if closed[v]:
            continue
        closed[v] = True
        used[nused] = v
        nused += 1
        coll = key >> 40
        if v == goal:
            found = q
            break
        g = pg[q]
        for d in range(4):
            u = nbr[v, d]
            if u < 0 or closed[u]:
                continue
            hu = np.int64(h[u])
            if g + 1 + hu > ub or g + 1 >= T:
                continue
            c = coll + cnt[g + 1, u]
            if park[u] <= g + 1:
                c += 1
            j = who[g, u]
            if j >= 0 and g + 1 < lengths[j] and paths[j, g + 1] == v:
                c += 1
            if u == goal:
                for t in range(g + 2, T):
                    c += cnt[t, u]
            pv[npush] = u
            pp[npush] = q
            pg[npush] = g + 1
            size = heap_push(hk, hv, size, (c << 40) | (np.int64(g + 1 + hu) << 20) | hu, npush)
            npush += 1
    for k in range(nused):
        closed[used[k]] = False
    if found < 0:
        return -1
    L = pg[found] + 1
    q = found
    for t in range(L - 1, -1, -1):
        paths[a, t] = pv[q]
        q = pp[q]
    lengths[a] = L
    return coll


@njit(cache=True)
def _round(nbr, table, rows, starts, goals, margin, order, paths, lengths, cnt, who, park):
    """Re-plan every agent in ``order`` around the others' paths; returns the collisions after
    the round (each counted from both sides)."""
    ncell = nbr.shape[0]
    closed = np.zeros(ncell, np.bool_)
    m = 4 * ncell + 1
    hk = np.empty(m, np.int64)
    hv = np.empty(m, np.int64)
    pv = np.empty(m, np.int64)
    pp = np.empty(m, np.int64)
    pg = np.empty(m, np.int64)
    used = np.empty(ncell, np.int64)
    for a in order:
        h = table[rows[a]]
        _enroll(a, paths, lengths, cnt, who, park, -1)
        _search(a, nbr, h, starts[a], goals[a], h[starts[a]] + margin, paths, lengths, cnt, who, park, closed,
                hk, hv, pv, pp, pg, used)
        _enroll(a, paths, lengths, cnt, who, park, 1)
    total = 0
    for a in range(starts.shape[0]):
        _enroll(a, paths, lengths, cnt, who, park, -1)
        total += _collisions(a, paths, lengths, cnt, who, park)
        _enroll(a, paths, lengths, cnt, who, park, 1)
    return total


@njit(cache=True)
def _steps(paths, lengths):
    """Every step of every path as (agent, cell, next cell) arrays."""
    m = 0
    for a in range(paths.shape[0]):
        m += max(lengths[a] - 1, 0)
    agents = np.empty(m, np.int64)
    cells = np.empty(m, np.int64)
    nxt = np.empty(m, np.int64)
    k = 0
    for a in range(paths.shape[0]):
        for t in range(lengths[a] - 1):
            agents[k] = a
            cells[k] = paths[a, t]
            nxt[k] = paths[a, t + 1]
            k += 1
    return agents, cells, nxt


def scatter(nbr: np.ndarray, table: np.ndarray, rows: np.ndarray, starts: np.ndarray, goals: np.ndarray,
            time_limit_s: float = 1.0, margin: int = 10, max_rounds: int = 8, seed: int = 0,
            clock=time.perf_counter) -> tuple[np.ndarray, dict]:
    """Paths that spread the agents over near-shortest routes (module docstring).

    nbr: (cells, 4) moves; table: uint16 distance rows; rows: (n,) each goal's row in
    ``table``; starts, goals: (n,) cells; margin: steps a path may be longer than the
    distance. Rounds stop when one does not cut the collisions (after two), after
    ``max_rounds`` or when ``time_limit_s`` seconds of ``clock`` are spent (a round is not
    cut short). Returns ``prefer`` (:func:`~.kernels.prefer_table` of the next cell of each
    agent's path from each of its cells) and stats: ``rounds``, ``collisions`` (per round),
    ``time_s``. Memory: 12 bytes per (step, cell) for the collision tables and 8 per (agent,
    step) for the paths, steps being the longest distance + ``margin`` + 1; the result at most
    32 bytes per (agent, step) of the paths.
    """
    t0 = clock()
    n, ncell = starts.shape[0], nbr.shape[0]
    T = int(table[rows, starts].max()) + margin + 1 if n else 1
    paths = np.zeros((n, T), np.int64)
    lengths = np.zeros(n, np.int64)
    cnt = np.zeros((T, ncell), np.int32)
    who = np.full((T, ncell), -1, np.int64)
    park = np.full(ncell, 2 ** 30, np.int64)
    rng = np.random.default_rng(seed)
    coll: list[int] = []
    best = None
    while len(coll) < max_rounds and clock() - t0 < time_limit_s:
        coll.append(int(_round(nbr, table, rows, starts, goals, margin, rng.permutation(n).astype(np.int64),
                               paths, lengths, cnt, who, park)))
        if best is None or coll[-1] < best[0]:
            best = (coll[-1], paths.copy(), lengths.copy())
        if len(coll) >= 2 and coll[-1] >= coll[-2] or coll[-1] == 0:
            break
    if best is None:
        return NO_PREFER, {"rounds": 0, "collisions": [], "time_s": clock() - t0}
    return prefer_table(*_steps(best[1], best[2]), ncell), {"rounds": len(coll), "collisions": coll,
                                                             "time_s": clock() - t0}

