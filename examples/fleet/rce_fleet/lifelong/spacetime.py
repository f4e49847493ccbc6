"""Space-time planning for one-shot MAPF: a reservation table of who holds which cell at which
step, two exact searches for one agent around everybody in it (space-time A*, and safe-interval
path planning), and prioritized planning (PP: the agents one after another, each around those
before it; Silver, "Cooperative pathfinding", AIIDE 2005; Erdmann & Lozano-Perez 1987),
compiled with numba.

The reservation table ``occ`` is (cells, H) int32: ``occ[c, t]`` the agent on cell ``c`` at
step ``t``, -1 free (one cell's steps contiguous, for the safe-interval scans). An agent is
done when it stands on its goal and stays there: from its arrival on, its goal is held to the
horizon (the usual "parked at the goal" convention of sum-of-costs MAPF). A planned path never
enters a held cell, never swaps cells with an agent (edge conflict), and arrives at its goal
only after the last other agent has left it.

The space-time A* (:func:`_astar`): states (t, cell) with unit steps, so the cost of a state
is its ``t`` and a state is final when first generated; ``f = max(t + h, ready)`` with ``h``
the breadth-first distance to the goal and ``ready`` the step after the goal is last held by
another agent. Open states sit in a bucket queue keyed by ``f``, then by ``h`` (nearest the
goal first), last in first out within a bucket: no heap, and a search that dives to the goal
and waits near it instead of flooding space-time while the goal is still in use (measured on
the MovingAI warehouse at 400 agents: the same LNS does 3,800 iterations in 3 s against 480
with a heap on ``f`` alone).

SIPP (:func:`_sipp`, Phillips & Likhachev, ICRA 2011): states (cell, safe interval), the same
order and the same arrivals, but a wait is no expansion; in the LNS re-plans at 1000 agents it
expands 4 - 5x fewer states for the same answers (:mod:`.refine`).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .kernels import heap_pop, heap_push
from ..numba_cache import seed

seed(__file__)          # numba's cache entries prepared in the tree (sandboxed nodes)

__all__ = ["SpaceTimeTable", "fits", "plan_agents", "warm_up"]


@njit(cache=True)
def _astar(nbr, h, start, goal, occ, ready, stamp, sid, parent, link, bucket, max_expand, out, stats):
    """One agent from ``start`` (at t = 0) to ``goal`` (arrival at t >= ``ready``) around
    ``occ``. Writes the path into ``out`` (cells by step) and returns its length (arrival + 1),
    or 0 when there is none within the horizon or ``max_expand`` expansions. ``stamp``,
    ``parent``, ``link`` are (H * cells) scratch: a state is seen when ``stamp == sid``;
    ``bucket`` is ((H + max h + 2) * (max h + 1)) scratch of list heads, left all -1, with
    max h >= ``h[start]``."""
    ncell, H = occ.shape
    nb = bucket.shape[0]
    w = h[start] + 1                           # bucket = f * w + h: lowest f, then nearest
    if occ[start, 0] >= 0 or h[start] >= 65535:
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
            if occ[v, t + 1] >= 0:
                continue
            if v != u:
                j = occ[v, t]
                if j >= 0 and occ[u, t + 1] == j:
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


_TB = 20                                       # bits of the step and of h in a heap key


@njit(cache=True)
def _sipp(nbr, h, start, goal, occ, hi, ready, goals, lengths, stamp, sid, parent, arrive, hk, hv, max_expand,
          out, stats):
    """Safe-interval path planning (Phillips & Likhachev, ICRA 2011) for one agent from
    ``start`` (at t = 0) to ``goal`` (arrival at t >= ``ready``, the goal free from then to the
    horizon) around ``occ`` ((cells, H); ``goals`` and ``lengths`` of the agents in it tell
    where one is parked to the horizon, ``hi`` bounds the last step of a path on each cell):
    the same paths as :func:`_astar` (earliest arrival,
    vertex and swap conflicts), but a state is a cell and one of its safe intervals (a maximal
    run of free steps), entered at the earliest step, so waiting costs no expansions.

    A state's key is (its interval's end - 1) * cells + cell. ``stamp`` (seen when == ``sid``),
    ``arrive`` (earliest step found), ``parent`` (key): (H * cells) scratch; ``hk``, ``hv``:
    heap scratch (its capacity bounds the pushes). Order: least f = max(t + h, ready), then
    least h, then latest t (a dive to the goal, as :func:`_astar`). Below ``ready`` f is flat,
    so a state may be expanded before its earliest arrival is known: a state reached earlier
    than before is opened again (without that, 26 of 200 re-plans at 1000 agents on the
    MovingAI warehouse came out later than :func:`_astar`'s or failed; with it, none).
    Writes the path into ``out`` and returns its length (arrival + 1), 0 when there is none
    within the horizon, ``max_expand`` expansions or the heap."""
    ncell, H = occ.shape
    cap = hk.shape[0]
    if occ[start, 0] >= 0 or h[start] >= 65535 or ready >= H:
        return 0
    mask = (1 << _TB) - 1
    e = 1
    while e < H and occ[start, e] < 0:
        e += 1
    key = (e - 1) * ncell + start
    stamp[key] = sid
    arrive[key] = 0
    parent[key] = -1
    hs = np.int64(h[start])
    f = max(hs, ready)
    size = heap_push(hk, hv, 0, (np.int64(f) << (2 * _TB)) | (hs << _TB) | mask, key)
    expanded = 0
    found = -1
    while size > 0:
        pk, key, size = heap_pop(hk, hv, size)
        a = mask - (pk & mask)
        if arrive[key] != a:
            continue                           # stale: reached earlier since
        expanded += 1
        end = key // ncell + 1                 # exclusive end of the interval
        u = key - (end - 1) * ncell
        if u == goal and end == H and a >= ready:
            found = key
            break
        if expanded > max_expand:
            break
        wend = end if end < H else H - 1       # latest arrival at a neighbour
        for d in range(4):
            v = nbr[u, d]
            if v < 0:
                continue
            hv_ = np.int64(h[v])
            if hv_ >= 65535:
                continue
            t = a + 1
            while t <= wend:
                j = occ[v, t]
                if j >= 0:
                    if goals[j] == v and t >= lengths[j] - 1:
                        break                  # parked there to the horizon
                    t += 1
                    continue
                ev = t + 1                     # the free run [t, ev)
                while ev < H and occ[v, ev] < 0:
                    if ev > hi[v]:             # no path on v after: free to the horizon
                        ev = H
                        break
                    ev += 1
                last = ev - 1 if ev - 1 < wend else wend
                tt = t
                while tt <= last:              # no swap with whoever was on v
                    j = occ[v, tt - 1]
                    if j < 0 or occ[u, tt] != j:
                        break
                    tt += 1
                if tt <= last and tt + hv_ < H:
                    nk = (ev - 1) * ncell + v
                    if stamp[nk] != sid or tt < arrive[nk]:    # (re)open: f is flat below ready
                        if size >= cap:
                            break
                        stamp[nk] = sid
                        arrive[nk] = tt
                        parent[nk] = key
                        f = max(tt + hv_, ready)
                        size = heap_push(hk, hv, size, (np.int64(f) << (2 * _TB)) | (hv_ << _TB) | (mask - tt), nk)
                t = ev + 1
    stats[0] += expanded
    if found < 0:
        return 0
    t_end = arrive[found]
    key = found
    until = t_end + 1
    while key >= 0:
        g = arrive[key]
        c = key % ncell
        for t in range(g, until):
            out[t] = c
        until = g
        key = parent[key]
    return t_end + 1


@njit(cache=True)
def _place(occ, hi, a, path, length, goal):
    for t in range(length):
        occ[path[t], t] = a
        if hi[path[t]] < t:
            hi[path[t]] = t
    for t in range(length, occ.shape[1]):
        occ[goal, t] = a


@njit(cache=True)
def _remove(occ, path, length, goal):
    for t in range(length):
        occ[path[t], t] = -1
    for t in range(length, occ.shape[1]):
        occ[goal, t] = -1


@njit(cache=True)
def _ready(occ, goal):
    """The first step from which nobody holds ``goal`` (H when it is held at the horizon)."""
    t = occ.shape[1]
    while t > 0 and occ[goal, t - 1] < 0:
        t -= 1
    return t


@njit(cache=True)
def plan_agents(nbr, table, hrow, starts, goals, agents, occ, hi, paths, lengths, stamp, sid, parent, link, bucket,
                max_expand, stats, sipp, arrive, hk, hv):
    """Plan ``agents`` one after another (prioritized planning) into ``occ``, each around all
    the agents already in it. paths: (n, H) int64 cells per step, lengths: (n,) int64 (arrival
    + 1), both written for each agent planned. Returns (the number of agents planned, the next
    search id): when it is less than ``len(agents)``, agent ``agents[k]`` had no path and
    is not in ``occ``; the agents before it are. ``sipp``: search by :func:`_sipp` (with its
    scratch ``arrive``, ``hk``, ``hv``) instead of :func:`_astar`."""
    for k in range(agents.shape[0]):
        a = agents[k]
        g = goals[a]
        ready = _ready(occ, g)
        if ready >= occ.shape[1] - 1:
            return k, sid
        sid += 1
        if sid >= 2 ** 31 - 2:
            stamp[:] = 0
            sid = 1
        if sipp:
            L = _sipp(nbr, table[hrow[a]], starts[a], g, occ, hi, ready, goals, lengths, stamp, sid, parent,
                      arrive, hk, hv, max_expand, paths[a], stats)
        else:
            L = _astar(nbr, table[hrow[a]], starts[a], g, occ, ready, stamp, sid, parent, link, bucket, max_expand,
                       paths[a], stats)
        if L == 0:
            return k, sid
        lengths[a] = L
        _place(occ, hi, a, paths[a], L, g)
    return agents.shape[0], sid


@njit(cache=True)
def fits(occ, path, length, goal):
    """Whether a path (``path[:length]`` cells by step, then held on ``goal`` to the horizon)
    can join ``occ``: no cell taken at its step, no exchange of cells with an agent in it, its
    goal free from its arrival on."""
    for t in range(length):
        if occ[path[t], t] >= 0:
            return False
        if t > 0 and path[t] != path[t - 1]:
            j = occ[path[t], t - 1]
            if j >= 0 and occ[path[t - 1], t] == j:
                return False
    for t in range(length, occ.shape[1]):
        if occ[goal, t] >= 0:
            return False
    return True


@njit(cache=True)
def remove_agents(occ, paths, lengths, goals, agents):
    """Take ``agents``' paths (and their parked goals) out of ``occ``."""
    for a in agents:
        _remove(occ, paths[a], lengths[a], goals[a])


@njit(cache=True)
def place_agents(occ, hi, paths, lengths, goals, agents):
    """Put ``agents``' paths (and their parked goals) into ``occ``; ``hi`` (cells,) keeps a
    bound on the last step of a path on each cell (never lowered)."""
    for a in agents:
        _place(occ, hi, a, paths[a], lengths[a], goals[a])


class SpaceTimeTable:
    """The scratch of :func:`plan_agents` for ``n`` agents on ``n_cells`` cells up to step
    ``horizon``: ``occ`` (cells, H) int32, ``paths`` (n, H) int64, ``lengths`` (n,) and the
    search arrays (about 16 bytes per (step, cell) plus 8 per (agent, step), 4 more per (step,
    cell) and 32 MiB of heap once a search by safe intervals runs); ``max_h`` the largest
    start-to-goal distance. ``stats[0]`` counts the states expanded."""

    def __init__(self, n: int, n_cells: int, horizon: int, max_h: int):
        self.H = int(horizon)
        self.occ = np.full((n_cells, self.H), -1, dtype=np.int32)
        self.hi = np.full(n_cells, -1, dtype=np.int64)
        self.paths = np.zeros((n, self.H), dtype=np.int64)
        self.lengths = np.zeros(n, dtype=np.int64)
        self.stamp = np.zeros(self.H * n_cells, dtype=np.int32)
        self.parent = np.empty(self.H * n_cells, dtype=np.int32)
        self.link = np.empty(self.H * n_cells, dtype=np.int32)
        self.bucket = np.full((self.H + max_h + 2) * (max_h + 1), -1, dtype=np.int32)
        self.sid = 0
        self.stats = np.zeros(1, dtype=np.int64)      # states expanded, summed over searches
        self._sipp = (np.zeros(1, np.int32), np.zeros(1, np.int64), np.zeros(1, np.int64))

    def plan(self, nbr, table, hrow, starts, goals, agents, max_expand: int, sipp: bool = False) -> int:
        """:func:`plan_agents` on this scratch, by space-time A* or, with ``sipp``, by safe
        intervals; returns how many of ``agents`` were planned. Raises ValueError for ``sipp``
        with a horizon of 2 ** 20 steps or more (the heap key's field for a step)."""
        if sipp and self.H >= 2 ** _TB:
            raise ValueError(f"a search by safe intervals needs a horizon below {2 ** _TB} steps, got {self.H}")
        if sipp and self._sipp[0].shape[0] < self.stamp.shape[0]:
            m = self.stamp.shape[0]
            self._sipp = (np.zeros(m, np.int32), np.zeros(2 ** 21, np.int64), np.zeros(2 ** 21, np.int64))
        k, self.sid = plan_agents(nbr, table, hrow, starts, goals, np.asarray(agents, dtype=np.int64), self.occ,
                                  self.hi, self.paths, self.lengths, self.stamp, self.sid, self.parent, self.link,
                                  self.bucket, max_expand, self.stats, sipp, *self._sipp)
        return int(k)

    def place(self, goals: np.ndarray, agents) -> None:
        """Put ``agents``' paths (``paths``, ``lengths``) and their parked ``goals`` ((n,) cells)
        into ``occ``."""
        place_agents(self.occ, self.hi, self.paths, self.lengths, goals, np.asarray(agents, dtype=np.int64))

    def remove(self, goals: np.ndarray, agents) -> None:
        """Take ``agents``' paths and parked ``goals`` out of ``occ``."""
        remove_agents(self.occ, self.paths, self.lengths, goals, np.asarray(agents, dtype=np.int64))


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels on a 2 x 2 grid."""
    from .grid import LifelongGrid
    g = LifelongGrid(np.ones((2, 2), dtype=bool))
    table = np.array([[2, 1, 1, 0], [0, 1, 1, 2]], dtype=np.uint16)
    r = SpaceTimeTable(2, 4, 6, 2)
    starts = np.array([0, 3], dtype=np.int64)
    goals = np.array([3, 0], dtype=np.int64)
    for sipp in (False, True):
        r.remove(goals, [0, 1])
        r.plan(g.nbr, table, np.array([0, 1], dtype=np.int64), starts, goals, [0, 1], 100, sipp)
    r.remove(goals, [0])
    fits(r.occ, r.paths[0], r.lengths[0], goals[0])
    r.place(goals, [0])

