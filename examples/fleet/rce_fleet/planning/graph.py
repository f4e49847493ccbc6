"""The grid graph the fleet planner searches: free cells of a rows x cols grid and the
4-neighbour moves between them, with its distances (reverse Dijkstra, scipy ``csgraph``).

Cells are integers ``r * cols + c`` (row 0 at the top of the map image, see
:mod:`rce_fleet.maps.grid`). The graph is undirected between free cells (a robot can drive both
ways between two cells).
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra as _csgraph_dijkstra

__all__ = ["GridGraph"]


def _grid_moves(flat: np.ndarray, rows: int, cols: int, cell: int) -> list[int]:
    """The free 4-neighbours of ``cell`` (north, west, east, south)."""
    r, c = divmod(cell, cols)
    cand = []
    if r > 0:
        cand.append(cell - cols)
    if c > 0:
        cand.append(cell - 1)
    if c + 1 < cols:
        cand.append(cell + 1)
    if r + 1 < rows:
        cand.append(cell + cols)
    return [x for x in cand if flat[x]]


class GridGraph:
    """Free cells of a rows x cols grid and the 4-neighbour moves between them.

    free: (rows, cols) bool. neighbours: ``nbrs[cell]`` lists the cells a robot
    can move to from ``cell``. Between free cells the moves must be symmetric;
    a cell that is not free gets "escape" moves to its free 4-neighbours (so a
    robot localised in a non-free cell can leave it) but can never be entered.
    Raises ValueError when ``free`` is not 2-D.
    """

    def __init__(self, free: np.ndarray, neighbours: Sequence[Sequence[int]] | None = None):
        free = np.asarray(free, dtype=bool)
        if free.ndim != 2:
            raise ValueError(f"free must be a (rows, cols) array, got shape {free.shape}")
        self.rows, self.cols = int(free.shape[0]), int(free.shape[1])
        self.free = free
        flat = free.ravel()
        n = self.rows * self.cols
        nbrs: list[list[int]] = []
        for cell in range(n):
            if flat[cell] and neighbours is not None:
                nbrs.append([int(x) for x in neighbours[cell] if flat[x]])
            else:
                nbrs.append(_grid_moves(flat, self.rows, self.cols, cell))
        self.nbrs = nbrs
        src, dst = [], []
        for cell in np.flatnonzero(flat):
            for x in nbrs[cell]:
                src.append(int(cell))
                dst.append(x)
        # distances are computed on the free cells only (compact numbering)
        self._free_idx = np.flatnonzero(flat)
        self._compact = np.full(n, -1, dtype=np.int64)
        self._compact[self._free_idx] = np.arange(self._free_idx.size)
        self._src = self._compact[np.asarray(src, dtype=np.int64)]
        self._dst = self._compact[np.asarray(dst, dtype=np.int64)]
        self._csr_cache: tuple[frozenset, csr_matrix] | None = None

    # -- constructors ------------------------------------------------------
    @classmethod
    def from_array(cls, free: np.ndarray) -> "GridGraph":
        """A 4-connected grid from a (rows, cols) bool array of free cells."""
        return cls(free)

    @classmethod
    def from_cellgrid(cls, grid) -> "GridGraph":
        """From a :class:`rce_fleet.maps.grid.CellGrid`, using its free cells and connections."""
        n = grid.rows * grid.cols
        return cls(grid.free, [grid.neighbours(c) for c in range(n)])

    # -- basics -------------------------------------------------------------
    @property
    def n_cells(self) -> int:
        """rows * cols."""
        return self.rows * self.cols

    def is_free(self, cell: int) -> bool:
        """True when ``cell`` is inside the grid and free."""
        return 0 <= cell < self.n_cells and bool(self.free.flat[cell])

    def neighbours(self, cell: int) -> list[int]:
        """Cells a robot can move to from ``cell`` (free cells only)."""
        return self.nbrs[cell]

    # -- distances ---------------------------------------------------------
    def _csr(self, blocked: frozenset) -> csr_matrix:
        """The adjacency matrix of the free cells without ``blocked`` (the last one is cached)."""
        if self._csr_cache is not None and self._csr_cache[0] == blocked:
            return self._csr_cache[1]
        keep = np.ones(self._src.size, dtype=bool)
        if blocked:
            b = self._compact[np.fromiter(blocked, dtype=np.int64)]
            b = b[b >= 0]
            keep &= ~np.isin(self._src, b) & ~np.isin(self._dst, b)
        n = self._free_idx.size
        m = csr_matrix((np.ones(int(keep.sum())), (self._src[keep], self._dst[keep])), shape=(n, n))
        self._csr_cache = (blocked, m)
        return m

    def distances_to(self, goals: Sequence[int], blocked: Iterable[int] = ()) -> np.ndarray:
        """Steps from every cell to each goal, avoiding ``blocked`` cells.

        Returns (len(goals), n_cells) float64; ``inf`` where unreachable (and at
        blocked or non-free cells). Reverse Dijkstra with unit costs (scipy
        ``csgraph.dijkstra``); equals forward distance since moves are symmetric.
        """
        blocked = frozenset(int(b) for b in blocked)
        goals = [int(g) for g in goals]
        out = np.full((len(goals), self.n_cells), np.inf)
        ok = [i for i, g in enumerate(goals) if self.is_free(g) and g not in blocked]
        if ok:
            d = _csgraph_dijkstra(self._csr(blocked), directed=True, unweighted=True,
                                  indices=self._compact[[goals[i] for i in ok]])
            out[np.ix_(ok, self._free_idx)] = d
        return out
