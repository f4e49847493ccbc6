"""Per-goal distance maps with a memory bound: breadth-first search from each goal cell
(Moore 1959), computed lazily when a goal is first asked for, kept in an LRU cache.

Each map is one row of a preallocated uint16 array (cells,), so the planner's compiled
loop reads every agent's goal distances without a Python call. On a 500 x 140 map a row
is 137 KiB and one breadth-first search takes 1 - 2 ms. The table is allocated untouched
(the kernel commits a row's pages when its map is first written), so a generous bound costs
memory only as maps are computed; :func:`cache_bytes_for` sizes it to a team and a machine.
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np

from .grid import LifelongGrid
from .kernels import UNREACHABLE, bfs_fill, bfs_pair, dial_fill

__all__ = ["DistanceCache", "cache_bytes_for", "heading_graph"]

GiB = 2 ** 30


def cache_bytes_for(grid: LifelongGrid, team_size: int, available: int | None = None, share: float = 0.25,
                    floor: int = GiB) -> int:
    """The byte bound of a :class:`DistanceCache` for ``team_size`` robots on ``grid``.

    Enough rows for a map of every free cell (every cell may become a goal, so a run never
    recomputes an evicted map) when ``share`` of the machine's ``available`` memory (bytes;
    default: ``psutil.virtual_memory().available``) allows; else that share, but never less
    than ``floor`` (the old fixed bound). The goals robots head to are pinned, so the cache
    needs one row per robot and some for the scheduler (``team_size + 16``): when the share
    holds fewer, the bound is those rows if they fit in half of the available memory (maps
    are then evicted and computed again often); else MemoryError, naming the bytes, so a
    run that would fail at its first step fails before it starts.
    """
    if available is None:
        import psutil
        available = int(psutil.virtual_memory().available)
    row = 2 * grid.n_cells
    every = row * int(grid.flat.sum())
    need = min(every, row * (team_size + 16))
    bound = min(every, max(int(share * available), min(floor, every)))
    if bound >= need:
        return bound
    if need <= available // 2:
        return need
    raise MemoryError(f"distance maps for {team_size} robots need {need / GiB:.2f} GiB "
                      f"({team_size + 16} rows of {row} bytes); half of the {available / GiB:.2f} GiB "
                      f"available is {available / 2 / GiB:.2f} GiB")


class DistanceCache:
    """Distance maps to goal cells, bounded by ``max_bytes`` (LRU eviction).

    ``slot(goal)`` returns the row of ``table`` (shape (capacity, cells), uint16, steps;
    :data:`~.kernels.UNREACHABLE` where the goal cannot be reached) that holds the map of
    ``goal``, computing it if needed. Rows in ``pinned`` (the goals agents are heading to
    this step) are never evicted; raises RuntimeError if all rows are pinned.
    """

    def __init__(self, grid: LifelongGrid, max_bytes: int = 768 * 2 ** 20, min_rows: int = 16,
                 cost: np.ndarray | None = None):
        self.grid = grid
        self.cost = cost
        if cost is not None:
            if cost.shape != grid.nbr.shape or cost.dtype != np.uint8 or int(cost.min()) < 1:
                raise ValueError(f"cost must be a uint8 array of shape {grid.nbr.shape} with every entry >= 1")
            k = int(cost.max())
            self._stacks = np.empty((k + 1, grid.n_cells), dtype=np.int32)
            self._sizes = np.zeros(k + 1, dtype=np.int64)
        n = grid.n_cells
        self.capacity = min(int(grid.flat.sum()), max(min_rows, int(max_bytes // (2 * n))))
        self.table = np.empty((self.capacity, n), dtype=np.uint16)
        self._slots: OrderedDict[int, int] = OrderedDict()
        self._free = list(range(self.capacity - 1, -1, -1))
        self._queue = np.empty(n, dtype=np.int32)
        self._seen = np.zeros(n, dtype=np.uint8)
        self._dist = np.empty(n, dtype=np.int32)
        self.computed = 0
        self.evicted = 0
        self.pinned: set[int] = set()

    def __contains__(self, goal: int) -> bool:
        return goal in self._slots

    def __len__(self) -> int:
        return len(self._slots)

    def slot(self, goal: int) -> int:
        """The row of ``table`` with the distance map of ``goal`` (computed on a miss)."""
        s = self._slots.get(goal)
        if s is not None:
            self._slots.move_to_end(goal)
            return s
        if self._free:
            s = self._free.pop()
        else:
            for old in self._slots:
                if old not in self.pinned:
                    break
            else:
                raise RuntimeError(f"all {self.capacity} distance maps are pinned; raise max_bytes")
            s = self._slots.pop(old)
            self.evicted += 1
        if self.cost is None:
            bfs_fill(self.grid.nbr, int(goal), self.table[s], self._queue)
        else:
            dial_fill(self.grid.nbr, self.cost, int(goal), self.table[s], self._stacks, self._sizes)
        self._slots[goal] = s
        self.computed += 1
        return s

    def cached(self, goal: int) -> int:
        """The row of ``table`` with the distance map of ``goal`` if it is cached, else -1 (computes
        nothing, and leaves the maps' order of use as it is)."""
        return self._slots.get(goal, -1)

    def slots(self, goals) -> np.ndarray:
        """The rows of ``table`` with the distance maps of ``goals`` ((n,) cells), in their
        order ((n,) int64; computed on a miss, so all of them must fit in the cache)."""
        return np.array([self.slot(int(g)) for g in goals], dtype=np.int64)

    def rows(self, goals) -> np.ndarray:
        """The distance maps of ``goals`` ((n,) cells) in their order: (n, cells) uint16, a copy
        (for a search over these goals only, in place of ``table`` and :meth:`slots`)."""
        return self.table[self.slots(goals)]

    def dist(self, src: int, goal: int) -> int:
        """Steps from ``src`` to ``goal`` (UNREACHABLE if none), from the cached map of
        ``goal`` if there is one, else by a breadth-first search that stops at ``goal``."""
        s = self._slots.get(goal)
        if s is not None:
            return int(self.table[s, src])
        d = bfs_pair(self.grid.nbr, int(src), int(goal), self._seen, self._queue, self._dist)
        return UNREACHABLE if d < 0 else int(d)

    def from_source(self, src: int, out: np.ndarray | None = None) -> np.ndarray:
        """A fresh (uncached) distance map from ``src`` to every cell (uint16, cells)."""
        if out is None:
            out = np.empty(self.grid.n_cells, dtype=np.uint16)
        bfs_fill(self.grid.nbr, int(src), out, self._queue)
        return out


def one_shot_distances(grid: LifelongGrid, starts, goals, cache: DistanceCache | None = None
                       ) -> tuple[np.ndarray, np.ndarray, DistanceCache, np.ndarray, np.ndarray]:
    """Check a one-shot instance and look up what its solvers start from: ``starts``, ``goals``
    ((n,) cells, as int64 arrays), the distance ``cache`` (``cache`` or a new one sized for n
    agents), each goal's row in ``cache.table`` ((n,) int64) and each agent's start-to-goal
    distance ((n,) cells, the table's dtype). Raises ValueError for two agents on one start or
    goal, or a goal that cannot be reached from its start (naming the agent)."""
    starts = np.asarray(starts, dtype=np.int64)
    goals = np.asarray(goals, dtype=np.int64)
    n = starts.shape[0]
    if len(set(starts.tolist())) != n or len(set(goals.tolist())) != n:
        raise ValueError("two agents share a start or a goal cell")
    if cache is None:                          # an empty cache is falsy (len 0) but is the one to use
        cache = DistanceCache(grid, max_bytes=max(2 * grid.n_cells * (n + 16), 64 * 2 ** 20))
    rows = cache.slots(goals)
    dist = cache.table[rows, starts]
    if (dist == UNREACHABLE).any():
        bad = int(np.flatnonzero(dist == UNREACHABLE)[0])
        raise ValueError(f"agent {bad}: goal {int(goals[bad])} cannot be reached from {int(starts[bad])}")
    return starts, goals, cache, rows, dist


def heading_graph(grid: LifelongGrid) -> np.ndarray:
    """The 2024 rules' moves as a graph over (cell, heading) states, in the form of ``grid.nbr`` for
    :func:`~.kernels.bfs_fill`: state ``cell * 4 + heading`` (headings 0 - 3: east, south, west,
    north). Returns pred (cells x 4, 4) int32, the states one action (a quarter turn or a forward
    move, one step each) leads into each state from (-1: none; slot 0 the state turning
    counter-clockwise into it, 1 clockwise, 2 moving forward into it, 3 none). ``bfs_fill(pred,
    goal * 4 + h, ...)`` then gives the least steps from every state to ``goal`` facing ``h``: the
    exact cost to go, where :func:`~.kernels.heading_cost` bounds it from a cell's map."""
    n = grid.n_cells
    x = np.arange(4 * n)
    c, h = x // 4, x % 4
    pred = np.full((4 * n, 4), -1, dtype=np.int32)
    pred[:, 0] = c * 4 + (h + 1) % 4                 # (c, h + 1) turns counter-clockwise into (c, h)
    pred[:, 1] = c * 4 + (h + 3) % 4                 # (c, h - 1) turns clockwise into (c, h)
    back = grid.nbr[c, (h + 2) % 4]                  # the cell behind, whose forward move leads here
    pred[:, 2] = np.where(back >= 0, back * 4 + h, -1)
    pred[~grid.flat[c]] = -1
    return pred
