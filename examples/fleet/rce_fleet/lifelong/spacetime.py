"""Space-time planning for one-shot MAPF: a reservation table of who holds which cell at which
step, two exact searches for one agent around everybody in it (space-time A*, and safe-interval
path planning), and prioritized planning (PP: the agents one after another, each around those
before it; Silver, "Cooperative pathfinding", AIIDE 2005; Erdmann & Lozano-Perez 1987),
compiled with numba.

An agent is done when it stands on its goal and stays there: from its arrival on, its goal is
held to the horizon (the usual "parked at the goal" convention of sum-of-costs MAPF). A planned
path never enters a held cell, never swaps cells with an agent (edge conflict), and arrives at
its goal only after the last other agent has left it. The reservation table has three parts:

- ``occ`` (cells, H) int32: ``occ[c, t]`` the agent whose path is on cell ``c`` at step ``t``
  (up to its arrival), -1 free; read only to tell who would swap cells with whom;
- ``bits`` (cells, ceil(H / 64)) uint64: bit ``t % 64`` of word ``t // 64`` of row ``c`` set
  when ``occ[c, t]`` is taken, so that a search finds the next free or taken step of a cell
  by a count of trailing zeros (a row of ~600 steps is 10 words: the whole map's is ~0.3 MiB
  at 5,700 cells, and stays in the cache, where the int32 table is 14 MiB);
- ``park`` (cells,) int64: the step from which a cell is held to the horizon by the agent
  parked on it (its arrival), H for none. A goal held this way costs one entry, not a write at
  every step up to the horizon.

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
expands 4 - 5x fewer states for the same answers (:mod:`.refine`). Its safe intervals come
from ``bits`` and ``park``, a run of free steps at a time.
"""
from __future__ import annotations

import numpy as np
from numba import njit
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros

from .kernels import heap_pop, heap_push
from ..numba_cache import seed

seed(__file__)          # numba's cache entries prepared in the tree (sandboxed nodes)

__all__ = ["SpaceTimeTable", "fits", "plan_agents", "replan_group", "warm_up"]

_ALL = np.uint64(0xFFFFFFFFFFFFFFFF)


@njit(cache=True)
def _taken(bits, c, t):
    """Whether step ``t`` of cell ``c`` is taken in ``bits``."""
    return (bits[c, t >> 6] >> np.uint64(t & 63)) & np.uint64(1) != 0


@njit(cache=True)
def _next_step(bits, c, t, lim, taken):
    """The first step in [``t``, ``lim``) of cell ``c`` that is taken (``taken``) or free (not
    ``taken``) in ``bits``; ``lim`` when there is none (``lim`` <= 64 * words)."""
    if t >= lim:
        return lim
    w = t >> 6
    x = bits[c, w] if taken else ~bits[c, w]
    x &= _ALL << np.uint64(t & 63)
    while x == 0:
        w += 1
        if w << 6 >= lim:
            return lim
        x = bits[c, w] if taken else ~bits[c, w]
    s = (w << 6) + np.int64(trailing_zeros(x))
    return s if s < lim else lim


@njit(cache=True)
def _last_taken(bits, c):
    """The last taken step of cell ``c`` in ``bits``, -1 when none."""
    for w in range(bits.shape[1] - 1, -1, -1):
        x = bits[c, w]
        if x != 0:
            return (w << 6) + 63 - np.int64(leading_zeros(x))
    return -1


@njit(cache=True)
def _astar(nbr, h, start, goal, occ, park, ready, latest, stamp, sid, parent, link, bucket, max_expand, out, stats):
    """One agent from ``start`` (at t = 0) to ``goal`` (arrival at t >= ``ready``, and at t <=
    ``latest``: later paths are of no use to the caller and their states are never opened)
    around ``occ`` and ``park``. Writes the path into ``out`` (cells by step) and returns its
    length (arrival + 1), or 0 when there is none by ``latest`` or within ``max_expand``
    expansions. ``stamp``,
    ``parent``, ``link`` are (H * cells) scratch: a state is seen when ``stamp == sid``;
    ``bucket`` is ((H + max h + 2) * (max h + 1)) scratch of list heads, left all -1, with
    max h >= ``h[start]``."""
    ncell, H = occ.shape
    nb = bucket.shape[0]
    w = h[start] + 1                           # bucket = f * w + h: lowest f, then nearest
    if occ[start, 0] >= 0 or park[start] <= 0 or h[start] >= 65535 or max(h[start], ready) > latest:
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
            if occ[v, t + 1] >= 0 or t + 1 >= park[v]:
                continue
            if v != u:
                j = occ[v, t]
                if j >= 0 and occ[u, t + 1] == j:
                    continue
            nk = base + v
            if stamp[nk] == sid or t + 1 + h[v] > latest:
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
def _slot(node, key, sid):
    """The slot of state ``key`` in the open-addressing table ``node`` (rows [search id, key,
    arrival, parent slot], a power of two of them): its row when the search ``sid`` has it,
    else the free row where it goes (linear probing)."""
    m = node.shape[0] - 1
    i = ((key * 2654435761) >> 12) & m
    while node[i, 0] == sid and node[i, 1] != key:
        i = (i + 1) & m
    return i


@njit(cache=True)
def _sipp(nbr, h, start, goal, occ, bits, park, ready, latest, node, sid, hk, hv, max_expand, out, stats):
    """Safe-interval path planning (Phillips & Likhachev, ICRA 2011) for one agent from
    ``start`` (at t = 0) to ``goal`` (arrival at t >= ``ready``, the goal free from then to the
    horizon, and at t <= ``latest``, as :func:`_astar`) around the reservation table (``occ``,
    ``bits``, ``park``: module doc): the same paths as :func:`_astar` (earliest arrival,
    vertex and swap conflicts), but a state is a cell and one of its safe intervals (a maximal
    run of free steps), entered at the earliest step, so waiting costs no expansions.

    A state's key is (its interval's end - 1) * cells + cell. The states of one search live
    in ``node`` ((2^k, 4) int32: search id (``sid`` when in use), key, earliest arrival found,
    parent's row), a hash table of 16-byte rows that stays in the cache, where an array over
    all (step, cell) keys does not (at 1000 agents on the MovingAI warehouse that is 33 MiB and
    re-plans took ~1.3x as long); at half full the search gives up. ``hk``, ``hv``: heap
    scratch (its capacity bounds the pushes). Order: least f = max(t + h, ready), then least h,
    then latest t (a dive to the goal, as :func:`_astar`). Below ``ready`` f is flat, so a
    state may be expanded before its earliest arrival is known: a state reached earlier than
    before is opened again (without that, 26 of 200 re-plans at 1000 agents on the MovingAI
    warehouse came out later than :func:`_astar`'s or failed; with it, none). Writes the path
    into ``out`` and returns its length (arrival + 1), 0 when there is none by ``latest``, or
    within ``max_expand`` expansions, the heap or half the table."""
    ncell, H = occ.shape
    cap = hk.shape[0]
    full = node.shape[0] >> 1
    if park[start] <= 0 or _taken(bits, start, 0) or h[start] >= 65535 or max(h[start], ready) > latest:
        return 0
    mask = (1 << _TB) - 1
    e = _next_step(bits, start, 1, min(park[start], H), True)
    key = (e - 1) * ncell + start
    s = _slot(node, key, sid)
    node[s, 0] = sid
    node[s, 1] = key
    node[s, 2] = 0
    node[s, 3] = -1
    used = 1
    hs = np.int64(h[start])
    f = max(hs, ready)
    size = heap_push(hk, hv, 0, (np.int64(f) << (2 * _TB)) | (hs << _TB) | mask, s)
    expanded = 0
    found = -1
    while size > 0:
        pk, s, size = heap_pop(hk, hv, size)
        a = mask - (pk & mask)
        if node[s, 2] != a:
            continue                           # stale: reached earlier since
        expanded += 1
        key = node[s, 1]
        end = key // ncell + 1                 # exclusive end of the interval
        u = key - (end - 1) * ncell
        if u == goal and end == H and a >= ready:
            found = s
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
            lim = park[v]                      # held from then to the horizon
            top = min(wend, lim - 1, latest - hv_)     # latest useful arrival at v
            t = a + 1
            while t <= top:
                t = _next_step(bits, v, t, top + 1, False)
                if t > top:
                    break
                ev = _next_step(bits, v, t + 1, lim, True)     # the free run [t, ev)
                last = ev - 1 if ev - 1 < wend else wend
                tt = t
                # a swap: whoever was on v comes to u as this agent leaves it, so at the end of
                # u's free interval (the only step in reach at which u is taken)
                if tt == end and _taken(bits, v, tt - 1) and occ[u, tt] == occ[v, tt - 1]:
                    tt += 1
                if tt <= last and tt + hv_ <= latest:
                    nk = (ev - 1) * ncell + v
                    ns = _slot(node, nk, sid)
                    new = node[ns, 0] != sid
                    if new or tt < node[ns, 2]:            # (re)open: f is flat below ready
                        if size >= cap or (new and used >= full):
                            size = -1
                            break
                        used += new
                        node[ns, 0] = sid
                        node[ns, 1] = nk
                        node[ns, 2] = tt
                        node[ns, 3] = s
                        f = max(tt + hv_, ready)
                        size = heap_push(hk, hv, size, (np.int64(f) << (2 * _TB)) | (hv_ << _TB) | (mask - tt), ns)
                t = ev + 1
            if size < 0:
                break                          # out of room: give up
    stats[0] += expanded
    if found < 0:
        return 0
    t_end = node[found, 2]
    s = found
    until = t_end + 1
    while s >= 0:
        g = node[s, 2]
        c = node[s, 1] % ncell
        for t in range(g, until):
            out[t] = c
        until = g
        s = node[s, 3]
    return t_end + 1


@njit(cache=True)
def _place(occ, bits, park, a, path, length, goal):
    for t in range(length):
        c = path[t]
        occ[c, t] = a
        bits[c, t >> 6] |= np.uint64(1) << np.uint64(t & 63)
    park[goal] = length - 1


@njit(cache=True)
def _remove(occ, bits, park, path, length, goal):
    for t in range(length):
        c = path[t]
        occ[c, t] = -1
        bits[c, t >> 6] &= ~(np.uint64(1) << np.uint64(t & 63))
    park[goal] = occ.shape[1]


@njit(cache=True)
def _ready(bits, park, goal, H):
    """The first step from which nobody holds ``goal`` (H when it is held at the horizon)."""
    if park[goal] < H:
        return H
    return _last_taken(bits, goal) + 1


@njit(cache=True)
def plan_agents(nbr, table, hrow, starts, goals, agents, occ, bits, park, paths, lengths, stamp, sid, parent, link,
                bucket, max_expand, stats, sipp, node, hk, hv, budget):
    """Plan ``agents`` one after another (prioritized planning) into the reservation table
    (``occ``, ``bits``, ``park``: module doc), each around all the agents already in it, while
    their sum of lengths can stay within ``budget`` (each agent's search stops at the latest
    arrival that leaves the agents after it their distances).
    paths: (n, H) int64 cells per step, lengths: (n,) int64 (arrival + 1), both written for
    each agent planned. Returns (the number of agents planned, the next search id): when it is
    less than ``len(agents)``, agent ``agents[k]`` had no path and is not in the table; the
    agents before it are. ``sipp``: search by :func:`_sipp` (with its scratch ``node``,
    ``hk``, ``hv``) instead of :func:`_astar`."""
    H = occ.shape[1]
    rest = 0                                   # the least sum of lengths of the agents not planned
    for k in range(agents.shape[0]):
        rest += table[hrow[agents[k]], starts[agents[k]]] + 1
    for k in range(agents.shape[0]):
        a = agents[k]
        g = goals[a]
        rest -= table[hrow[a], starts[a]] + 1
        latest = min(budget - rest - 1, H - 1)
        ready = _ready(bits, park, g, H)
        if ready >= H - 1 or ready > latest:
            return k, sid
        sid += 1
        if sid >= 2 ** 31 - 2:
            stamp[:] = 0
            node[:, 0] = 0
            sid = 1
        if sipp:
            L = _sipp(nbr, table[hrow[a]], starts[a], g, occ, bits, park, ready, latest, node, sid, hk, hv, max_expand,
                      paths[a], stats)
        else:
            L = _astar(nbr, table[hrow[a]], starts[a], g, occ, park, ready, latest, stamp, sid, parent, link, bucket,
                       max_expand, paths[a], stats)
        if L == 0:
            return k, sid
        lengths[a] = L
        budget -= L
        _place(occ, bits, park, a, paths[a], L, g)
    return agents.shape[0], sid


@njit(cache=True)
def replan_group(nbr, table, hrow, starts, goals, group, occ, bits, park, paths, lengths, stamp, sid, parent, link,
                 bucket, max_expand, stats, sipp, node, hk, hv, old_paths, old_lengths):
    """One LNS step in one call: take ``group``'s paths out of the table, plan them again in
    that order (:func:`plan_agents`) and keep the new paths when all were found and their sum
    of (arrival + 1) is not higher, else put the old ones back. ``old_paths`` ((k, H)) and
    ``old_lengths`` ((k,)) receive the old paths. Returns (1 kept, 0 rolled back; the next
    search id)."""
    before = 0
    for i in range(group.shape[0]):
        a = group[i]
        old_paths[i, :] = paths[a]
        old_lengths[i] = lengths[a]
        before += lengths[a]
        _remove(occ, bits, park, paths[a], lengths[a], goals[a])
    k, sid = plan_agents(nbr, table, hrow, starts, goals, group, occ, bits, park, paths, lengths, stamp, sid, parent,
                         link, bucket, max_expand, stats, sipp, node, hk, hv, before)
    if k == group.shape[0]:
        return 1, sid                          # within the budget: not worse
    for i in range(k):
        a = group[i]
        _remove(occ, bits, park, paths[a], lengths[a], goals[a])
    for i in range(group.shape[0]):
        a = group[i]
        paths[a, :] = old_paths[i]
        lengths[a] = old_lengths[i]
        _place(occ, bits, park, a, paths[a], lengths[a], goals[a])
    return 0, sid


@njit(cache=True)
def fits(occ, bits, park, path, length, goal):
    """Whether a path (``path[:length]`` cells by step, then held on ``goal`` to the horizon)
    can join the table (``occ``, ``bits``, ``park``): no cell taken at its step, no exchange of
    cells with an agent in it, its goal free from its arrival on."""
    H = occ.shape[1]
    for t in range(length):
        c = path[t]
        if _taken(bits, c, t) or t >= park[c]:
            return False
        if t > 0 and c != path[t - 1] and _taken(bits, c, t - 1):
            if occ[path[t - 1], t] == occ[c, t - 1]:
                return False
    return park[goal] >= H and _next_step(bits, goal, length, H, True) >= H


@njit(cache=True)
def remove_agents(occ, bits, park, paths, lengths, goals, agents):
    """Take ``agents``' paths (and their parked goals) out of the table."""
    for a in agents:
        _remove(occ, bits, park, paths[a], lengths[a], goals[a])


@njit(cache=True)
def place_agents(occ, bits, park, paths, lengths, goals, agents):
    """Put ``agents``' paths (and their parked goals) into the table."""
    for a in agents:
        _place(occ, bits, park, a, paths[a], lengths[a], goals[a])


class SpaceTimeTable:
    """The reservation table (``occ``, ``bits``, ``park``: module doc) and the scratch of
    :func:`plan_agents` for ``n`` agents on ``n_cells`` cells up to step ``horizon``:
    ``paths`` (n, H) int64, ``lengths`` (n,) and the search arrays, each allocated when first
    used (about 16 bytes per (step, cell) for the space-time A*; for the search by safe
    intervals 128 bytes per state it may expand, up to 32 per (step, cell), and 32 MiB of
    heap), plus 8 bytes per (agent, step); ``max_h`` the largest start-to-goal distance.
    ``stats[0]`` counts the states expanded. Raises ValueError for more than 2 ** 31 (step,
    cell) pairs."""

    def __init__(self, n: int, n_cells: int, horizon: int, max_h: int):
        self.H = int(horizon)
        if self.H * n_cells >= 2 ** 31:
            raise ValueError(f"a space-time table holds up to 2 ** 31 (step, cell) pairs, got {self.H} x {n_cells}")
        self.occ = np.full((n_cells, self.H), -1, dtype=np.int32)
        self.bits = np.zeros((n_cells, (self.H + 63) // 64), dtype=np.uint64)
        self.park = np.full(n_cells, self.H, dtype=np.int64)
        self.paths = np.zeros((n, self.H), dtype=np.int64)
        self.lengths = np.zeros(n, dtype=np.int64)
        self.max_h = int(max_h)
        self.sid = 0
        self.stats = np.zeros(1, dtype=np.int64)      # states expanded, summed over searches
        none32 = np.zeros(1, np.int32)
        self._astar = (none32, none32, none32, none32)                      # stamp, parent, link, bucket
        self._sipp = (np.zeros((1, 4), np.int32), np.zeros(1, np.int64), np.zeros(1, np.int64))  # node, hk, hv
        self._old = (np.zeros((0, self.H), np.int64), np.zeros(0, np.int64))

    def _scratch(self, sipp: bool, max_expand: int) -> tuple:
        """The search arrays for ``sipp`` (or the A*), allocated on first use: for ``sipp`` a
        table of states with room for 4 per expansion (:func:`_sipp`; a re-plan at 1000 agents
        on the MovingAI warehouse reaches ~1.4 per expansion). Raises
        ValueError for ``sipp`` with a horizon of 2 ** 20 steps or more (the heap key's field
        for a step)."""
        m = self.H * self.occ.shape[0]
        if sipp:
            if self.H >= 2 ** _TB:
                raise ValueError(f"a search by safe intervals needs a horizon below {2 ** _TB} steps, got {self.H}")
            rows = 1 << int(min(8 * max_expand, 2 * m, 2 ** 30) + 63).bit_length()
            if self._sipp[0].shape[0] < rows:
                self._sipp = (np.zeros((rows, 4), np.int32), np.zeros(2 ** 21, np.int64), np.zeros(2 ** 21, np.int64))
            elif self.sid >= 2 ** 31 - 2 - 2 * len(self.lengths):      # the search ids wrap within this call:
                self._sipp[0][:, 0] = 0                                  # clear the rows past the view too
            # a view as large as this cap asks: after one long search the table stays large, and
            # hashing a small search over all of it costs ~10 % of an LNS run in cache misses
            return self._astar + (self.stats, sipp, self._sipp[0][:rows]) + self._sipp[1:]
        elif self._astar[0].shape[0] < m:
            nb = (self.H + self.max_h + 2) * (self.max_h + 1)
            self._astar = (np.zeros(m, np.int32), np.empty(m, np.int32), np.empty(m, np.int32),
                           np.full(nb, -1, dtype=np.int32))
        return self._astar + (self.stats, sipp) + self._sipp

    def plan(self, nbr, table, hrow, starts, goals, agents, max_expand: int, sipp: bool = False) -> int:
        """:func:`plan_agents` on this table, by space-time A* or, with ``sipp``, by safe
        intervals; returns how many of ``agents`` were planned. Raises ValueError for ``sipp``
        with a horizon of 2 ** 20 steps or more (the heap key's field for a step)."""
        stamp, parent, link, bucket, *rest = self._scratch(sipp, max_expand)
        k, self.sid = plan_agents(nbr, table, hrow, starts, goals, np.asarray(agents, dtype=np.int64), self.occ,
                                  self.bits, self.park, self.paths, self.lengths, stamp, self.sid, parent, link,
                                  bucket, max_expand, *rest, 2 ** 62)
        return int(k)

    def replan(self, nbr, table, hrow, starts, goals, group: np.ndarray, max_expand: int, sipp: bool = False) -> bool:
        """:func:`replan_group`: re-plan ``group`` ((k,) int64 agents, in this order) and keep
        the new paths when all were found and their sum of costs is not higher (True), else
        keep the old ones (False). Raises as :meth:`plan`."""
        stamp, parent, link, bucket, *rest = self._scratch(sipp, max_expand)
        if self._old[1].shape[0] < group.shape[0]:
            self._old = (np.zeros((group.shape[0], self.H), np.int64), np.zeros(group.shape[0], np.int64))
        kept, self.sid = replan_group(nbr, table, hrow, starts, goals, group, self.occ, self.bits, self.park,
                                      self.paths, self.lengths, stamp, self.sid, parent, link, bucket, max_expand,
                                      *rest, *self._old)
        return bool(kept)

    def fits(self, path: np.ndarray, length: int, goal: int) -> bool:
        """:func:`fits`: whether ``path[:length]`` (cells by step, then held on ``goal``) can
        join the table."""
        return bool(fits(self.occ, self.bits, self.park, path, length, goal))

    def place(self, goals: np.ndarray, agents) -> None:
        """Put ``agents``' paths (``paths``, ``lengths``) and their parked ``goals`` ((n,) cells)
        into the table."""
        place_agents(self.occ, self.bits, self.park, self.paths, self.lengths, goals,
                     np.asarray(agents, dtype=np.int64))

    def remove(self, goals: np.ndarray, agents) -> None:
        """Take ``agents``' paths and parked ``goals`` out of the table."""
        remove_agents(self.occ, self.bits, self.park, self.paths, self.lengths, goals,
                      np.asarray(agents, dtype=np.int64))


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels on a 2 x 2 grid."""
    from .grid import LifelongGrid
    g = LifelongGrid(np.ones((2, 2), dtype=bool))
    table = np.array([[2, 1, 1, 0], [0, 1, 1, 2]], dtype=np.uint16)
    r = SpaceTimeTable(2, 4, 6, 2)
    starts = np.array([0, 3], dtype=np.int64)
    goals = np.array([3, 0], dtype=np.int64)
    hrow = np.array([0, 1], dtype=np.int64)
    for sipp in (False, True):
        r.remove(goals, [0, 1])
        r.plan(g.nbr, table, hrow, starts, goals, [0, 1], 100, sipp)
        r.replan(g.nbr, table, hrow, starts, goals, np.array([1, 0], dtype=np.int64), 100, sipp)
    r.remove(goals, [0])
    r.fits(r.paths[0], r.lengths[0], goals[0])
    r.place(goals, [0])
