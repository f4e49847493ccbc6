"""The project's own default map: a lab-like room, generated (no external data needed).

``write_lab_map(dir)`` writes ``lab.pgm`` + ``lab.yaml`` (ROS map_server,
trinary) describing an 8 m x 8 m room at 0.05 m/pixel, centred on the world
origin, so ``make demo`` runs on a machine without ``../shared/data``.

Layout (world metres, x right, y up; the 8x8 default grid gives 1 m cells)::

    outer walls 0.1 m thick on all four sides
    a partition wall 0.1 m thick along the border between grid rows 2 and 3,
        from the west wall to x = +1 m, with a 1 m door at grid column 3
    two shelves (0.6 m x 2 m) in grid column 2 and column 5, rows 5-6
    a 0.6 m x 0.6 m table in cell (1, 6)
    a pillar (0.4 m) in cell (3, 5)

The partition lies on a cell border, so it removes grid *connections* (not
cells); shelves, table and pillar remove cells. Cell 26 (row 3, col 2) is free
and lies on the way from the west side to the door.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .occupancy import FREE, OCCUPIED, OccupancyMap, save_map

__all__ = ["write_lab_map", "lab_map", "LAB_SIZE_M", "LAB_RESOLUTION"]

LAB_SIZE_M = 8.0
LAB_RESOLUTION = 0.05


def lab_map() -> OccupancyMap:
    """The lab room as an in-memory :class:`OccupancyMap` (160 x 160 px, origin (-4, -4, 0))."""
    res = LAB_RESOLUTION
    n = int(round(LAB_SIZE_M / res))
    occ = np.full((n, n), FREE, dtype=np.int8)

    def box(top_m: float, left_m: float, h_m: float, w_m: float) -> None:
        """Mark a rectangle occupied; coordinates from the image's top-left corner, metres."""
        r0, c0 = int(round(top_m / res)), int(round(left_m / res))
        r1, c1 = int(round((top_m + h_m) / res)), int(round((left_m + w_m) / res))
        occ[max(r0, 0):min(r1, n), max(c0, 0):min(c1, n)] = OCCUPIED

    t = 0.1
    box(0, 0, t, LAB_SIZE_M)                      # north wall
    box(LAB_SIZE_M - t, 0, t, LAB_SIZE_M)         # south wall
    box(0, 0, LAB_SIZE_M, t)                      # west wall
    box(0, LAB_SIZE_M - t, LAB_SIZE_M, t)         # east wall
    box(3.0 - t / 2, 0, t, 3.0)                   # partition, west part (columns 0-2)
    box(3.0 - t / 2, 4.0, t, 1.0)                 # partition, east part (column 4); door at column 3
    box(5.0, 2.2, 2.0, 0.6)                       # shelf, column 2, rows 5-6
    box(5.0, 5.2, 2.0, 0.6)                       # shelf, column 5, rows 5-6
    box(1.2, 6.2, 0.6, 0.6)                       # table, cell (1, 6)
    box(3.3, 5.3, 0.4, 0.4)                       # pillar, cell (3, 5)
    half = LAB_SIZE_M / 2
    return OccupancyMap(occupancy=occ, resolution=res, origin=(-half, -half, 0.0))


def write_lab_map(directory: str | Path) -> Path:
    """Write ``lab.pgm`` and ``lab.yaml`` into ``directory`` (created if needed).

    Returns the YAML path, loadable with :func:`rce_fleet.maps.occupancy.load_map`.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    return save_map(lab_map(), d / "lab.yaml", image_name="lab.pgm")
