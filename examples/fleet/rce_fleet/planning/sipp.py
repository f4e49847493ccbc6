"""One robot's path around the reservations of the robots planned before it: space-time A*
over safe intervals (SIPP: Phillips & Likhachev 2011, "SIPP: Safe Interval Path Planning
for Dynamic Environments", ICRA), weighted (Pohl 1970, "Heuristic search viewed as path
finding in a graph", Artificial Intelligence 1).

A safe interval of a cell is a maximal run of plan steps in which nobody holds it. A
search state is (cell, safe interval), reached at its earliest step; waiting is implicit
(a robot waits in its cell until it can enter the next), which keeps the search small
even when a robot must wait a long time.
"""
from __future__ import annotations

import bisect
import heapq
import math
import time
from collections.abc import Sequence

from .reservations import Reservations

__all__ = ["SearchDeadline", "safe_interval_astar"]

INF = math.inf
DEADLINE_EVERY = 64        # expansions between looks at the clock


class SearchDeadline(Exception):
    """A search passed its ``deadline`` (:func:`safe_interval_astar`) before it ended."""


def _start_interval_end(res: Reservations, start: int, t0: int) -> float:
    """Last step of the start cell's safe interval that holds ``t0`` (the robot is there)."""
    ts = res.occ.get(start, ())
    k = bisect.bisect_right(ts, t0)
    e0 = ts[k] - 1 if k < len(ts) else INF
    p = res.parked.get(start)
    if p is not None and p - 1 < e0:
        e0 = p - 1
    return t0 if e0 < t0 else e0


def _path(info: dict[int, tuple[int, int, float, int]], skey: int) -> list[int]:
    """The cells for every step from the start to state ``skey``, waits filled in."""
    cells = []
    while skey != -1:
        c, g, _, par = info[skey]
        cells.append((c, g))
        skey = par
    cells.reverse()
    path: list[int] = []
    for (c, g), nxt in zip(cells, cells[1:] + [None], strict=True):
        until = nxt[1] if nxt is not None else g + 1
        path.extend([c] * (until - g))
    return path


def _successors(res: Reservations, nbrs_u: Sequence[int], heuristic: Sequence[float], cell: int, arrival: int,
                safe_until: float) -> list[tuple[int, int, float, int, float]]:
    """The states a robot in ``cell`` (arrived at step ``arrival``, safe there until ``safe_until``) can move
    to: ``(state key, arrival step, interval end, cell, h of the cell)`` for every safe interval
    of every neighbour it can reach, arriving as early as it can without swapping cells with
    whoever is in the neighbour or closing a rotation."""
    N, vertex, occ, parked = res.n, res.vertex, res.occ, res.parked
    bisect_right = bisect.bisect_right
    lo, hi = arrival + 1, safe_until + 1                    # earliest and latest arrival at a neighbour
    out = []
    for v in nbrs_u:
        hv = heuristic[v]
        if hv == INF:
            continue
        vts = occ.get(v)
        pv = parked.get(v, INF)
        if vts is None:
            k, nv, s_int = 0, 0, 0
        else:
            nv = len(vts)
            k = bisect_right(vts, lo)
            s_int = vts[k - 1] + 1 if k > 0 else 0
        while s_int <= hi and s_int < pv:
            e_int = vts[k] - 1 if k < nv else INF
            if e_int > pv - 1:
                e_int = pv - 1
            if e_int >= s_int and e_int >= lo:
                t_arr = lo if lo > s_int else s_int
                last_ok = e_int if e_int < hi else hi
                # following whoever is in v at t_arr - 1: no swap, no rotation
                while t_arr <= last_ok:
                    o = vertex.get((t_arr - 1) * N + v)
                    if o is None:
                        break
                    if vertex.get(t_arr * N + cell) != o and not res.closes_rotation(cell, v, t_arr - 1):
                        break
                    t_arr += 1
                if t_arr <= last_ok:
                    out.append((s_int * N + v, t_arr, e_int, v, hv))
            if k >= nv:
                break
            s_int = vts[k] + 1
            k += 1
    return out


def safe_interval_astar(nbrs: Sequence[Sequence[int]], start: int, goal: int, heuristic: Sequence[float],
                        res: Reservations, max_expansions: int, t0: int = 0,
                        weight: float = 1.0, deadline: float = INF) -> list[int] | None:
    """Space-time A* over safe intervals (SIPP, Phillips & Likhachev 2011, ICRA).

    Finds a path for one robot from ``start`` at step ``t0`` to ``goal``
    around the reservations ``res``: never in a reserved (cell, step), never
    in a parked cell from its park step on, never swapping cells with the
    owner of its target cell nor closing a rotation (a cycle of robots each
    following the next, which ordered execution could not carry out), and
    arriving in the goal's last, unbounded safe interval, so the robot can stay
    there for ever.

    ``nbrs[cell]``: the cells a robot can move to. ``h[cell]``: exact distance to
    ``goal`` ignoring other robots (inf = unreachable: pruned). Ordering
    ``f = g + weight * max(h, G + 1 - g)`` (G: last reserved step of the goal cell),
    ties to smaller h then later g. ``weight`` 1 gives the earliest arrival; slightly
    above 1 (weighted A*) avoids expanding the large ties of 4-connected grids and
    keeps the arrival within ``weight`` x optimal. ``max_expansions`` bounds work;
    ``deadline`` (``time.perf_counter()`` s) bounds its wall time: past it the search raises
    :class:`SearchDeadline`.

    Returns cells for steps ``t0 .. arrival`` (``path[0] == start``), or None.
    """
    N = res.n
    if heuristic[start] == INF or goal in res.parked:
        return None
    G1 = res.last(goal) + 1
    w = weight
    s_key = t0 * N + start
    best = {s_key: t0}
    info = {s_key: (start, t0, _start_interval_end(res, start, t0), -1)}   # state -> (cell, arrival, end, parent)
    h0 = heuristic[start]
    open_ = [(t0 + w * (h0 if h0 > G1 - t0 else G1 - t0), h0, -t0, s_key)]
    closed: set[int] = set()
    push, pop = heapq.heappush, heapq.heappop
    expansions = 0
    while open_:
        skey = pop(open_)[3]
        if skey in closed:
            continue
        closed.add(skey)
        u, a, e, _ = info[skey]
        if u == goal and e == INF:
            return _path(info, skey)
        expansions += 1
        if expansions > max_expansions:
            return None
        if expansions % DEADLINE_EVERY == 0 and time.perf_counter() > deadline:
            raise SearchDeadline(f"search from cell {start} to {goal} passed its deadline")
        for key, t_arr, e_int, v, hv in _successors(res, nbrs[u], heuristic, u, a, e):
            if key not in closed and t_arr < best.get(key, INF):
                best[key] = t_arr
                info[key] = (v, t_arr, e_int, skey)
                rest = G1 - t_arr
                push(open_, (t_arr + w * (hv if hv > rest else rest), hv, -t_arr, key))
    return None
