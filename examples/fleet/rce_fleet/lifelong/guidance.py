"""Static traffic guidance for the lifelong planner: one-way lanes in one-cell-wide corridors.

A corridor cell has blocked cells (or the map's edge) on both sides across it: north and
south for a horizontal corridor, east and west for a vertical one. In a warehouse of shelf
blocks the corridors form lanes; two robots meeting head-on in one cost both a detour or a
long swap. :func:`lane_costs` makes every other lane one-way in each direction (the
"crisscross" guidance graph of Zhang et al., "Guidance graph optimization for lifelong
multi-agent path finding", IJCAI-24): a move along a lane against its direction costs
``1 + against`` instead of 1. The planner's distance maps then follow the lanes
(:class:`~.distances.DistanceCache` with ``cost``); PIBT itself is unchanged, so a robot
may still go against a lane when that is its best move.
"""
from __future__ import annotations

import numpy as np

from .grid import EAST, NORTH, SOUTH, WEST, LifelongGrid

__all__ = ["lane_costs"]


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
