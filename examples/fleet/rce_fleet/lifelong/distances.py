"""Per-goal distance maps with a memory bound: breadth-first search from each goal cell
(Moore 1959), computed lazily when a goal is first asked for, kept in an LRU cache.

Each map is one row of a preallocated uint16 array (cells,), so the planner's compiled
loop reads every agent's goal distances without a Python call. On a 500 x 140 map a row
is 137 KiB and one breadth-first search takes ~0.3 ms.
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np

from .grid import LifelongGrid
from .kernels import UNREACHABLE, bfs_fill, bfs_pair

__all__ = ["DistanceCache"]


class DistanceCache:
    """Distance maps to goal cells, bounded by ``max_bytes`` (LRU eviction).

    ``slot(goal)`` returns the row of ``table`` (shape (capacity, cells), uint16, steps;
    :data:`~.kernels.UNREACHABLE` where the goal cannot be reached) that holds the map of
    ``goal``, computing it if needed. Rows in ``pinned`` (the goals agents are heading to
    this step) are never evicted; raises RuntimeError if all rows are pinned.
    """

    def __init__(self, grid: LifelongGrid, max_bytes: int = 768 * 2 ** 20, min_rows: int = 16):
        self.grid = grid
        n = grid.n_cells
        self.capacity = min(n, max(min_rows, int(max_bytes // (2 * n))))
        self.table = np.empty((self.capacity, n), dtype=np.uint16)
        self._slots: OrderedDict[int, int] = OrderedDict()
        self._free = list(range(self.capacity - 1, -1, -1))
        self._queue = np.empty(n, dtype=np.int32)
        self._seen = np.zeros(n, dtype=np.uint8)
        self._dist = np.empty(n, dtype=np.int32)
        self.computed = 0
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
        bfs_fill(self.grid.nbr, int(goal), self.table[s], self._queue)
        self._slots[goal] = s
        self.computed += 1
        return s

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
