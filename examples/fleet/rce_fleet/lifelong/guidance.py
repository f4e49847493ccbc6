"""Static traffic guidance for the lifelong planner: one-way lanes in one-cell-wide corridors,
and keep-right lanes in wider ones.

A corridor cell has blocked cells (or the map's edge) on both sides across it: north and
south for a horizontal corridor, east and west for a vertical one. In a warehouse of shelf
blocks the corridors form lanes; two robots meeting head-on in one cost both a detour or a
long swap. :func:`lane_costs` makes every other lane one-way in each direction (the
"crisscross" guidance graph of Zhang et al., "Guidance graph optimization for lifelong
multi-agent path finding", IJCAI-24): a move along a lane against its direction costs
``1 + against`` instead of 1. The planner's distance maps then follow the lanes
(:class:`~.distances.DistanceCache` with ``cost``); PIBT itself is unchanged, so a robot
may still go against a lane when that is its best move.

A corridor 2 to 12 cells wide between rooms carries both directions at once: streams that meet
in it head-on pack its mouths until nothing moves (docs/lifelong.md, "A jam on GAME").
:func:`keep_right_costs` splits such a corridor down its middle into two lanes, right-hand
traffic as on a road: moving along the wrong half costs more, crossing over costs nothing.
"""
from __future__ import annotations

import numpy as np

from .grid import EAST, NORTH, SOUTH, WEST, LifelongGrid

__all__ = ["keep_right_costs", "lane_costs"]


def lane_costs(grid: LifelongGrid, against: int = 1, min_cells: int = 4, everywhere: bool = False) -> np.ndarray:
    """(cells, 4) uint8 move costs for :class:`~.distances.DistanceCache`: 1 everywhere,
    ``1 + against`` for a move out of a corridor cell against its lane.

    Lanes: the rows (columns) with at least ``min_cells`` horizontal (vertical) corridor
    cells, numbered top to bottom (left to right); even rows run east, odd rows west, even
    columns south, odd columns north. With ``everywhere`` every row and column of the map is a
    lane (by its index: even rows east, even columns south), corridor or not: the crisscross
    graph over an open map. Raises ValueError for ``against`` outside 0..254.
    """
    if not 0 <= against <= 254:
        raise ValueError(f"against must be in 0..254, got {against}")
    nbr = grid.nbr
    free = grid.flat
    cost = np.ones(nbr.shape, dtype=np.uint8)
    if against == 0:
        return cost
    if everywhere:
        horiz = vert = free.reshape(grid.rows, grid.cols)
        rows, cols = np.arange(grid.rows), np.arange(grid.cols)
    else:
        horiz = free & (nbr[:, NORTH] < 0) & (nbr[:, SOUTH] < 0) & ((nbr[:, EAST] >= 0) | (nbr[:, WEST] >= 0))
        vert = free & (nbr[:, EAST] < 0) & (nbr[:, WEST] < 0) & ((nbr[:, NORTH] >= 0) | (nbr[:, SOUTH] >= 0))
        horiz = horiz.reshape(grid.rows, grid.cols)
        vert = vert.reshape(grid.rows, grid.cols)
        rows = np.flatnonzero(horiz.sum(axis=1) >= min_cells)
        cols = np.flatnonzero(vert.sum(axis=0) >= min_cells)
    for k, r in enumerate(rows):
        cells = r * grid.cols + np.flatnonzero(horiz[r])
        cost[cells, WEST if k % 2 == 0 else EAST] += against
    for k, c in enumerate(cols):
        cells = np.flatnonzero(vert[:, c]) * grid.cols + c
        cost[cells, NORTH if k % 2 == 0 else SOUTH] += against
    return cost


def _runs(free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per cell of a (rows, cols) bool grid: the length of the run of free cells along its row
    that it is in, and its offset from the run's west end (0 where blocked)."""
    start = free.copy()
    start[:, 1:] &= ~free[:, :-1]
    flat = free.ravel()
    rid = np.cumsum(start.ravel()) * flat
    length = np.bincount(rid)[rid] * flat
    idx = np.arange(flat.size)
    first = np.zeros(int(rid.max()) + 1, dtype=np.int64)
    first[rid[start.ravel()]] = idx[start.ravel()]
    offset = (idx - first[rid]) * flat
    return length.reshape(free.shape), offset.reshape(free.shape)


def keep_right_costs(grid: LifelongGrid, against: int = 1, max_width: int = 12, ratio: int = 3,
                     min_len: int = 16, cost: np.ndarray | None = None) -> np.ndarray:
    """(cells, 4) uint8 move costs: right-hand traffic in corridors 2 to ``max_width`` cells
    wide, added to ``cost`` (default all 1).

    A free cell is in a horizontal corridor when the free cells above and below it run
    ``2..max_width`` cells (its corridor's width) and those along its row at least ``ratio``
    times that and at least ``min_len`` (vertical corridors likewise; the gaps between a
    random map's obstacles are no corridors). A robot keeps right: in the half of a
    horizontal corridor nearer its north wall the lane runs west, in the south half east; in a
    vertical corridor's west half south, in its east half north; a middle row of an odd width
    has no lane. A move along the corridor against its half's lane costs ``1 + against`` more,
    a move across it nothing, so streams meeting in a corridor pass each other instead of
    jamming at its mouth. One-cell corridors are :func:`lane_costs`'s. Raises ValueError for
    ``against`` outside 0..254 or a ``max_width`` below 2.
    """
    if not 0 <= against <= 254:
        raise ValueError(f"against must be in 0..254, got {against}")
    if max_width < 2:
        raise ValueError(f"max_width must be at least 2, got {max_width}")
    free = grid.flat.reshape(grid.rows, grid.cols)
    out = np.ones(grid.nbr.shape, dtype=np.uint8) if cost is None else cost.astype(np.uint8, copy=True)
    if against == 0:
        return out
    h_len, h_off = _runs(free)
    v_len, v_off = (a.T for a in _runs(np.ascontiguousarray(free.T)))
    horiz = free & (v_len >= 2) & (v_len <= max_width) & (h_len >= np.maximum(ratio * v_len, min_len))
    vert = free & (h_len >= 2) & (h_len <= max_width) & (v_len >= np.maximum(ratio * h_len, min_len))
    west = (horiz & (2 * v_off + 1 < v_len)).ravel()      # north half of a horizontal corridor
    east = (horiz & (2 * v_off + 1 > v_len)).ravel()
    south = (vert & (2 * h_off + 1 < h_len)).ravel()      # west half of a vertical corridor
    north = (vert & (2 * h_off + 1 > h_len)).ravel()
    bump = np.uint8(against)
    for cells, d in ((west, EAST), (east, WEST), (south, NORTH), (north, SOUTH)):
        out[cells, d] = np.minimum(out[cells, d].astype(np.int64) + bump, 255).astype(np.uint8)
    return out
