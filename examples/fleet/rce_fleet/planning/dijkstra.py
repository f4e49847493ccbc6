"""Dijkstra on the grid graph (Dijkstra 1959, "A note on two problems in connexion with
graphs", Numerische Mathematik 1).

* :func:`shortest_path`: one robot's shortest cell path, ignoring the others: the seed
  paper's planner (section IV-A), kept for failure reasons and as the tests' reference.
* :class:`DistanceTable`: the fleet planner's heuristic, the true distance of every cell to
  a goal (reverse Dijkstra from the goal, :meth:`GridGraph.distances_to`), cached per goal
  and set of blocked cells.

Unit cost per move; distances are in steps (cell moves).
"""
from __future__ import annotations

import heapq
import math
from collections.abc import Iterable, Mapping

from .graph import GridGraph

__all__ = ["shortest_path", "DistanceTable", "MAX_CACHED_DISTANCES"]

INF = math.inf

#: Bound of a DistanceTable: cached distances, one per cell and goal (a list slot and a
#: Python float each, about 32 bytes: at most about 0.6 GB). Past it the table is emptied
#: and refilled on demand (counted in ``DistanceTable.clears``).
MAX_CACHED_DISTANCES = 20_000_000


def shortest_path(graph: GridGraph, start: int, goal: int, blocked: Iterable[int] = ()) -> list[int] | None:
    """Single-robot shortest cell path by Dijkstra (the seed paper's planner), or None.

    Unit cost per move; ``blocked`` cells are never entered (the start may be
    blocked: the robot is leaving it). Returns the list of cells from start to
    goal inclusive, ``[start]`` when start == goal.
    """
    blocked = set(blocked)
    if goal in blocked or not graph.is_free(goal):
        return None
    dist = {start: 0}
    parent = {start: -1}
    heap = [(0, start)]
    while heap:
        d, c = heapq.heappop(heap)
        if c == goal:
            path = []
            while c != -1:
                path.append(c)
                c = parent[c]
            return path[::-1]
        if d > dist[c]:
            continue
        for n in graph.nbrs[c]:
            if n in blocked:
                continue
            if d + 1 < dist.get(n, INF):
                dist[n] = d + 1
                parent[n] = c
                heapq.heappush(heap, (d + 1, n))
    return None


class DistanceTable:
    """Steps from every cell to a goal around the blocked cells, cached per (goal, blocked set).

    ``blocked`` arguments are the planner's cell -> source mapping (its keys count). A row is
    a list of ``n_cells`` floats (``inf``: unreachable, blocked or not free). At most
    ``max_cached`` distances are kept; past that the cache is emptied (``clears`` counts it).
    """

    def __init__(self, graph: GridGraph, max_cached: int = MAX_CACHED_DISTANCES):
        self.graph = graph
        self.max_cached = max_cached
        self.clears = 0
        self._rows: dict[tuple[int, frozenset], list[float]] = {}
        self._key: frozenset | None = None

    def _blocked_key(self, blocked: Mapping[int, str]) -> frozenset:
        """``blocked``'s cells as a frozenset, the same object while they do not change."""
        k = self._key
        if k is None or len(k) != len(blocked) or not k.issuperset(blocked):
            self._key = k = frozenset(blocked)
        return k

    def fill(self, goals: Iterable[int], blocked: Mapping[int, str]) -> None:
        """Compute the missing rows of ``goals`` in one batched reverse Dijkstra."""
        bl = self._blocked_key(blocked)
        need = sorted({g for g in goals if (g, bl) not in self._rows})
        if need:
            if (len(self._rows) + len(need)) * self.graph.n_cells > self.max_cached:
                self._rows.clear()
                self.clears += 1
            d = self.graph.distances_to(need, bl)
            for g, row in zip(need, d, strict=True):
                self._rows[(g, bl)] = row.tolist()

    def row(self, goal: int, blocked: Mapping[int, str]) -> list[float]:
        """Steps from every cell to ``goal`` (index: cell number)."""
        bl = self._blocked_key(blocked)
        if (goal, bl) not in self._rows:
            self.fill([goal], blocked)
        return self._rows[(goal, bl)]

    def distance(self, start: int, goal: int, blocked: Mapping[int, str]) -> float:
        """Steps of the shortest path from ``start`` to ``goal`` (inf if none). A ``start``
        that is blocked or not free is left by its escape moves."""
        h = self.row(goal, blocked)
        if h[start] < INF:
            return h[start]
        best = min((h[n] for n in self.graph.nbrs[start]), default=INF)
        return best + 1
