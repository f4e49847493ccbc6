"""The lidar's ray casting, compiled (numba, ``cache=True``): the same hits as pymunk's
``Space.segment_query_first`` over the world's shapes, an order of magnitude cheaper.

Why (py-spy of the live 100-robot fleet, ``bench/fleet_live.py --robots 100``): the simulated
robots' scans took 31 % of the simulator process, one chipmunk segment query per beam (360
per scan, 1.2 - 4 ms a scan on the warehouse map's 2,084 wall rectangles).

The world's shapes, as :class:`.world.SimWorld` builds them:

- static walls: the map's blocked pixels (:func:`.walls.merge_rectangles` covers them with
  disjoint rectangles) and the walls around the image. A beam walks the pixels it crosses
  (Amanatides and Woo, "A Fast Voxel Traversal Algorithm for Ray Tracing", Eurographics 1987)
  and stops at the first blocked pixel; leaving the image is a hit on the border wall;
- boxes: axis-aligned rectangles ``(x0, y0, x1, y1)``, m (slab test);
- robots: discs ``(x, y, r)``, m (chipmunk's circle segment query, term for term).

A beam that starts inside a shape hits it at 0 (chipmunk's ``cpShapeSegmentQuery`` checks the
start point first). Hits are ``alpha * range_max`` along the segment from the sensor to
``range_max``; ``inf`` where no shape is hit.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy import ndimage

from ..numba_cache import seed
from .walls import PixelRect, rasterise

seed(__file__)          # numba's cache entries prepared in the tree (sandboxed nodes)

__all__ = ["RayCaster", "free_run", "warm_up"]


def free_run(wall: np.ndarray, resolution: float) -> np.ndarray:
    """(H, W) float64: how far, m, a beam from any point of each pixel can go in any direction
    without reaching a wall pixel (the image's outside counts as wall): the distance between
    pixel centres to the nearest wall pixel, less the two half-diagonals, less 1 % of a pixel."""
    blocked = np.pad(wall, 1, constant_values=True)
    d = ndimage.distance_transform_edt(~blocked)[1:-1, 1:-1] * resolution
    return np.maximum(d - (math.sqrt(2.0) + 0.01) * resolution, 0.0)


@njit(cache=True)
def _walls(wall, run, res, ox, oy, x, y, dx, dy):
    """alpha in [0, 1] of the first wall pixel on the segment (x, y) + alpha (dx, dy), 2.0 if
    none. ``run``: :func:`free_run`; the walk jumps over free space wider than two pixels."""
    h, w = wall.shape
    col, rrow = int(math.floor((x - ox) / res)), int(math.floor((y - oy) / res))   # rrow: rows from the bottom
    if col < 0 or col >= w or rrow < 0 or rrow >= h or wall[h - 1 - rrow, col]:
        return 0.0                                                  # inside a wall or the border walls
    sx = 1 if dx > 0 else -1
    sy = 1 if dy > 0 else -1
    length = math.hypot(dx, dy)
    t = 0.0
    while True:
        jump = run[h - 1 - rrow, col]
        if jump > 2.0 * res:                # free all round: go on from the point ``jump`` m further
            t += jump / length
            if t > 1.0:
                return 2.0
            col, rrow = int(math.floor((x + t * dx - ox) / res)), int(math.floor((y + t * dy - oy) / res))
            continue
        tx = ((ox + (col + (1 if dx > 0 else 0)) * res) - x) / dx if dx != 0 else 3.0
        ty = ((oy + (rrow + (1 if dy > 0 else 0)) * res) - y) / dy if dy != 0 else 3.0
        if tx <= ty:
            t = tx
            col += sx
        else:
            t = ty
            rrow += sy
        if t > 1.0:
            return 2.0
        if col < 0 or col >= w or rrow < 0 or rrow >= h:
            return t
        if wall[h - 1 - rrow, col]:
            return t


@njit(cache=True)
def _box(b, x, y, dx, dy):
    """alpha of the segment's entry into box b (x0, y0, x1, y1) (0 from inside), 2.0 if it misses."""
    if b[0] <= x <= b[2] and b[1] <= y <= b[3]:
        return 0.0
    lo, hi = -np.inf, np.inf
    if dx != 0:
        t1, t2 = (b[0] - x) / dx, (b[2] - x) / dx
        lo, hi = max(lo, min(t1, t2)), min(hi, max(t1, t2))
    elif x < b[0] or x > b[2]:
        return 2.0
    if dy != 0:
        t1, t2 = (b[1] - y) / dy, (b[3] - y) / dy
        lo, hi = max(lo, min(t1, t2)), min(hi, max(t1, t2))
    elif y < b[1] or y > b[3]:
        return 2.0
    if lo > hi or lo < 0.0 or lo > 1.0:
        return 2.0
    return lo


@njit(cache=True)
def _disc(cx, cy, r, ax, ay, bx, by):
    """alpha of the segment a -> b's entry into the disc (chipmunk's CircleSegmentQuery; 0 from
    inside), 2.0 if none."""
    dax, day = ax - cx, ay - cy
    if math.hypot(dax, day) <= r:
        return 0.0
    dbx, dby = bx - cx, by - cy
    aa = dax * dax + day * day
    ab = dax * dbx + day * dby
    qa = aa - 2.0 * ab + (dbx * dbx + dby * dby)
    qb = ab - aa
    det = qb * qb - qa * (aa - r * r)
    if det >= 0.0:
        t = (-qb - math.sqrt(det)) / qa
        if 0.0 <= t <= 1.0:
            return t
    return 2.0


@njit(cache=True)
def cast(wall, run, res, ox, oy, x, y, ex, ey, rmax, boxes, discs, groups, group):
    """Ranges, m, of the beams from (x, y) to (ex[i], ey[i]) (each ``rmax`` long), inf where
    nothing is hit: (n,) float64. ``wall``: (H, W) bool wall pixels (:func:`covered`), ``run``
    their :func:`free_run`; ``res`` m per pixel;
    (``ox``, ``oy``) the image's lower-left corner, m; ``boxes`` (K, 4); ``discs`` (M, 3) with
    their shape filter ``groups`` (M,): those of ``group`` (the sensor's own robot; 0: none) are
    left out."""
    n = ex.shape[0]
    out = np.full(n, np.inf)
    near = np.empty(discs.shape[0], dtype=np.int64)
    m = 0
    for j in range(discs.shape[0]):
        if (group == 0 or groups[j] != group) and math.hypot(discs[j, 0] - x, discs[j, 1] - y) <= rmax + discs[j, 2]:
            near[m] = j
            m += 1
    for i in range(n):
        bx, by = ex[i], ey[i]
        dx, dy = bx - x, by - y                 # as chipmunk takes the segment's direction
        best = _walls(wall, run, res, ox, oy, x, y, dx, dy)
        for k in range(boxes.shape[0]):
            t = _box(boxes[k], x, y, dx, dy)
            if t < best:
                best = t
        for q in range(m):
            j = near[q]
            t = _disc(discs[j, 0], discs[j, 1], discs[j, 2], x, y, bx, by)
            if t < best:
                best = t
        if best <= 1.0:
            out[i] = best * rmax
    return out


class RayCaster:
    """The static walls of a map for :func:`cast`: ``rects`` the blocked pixels' rectangles in an
    image of ``shape`` (H, W) (row 0 the top), ``resolution`` m per pixel, ``origin`` (x, y) m of
    the image's lower-left corner (map_server convention)."""

    def __init__(self, rects: list[PixelRect], shape: tuple[int, int], resolution: float,
                 origin: tuple[float, ...]) -> None:
        self.wall = rasterise(rects, shape) > 0       # the pixels the rectangles cover
        self.run = free_run(self.wall, resolution)
        self.resolution = float(resolution)
        self.origin = (float(origin[0]), float(origin[1]))

    def cast(self, x: float, y: float, ex: np.ndarray, ey: np.ndarray, range_max: float,
             boxes: np.ndarray, discs: np.ndarray, groups: np.ndarray, group: int = 0) -> np.ndarray:
        """Ranges, m, of beams from (x, y) m to the points (ex, ey) m ((n,) float64 each,
        ``range_max`` m away): (n,) float64, inf where nothing is hit; ``boxes`` (K, 4) float64
        (x0, y0, x1, y1) m; ``discs`` (M, 3) float64 (x, y, r) m with their shape filter groups
        (M,) int64, those in ``group`` (not 0) left out, as pymunk's ``ShapeFilter(group=...)``."""
        return cast(self.wall, self.run, self.resolution, self.origin[0], self.origin[1], float(x), float(y), ex, ey,
                    float(range_max), boxes, discs, groups, int(group))


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel on a 2 x 2 image."""
    caster = RayCaster([PixelRect(0, 0, 1, 1)], (2, 2), 1.0, (0.0, 0.0))
    caster.cast(1.5, 0.5, np.array([2.5, 1.5]), np.array([0.5, 1.5]), 1.0, np.zeros((1, 4)),
                np.array([[1.8, 0.5, 0.1]]), np.array([1], dtype=np.int64), 0)
