"""Static walls from an occupancy grid: pixel mask -> few axis-aligned rectangles.

A map_server map has hundreds of thousands of occupied (or unknown) pixels;
one physics body per pixel would be far too slow.  :func:`merge_rectangles`
merges them greedily: each image row is split into maximal runs of blocked
pixels, and a run that repeats exactly (same first and last column) in the
next row extends the rectangle above it.  The rectangles are disjoint and
cover the mask exactly.  The warehouse map (1006 x 1674 px) collapses to a
few thousand rectangles this way.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class PixelRect(NamedTuple):
    """A rectangle of pixels: rows ``row0 .. row1-1``, columns ``col0 .. col1-1``
    (end-exclusive, row 0 = top of the image)."""

    row0: int
    col0: int
    row1: int
    col1: int


def blocked_mask(occupancy: np.ndarray) -> np.ndarray:
    """Pixels a robot cannot enter: occupied (>= 50, as rce_fleet.maps.occupancy) or unknown (< 0).

    ``occupancy`` is the map's (H, W) int8 grid (0 free, 100 occupied,
    -1 unknown); returns an (H, W) bool array.
    """
    occ = np.asarray(occupancy)
    return (occ < 0) | (occ >= 50)


def merge_rectangles(mask: np.ndarray) -> list[PixelRect]:
    """Cover the True pixels of ``mask`` (H, W bool) with disjoint rectangles.

    Greedy row-run merging: maximal horizontal runs per row; a run whose
    [col0, col1) is identical to an open rectangle's in the row above extends
    it, every other run opens a new rectangle.  Runs are found with numpy
    (one ``diff`` over the whole image), so the Python loop is over runs,
    not pixels.  Rectangles are returned in row-major order of their top-left
    pixel.
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"mask must be 2-D, got shape {mask.shape}")
    h, w = mask.shape
    padded = np.zeros((h, w + 2), dtype=np.int8)
    padded[:, 1:-1] = mask
    d = np.diff(padded, axis=1)
    start_rows, start_cols = np.nonzero(d == 1)  # run starts at col
    _, end_cols = np.nonzero(d == -1)  # run ends before col (exclusive)
    # np.nonzero is row-major, so starts and ends pair up in order.

    rects: list[PixelRect] = []
    open_rects: dict[tuple[int, int], int] = {}  # (col0, col1) -> row0
    current_row = -1

    # Process row by row.
    n = len(start_rows)
    i = 0
    while i < n:
        row = int(start_rows[i])
        j = i
        runs: list[tuple[int, int]] = []
        while j < n and start_rows[j] == row:
            runs.append((int(start_cols[j]), int(end_cols[j])))
            j += 1
        run_set = set(runs)
        continues = row == current_row + 1
        new_open: dict[tuple[int, int], int] = {}
        for key, row0 in open_rects.items():
            if continues and key in run_set:
                new_open[key] = row0
            else:
                rects.append(PixelRect(row0, key[0], current_row + 1, key[1]))
        for key in runs:
            if key not in new_open:
                new_open[key] = row
        open_rects = new_open
        current_row = row
        i = j
    for key, row0 in open_rects.items():
        rects.append(PixelRect(row0, key[0], current_row + 1, key[1]))
    rects.sort()
    return rects


def rasterise(rects: list[PixelRect], shape: tuple[int, int]) -> np.ndarray:
    """Count how many rectangles cover each pixel: (H, W) int32."""
    out = np.zeros(shape, dtype=np.int32)
    for r in rects:
        out[r.row0 : r.row1, r.col0 : r.col1] += 1
    return out


def rect_to_world(
    rect: PixelRect,
    height_px: int,
    resolution: float,
    origin: tuple[float, float, float] | tuple[float, ...],
) -> tuple[float, float, float, float]:
    """World bounds ``(x0, y0, x1, y1)`` in metres of a pixel rectangle.

    map_server convention: ``origin`` is the world pose of the LOWER-LEFT
    corner of the image (yaw assumed 0), row 0 is the TOP row, so pixel
    (row, col) spans x in [ox + col*res, ox + (col+1)*res] and
    y in [oy + (H-1-row)*res, oy + (H-row)*res].
    """
    ox, oy = float(origin[0]), float(origin[1])
    x0 = ox + rect.col0 * resolution
    x1 = ox + rect.col1 * resolution
    y0 = oy + (height_px - rect.row1) * resolution
    y1 = oy + (height_px - rect.row0) * resolution
    return x0, y0, x1, y1
