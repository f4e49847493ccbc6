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

import math
from collections.abc import Sequence

import numpy as np

from .reservations import Reservations
from .sipp_kernel import sipp_search

__all__ = ["safe_interval_astar"]

INF = math.inf
_GRAPHS_KEPT = 8            # neighbour arrays kept (one per graph searched)


class _Scratch:
    """The search's scratch arrays (one set, grown to the largest table searched)."""

    def __init__(self):
        self.size, self.sid = 0, 0
        self.graphs: dict[int, tuple[Sequence[Sequence[int]], np.ndarray, np.ndarray]] = {}

    def neighbours(self, nbrs: Sequence[Sequence[int]]) -> tuple[np.ndarray, np.ndarray]:
        """``nbrs`` as (cells, 4) int64 and (cells,) counts, cached per graph."""
        got = self.graphs.get(id(nbrs))
        if got is None or got[0] is not nbrs:
            if len(self.graphs) >= _GRAPHS_KEPT:
                self.graphs.clear()
            arr = np.full((len(nbrs), 4), -1, dtype=np.int64)
            cnt = np.zeros(len(nbrs), dtype=np.int64)
            for c, ns in enumerate(nbrs):
                arr[c, :len(ns)] = ns
                cnt[c] = len(ns)
            got = self.graphs[id(nbrs)] = (nbrs, arr, cnt)
        return got[1], got[2]

    def arrays(self, size: int) -> tuple[np.ndarray, ...]:
        """The scratch for ``size`` states and a fresh search id."""
        if size > self.size:
            self.size = max(size, 2 * self.size)
            self.stamp = np.zeros(self.size, dtype=np.int32)
            self.closed = np.zeros(self.size, dtype=np.int32)
            self.rest = [np.zeros(self.size, dtype=np.int64) for _ in range(5)]
            self.sid = 0
        self.sid += 1
        if self.sid >= 2 ** 31 - 2:
            self.stamp[:] = 0
            self.closed[:] = 0
            self.sid = 1
        return (self.stamp, self.sid, self.closed, *self.rest)


_SCRATCH = _Scratch()


def safe_interval_astar(nbrs: Sequence[Sequence[int]], start: int, goal: int, heuristic: Sequence[float],
                        res: Reservations, max_expansions: int, t0: int = 0,
                        weight: float = 1.0) -> list[int] | None:
    """Space-time A* over safe intervals (SIPP, Phillips & Likhachev 2011, ICRA).

    Finds a path for one robot from ``start`` at step ``t0`` to ``goal``
    around the reservations ``res``: never in a reserved (cell, step), never
    in a parked cell from its park step on, never swapping cells with the
    owner of its target cell nor closing a rotation (a cycle of robots each
    following the next, which ordered execution could not carry out), and
    arriving in the goal's last, unbounded safe interval, so the robot can stay
    there for ever.

    ``nbrs[cell]``: the cells a robot can move to (at most 4). ``h[cell]``: exact distance to
    ``goal`` ignoring other robots (inf = unreachable: pruned). Ordering
    ``f = g + weight * max(h, G + 1 - g)`` (G: last reserved step of the goal cell),
    ties to smaller h then later g. ``weight`` 1 gives the earliest arrival; slightly
    above 1 (weighted A*) avoids expanding the large ties of 4-connected grids and
    keeps the arrival within ``weight`` x optimal. ``max_expansions`` bounds work (compiled,
    :mod:`.sipp_kernel`: about a microsecond per expansion).

    Returns cells for steps ``t0 .. arrival`` (``path[0] == start``), or None.
    """
    nbr, nnbr = _SCRATCH.neighbours(nbrs)
    h = np.asarray(heuristic, dtype=np.float64)
    top = res.top
    rows = max(top, t0 + 1) + 2
    out_len = 4 * rows + len(nbrs)
    while True:
        stamp, sid, closed, best, scell, sarr, send, spar = _SCRATCH.arrays((rows + 1) * res.n)
        out = np.empty(out_len, dtype=np.int64)
        n = sipp_search(nbr, nnbr, h, int(start), int(goal), res.vt, top, res.park, res.opath, res.olen, res.opark,
                        len(res.paths), int(t0), float(weight), int(max_expansions), stamp, sid, closed, best, scell,
                        sarr, send, spar, out)
        if n >= 0:
            return None if n == 0 else out[:n].tolist()
        out_len *= 2

