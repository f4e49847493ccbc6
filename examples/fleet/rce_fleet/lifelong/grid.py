"""The grid a lifelong fleet runs on: free cells, the four headings and the move table.

Cells are integers ``row * cols + col`` (the League of Robot Runners' "locations" and
:mod:`rce_fleet.maps.grid`'s cell numbers alike). Headings follow the start-kit
(MAPF-Competition/Start-Kit, ``ActionModel.cpp``): 0 east, 1 south, 2 west, 3 north; a
clockwise turn (``R``) adds 1, a counter-clockwise turn (``C``) subtracts 1, modulo 4.
"""
from __future__ import annotations

import numpy as np

__all__ = ["EAST", "HEADING_NAMES", "MAX_STEPS", "NORTH", "SOUTH", "WEST", "LifelongGrid"]

EAST, SOUTH, WEST, NORTH = 0, 1, 2, 3
#: The longest distance (steps) the planner's uint16 distance maps hold; their maximum, 65,535,
#: is :data:`~.kernels.UNREACHABLE` (no path).
MAX_STEPS = int(np.iinfo(np.uint16).max) - 1
HEADING_NAMES = "ESWN"


class LifelongGrid:
    """Free cells of a ``rows x cols`` grid and the table of 4-neighbour moves.

    free: (rows, cols) bool array. ``nbr`` is an int32 array (rows * cols, 4): ``nbr[c, h]``
    is the cell one step from ``c`` towards heading ``h``, or -1 when that is off the map
    or not free. Raises ValueError when ``free`` is not 2-D or has no free cell, or when a
    shortest path is too long for the planner's uint16 distance tables (65,535 steps or more:
    a maze of over 65,535 cells, never an open floor).
    """

    def __init__(self, free: np.ndarray):
        free = np.asarray(free, dtype=bool)
        if free.ndim != 2:
            raise ValueError(f"free must be a (rows, cols) array, got shape {free.shape}")
        if not free.any():
            raise ValueError("the map has no free cell")
        self.rows, self.cols = int(free.shape[0]), int(free.shape[1])
        self.free = free
        self.flat = np.ascontiguousarray(free.ravel())
        n = self.rows * self.cols
        r, c = np.divmod(np.arange(n), self.cols)
        nbr = np.full((n, 4), -1, dtype=np.int32)
        steps = ((0, 1), (1, 0), (0, -1), (-1, 0))          # E, S, W, N as (drow, dcol)
        for h, (dr, dc) in enumerate(steps):
            rr, cc = r + dr, c + dc
            ok = (rr >= 0) & (rr < self.rows) & (cc >= 0) & (cc < self.cols)
            tgt = np.where(ok, rr * self.cols + cc, 0)
            ok &= self.flat[tgt] & self.flat
            nbr[ok, h] = tgt[ok]
        self.nbr = nbr
        if int(self.flat.sum()) > MAX_STEPS + 1:    # only then can a shortest path be longer than MAX_STEPS
            longest = self.longest_path_bound()
            if longest > MAX_STEPS:
                raise ValueError(f"a shortest path on this map is {longest} steps long; the planner's distance "
                                 f"tables hold at most {MAX_STEPS}")

    def longest_path_bound(self) -> int:
        """A lower bound of the longest shortest path (steps) between two free cells: the
        double sweep (a breadth-first search from any cell, then one from the farthest cell it
        found; exact on trees and corridors) in each connected part of over 65,535 cells, 0 if
        there is none (no path can be longer than its part has cells)."""
        from scipy.sparse import csr_matrix
        from scipy.sparse.csgraph import connected_components, shortest_path
        n = self.n_cells
        src, dst = np.repeat(np.arange(n), 4), self.nbr.ravel()
        ok = dst >= 0
        g = csr_matrix((np.ones(int(ok.sum()), dtype=np.int8), (src[ok], dst[ok])), shape=(n, n))
        _, labels = connected_components(g, directed=False)
        longest = 0
        for part in np.flatnonzero(np.bincount(labels[self.flat]) > MAX_STEPS + 1):
            v = int(np.flatnonzero((labels == part) & self.flat)[0])
            for _ in range(2):
                d = shortest_path(g, unweighted=True, indices=v)
                d[~np.isfinite(d)] = -1
                v = int(np.argmax(d))
            longest = max(longest, int(d[v]))
        return longest

    @property
    def n_cells(self) -> int:
        """rows * cols (free or not)."""
        return self.rows * self.cols

    def is_free(self, cell: int) -> bool:
        """Whether ``cell`` is on the map and free."""
        return 0 <= cell < self.n_cells and bool(self.flat[cell])

    def free_cells(self) -> np.ndarray:
        """The free cells, ascending (int64 array)."""
        return np.flatnonzero(self.flat)

    def rc(self, cell: int) -> tuple[int, int]:
        """(row, col) of ``cell``."""
        return divmod(int(cell), self.cols)

    @classmethod
    def from_graph(cls, graph) -> LifelongGrid:
        """The grid of a :class:`rce_fleet.planning.GridGraph`: its free cells, and only the
        moves its neighbour lists allow (a cell grid may forbid some between free cells)."""
        g = cls(graph.free)
        for c in np.flatnonzero(g.flat):
            allowed = set(graph.nbrs[int(c)])
            for h in range(4):
                if g.nbr[c, h] >= 0 and int(g.nbr[c, h]) not in allowed:
                    g.nbr[c, h] = -1
        return g
