"""Space-time planning for one-shot MAPF: a reservation table of who holds which cell at which
step, a space-time A* for one agent around everybody in it, and prioritized planning (PP: the
agents one after another, each around those before it; Silver, "Cooperative pathfinding",
AIIDE 2005; Erdmann & Lozano-Perez 1987), compiled with numba.

The reservation table ``occ`` is (H, cells) int32: ``occ[t, c]`` the agent on cell ``c`` at
step ``t``, -1 free. An agent is done when it stands on its goal and stays there: from its
arrival on, its goal is held to the horizon (the usual "parked at the goal" convention of
sum-of-costs MAPF). A planned path never enters a held cell, never swaps cells with an agent
(edge conflict), and arrives at its goal only after the last other agent has left it.

The search: states (t, cell) with unit steps, so the cost of a state is its ``t`` and a state
is final when first generated; ``f = max(t + h, ready)`` with ``h`` the breadth-first
distance to the goal and ``ready`` the step after the goal is last held by another agent.
Open states sit in a bucket queue keyed by ``f``, then by ``h`` (nearest the goal first), last
in first out within a bucket: no heap, and a search that dives to the goal and waits near it
instead of flooding space-time while the goal is still in use (measured on the MovingAI
warehouse at 400 agents: the same LNS does 3,800 iterations in 3 s against 480 with a heap
on ``f`` alone).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ..numba_cache import seed

seed(__file__)          # numba's cache entries prepared in the tree (sandboxed nodes)

__all__ = ["SpaceTimeTable", "plan_agents", "warm_up"]


@njit(cache=True)
def _astar(nbr, h, start, goal, occ, ready, stamp, sid, parent, link, bucket, max_expand, out, stats):
    """One agent from ``start`` (at t = 0) to ``goal`` (arrival at t >= ``ready``) around
    ``occ``. Writes the path into ``out`` (cells by step) and returns its length (arrival + 1),
    or 0 when there is none within the horizon or ``max_expand`` expansions. ``stamp``,
    ``parent``, ``link`` are (H * cells) scratch: a state is seen when ``stamp == sid``;
    ``bucket`` is ((H + max h + 2) * (max h + 1)) scratch of list heads, left all -1, with
    max h >= ``h[start]``."""
    H, ncell = occ.shape
    nb = bucket.shape[0]
    w = h[start] + 1                           # bucket = f * w + h: lowest f, then nearest
    if occ[0, start] >= 0 or h[start] >= 65535:
        return 0
    b0 = max(h[start], ready) * w + h[start]
    if b0 >= nb:
        return 0
    bucket[b0] = start
    link[start] = -1
    stamp[start] = sid
    parent[start] = -1
    bmin = b0
    bmax = b0
    expanded = 0
    found = -1
    while bmin <= bmax:
        key = bucket[bmin]
        if key < 0:
            bmin += 1
            continue
        bucket[bmin] = link[key]
        expanded += 1
        t = key // ncell
        u = key - t * ncell
        if u == goal and t >= ready:
            found = key
            break
        if expanded > max_expand:
            break
        if t + 1 >= H:
            continue
        base = (t + 1) * ncell
        for d in range(5):
            v = u if d == 4 else nbr[u, d]
            if v < 0:
                continue
            if occ[t + 1, v] >= 0:
                continue
            if v != u:
                j = occ[t, v]
                if j >= 0 and occ[t + 1, u] == j:
                    continue
            nk = base + v
            if stamp[nk] == sid:
                continue
            hv = h[v]
            if hv >= w:                        # farther than the start: last among equal f
                if hv >= 65535 or t + 1 + hv >= H:
                    continue
                hv = w - 1
            stamp[nk] = sid
            parent[nk] = key
            b = max(t + 1 + h[v], ready) * w + hv
            if b >= nb:
                continue
            link[nk] = bucket[b]
            bucket[b] = nk
            if b > bmax:
                bmax = b
            if b < bmin:
                bmin = b
    for b in range(bmin, bmax + 1):            # leave the buckets empty for the next call
        bucket[b] = -1
    stats[0] += expanded
    if found < 0:
        return 0
    t = found // ncell
    key = found
    for k in range(t, -1, -1):
        out[k] = key % ncell
        key = parent[key]
    return t + 1


@njit(cache=True)
def _place(occ, a, path, length, goal):
    for t in range(length):
        occ[t, path[t]] = a
    for t in range(length, occ.shape[0]):
        occ[t, goal] = a


@njit(cache=True)
def _remove(occ, path, length, goal):
    for t in range(length):
        occ[t, path[t]] = -1
    for t in range(length, occ.shape[0]):
        occ[t, goal] = -1


@njit(cache=True)
def _ready(occ, goal):
    """The first step from which nobody holds ``goal`` (H when it is held at the horizon)."""
    t = occ.shape[0]
    while t > 0 and occ[t - 1, goal] < 0:
        t -= 1
    return t


@njit(cache=True)
def plan_agents(nbr, table, hrow, starts, goals, agents, occ, paths, lengths, stamp, sid, parent, link, bucket,
                max_expand, stats):
    """Plan ``agents`` one after another (prioritized planning) into ``occ``, each around all
    the agents already in it. paths: (n, H) int64 cells per step, lengths: (n,) int64 (arrival
    + 1), both written for each agent planned. Returns (the number of agents planned, the next
    search id): when it is less than ``len(agents)``, agent ``agents[k]`` had no path and
    is not in ``occ``; the agents before it are."""
    for k in range(agents.shape[0]):
        a = agents[k]
        g = goals[a]
        ready = _ready(occ, g)
        if ready >= occ.shape[0] - 1:
            return k, sid
        sid += 1
        if sid >= 2 ** 31 - 2:
            stamp[:] = 0
            sid = 1
        L = _astar(nbr, table[hrow[a]], starts[a], g, occ, ready, stamp, sid, parent, link, bucket, max_expand,
                   paths[a], stats)
        if L == 0:
            return k, sid
        lengths[a] = L
        _place(occ, a, paths[a], L, g)
    return agents.shape[0], sid


@njit(cache=True)
def remove_agents(occ, paths, lengths, goals, agents):
    """Take ``agents``' paths (and their parked goals) out of ``occ``."""
    for a in agents:
        _remove(occ, paths[a], lengths[a], goals[a])


@njit(cache=True)
def place_agents(occ, paths, lengths, goals, agents):
    """Put ``agents``' paths (and their parked goals) into ``occ``."""
    for a in agents:
        _place(occ, a, paths[a], lengths[a], goals[a])


class SpaceTimeTable:
    """The scratch of :func:`plan_agents` for ``n`` agents on ``n_cells`` cells up to step
    ``horizon``: ``occ`` (H, cells) int32, ``paths`` (n, H) int64, ``lengths`` (n,) and the
    search arrays (about 16 bytes per (step, cell) plus 8 per (agent, step)); ``max_h`` the
    largest start-to-goal distance. ``stats[0]`` counts the states expanded."""

    def __init__(self, n: int, n_cells: int, horizon: int, max_h: int):
        self.H = int(horizon)
        self.occ = np.full((self.H, n_cells), -1, dtype=np.int32)
        self.paths = np.zeros((n, self.H), dtype=np.int64)
        self.lengths = np.zeros(n, dtype=np.int64)
        self.stamp = np.zeros(self.H * n_cells, dtype=np.int32)
        self.parent = np.empty(self.H * n_cells, dtype=np.int32)
        self.link = np.empty(self.H * n_cells, dtype=np.int32)
        self.bucket = np.full((self.H + max_h + 2) * (max_h + 1), -1, dtype=np.int32)
        self.sid = 0
        self.stats = np.zeros(1, dtype=np.int64)      # states expanded, summed over searches

    def plan(self, nbr, table, hrow, starts, goals, agents, max_expand: int) -> int:
        """:func:`plan_agents` on this scratch; returns how many of ``agents`` were planned."""
        k, self.sid = plan_agents(nbr, table, hrow, starts, goals, np.asarray(agents, dtype=np.int64), self.occ,
                                  self.paths, self.lengths, self.stamp, self.sid, self.parent, self.link,
                                  self.bucket, max_expand, self.stats)
        return int(k)


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels on a 2 x 2 grid."""
    from .grid import LifelongGrid
    g = LifelongGrid(np.ones((2, 2), dtype=bool))
    table = np.array([[2, 1, 1, 0], [0, 1, 1, 2]], dtype=np.uint16)
    r = SpaceTimeTable(2, 4, 6, 2)
    starts = np.array([0, 3], dtype=np.int64)
    goals = np.array([3, 0], dtype=np.int64)
    r.plan(g.nbr, table, np.array([0, 1], dtype=np.int64), starts, goals, [0, 1], 100)
    remove_agents(r.occ, r.paths, r.lengths, goals, np.array([0], dtype=np.int64))
    place_agents(r.occ, r.paths, r.lengths, goals, np.array([0], dtype=np.int64))

