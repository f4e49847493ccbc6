"""Which lidar hits are NEW obstacles, i.e. not the map's static walls.

The fleet marks grid cells blocked when a robot's lidar sees something the
map does not explain (docs/design.md, section 6.2).  :class:`ObstacleDetector` turns a
scan into world-frame hit points and drops every point within
``wall_tolerance`` of a blocked (occupied or unknown) map pixel, using a
Euclidean distance transform of the map computed once (scipy.ndimage), and
every point on a known robot (``exclude`` discs), so only boxes, people and
other surprises remain.
"""

from __future__ import annotations

from typing import Any, Iterable

import numpy as np
from scipy import ndimage

from .lidar import LidarParams, scan_to_points
from .walls import blocked_mask


class ObstacleDetector:
    """Filter lidar hits against a static occupancy map.

    ``occupancy_map``: ``occupancy`` (H, W) int8, ``resolution`` m/px,
    ``origin`` (x, y, yaw) of the lower-left corner (map_server convention).
    ``wall_tolerance``: hits closer than this to a static wall pixel are
    static, m (cover lidar noise plus localisation error; default 0.12 m).
    """

    def __init__(self, occupancy_map: Any, *, wall_tolerance: float = 0.12,
                 lidar_params: LidarParams | None = None) -> None:
        occ = np.asarray(occupancy_map.occupancy)
        self.resolution = float(occupancy_map.resolution)
        self.origin = (float(occupancy_map.origin[0]), float(occupancy_map.origin[1]))
        self.height, self.width = occ.shape
        self.wall_tolerance = float(wall_tolerance)
        self.lidar_params = lidar_params or LidarParams()
        # Distance (m) from each pixel centre to the nearest blocked pixel centre. The
        # outside of the image is blocked (SimWorld closes the border with walls), so hits
        # on that border are static too, even where the image's edge pixels are free.
        blocked = np.pad(blocked_mask(occ), 1, constant_values=True)
        self._dist = (ndimage.distance_transform_edt(~blocked)[1:-1, 1:-1]
                      * self.resolution).astype(np.float32)

    def distance_to_wall(self, points: np.ndarray) -> np.ndarray:
        """(K,) distance, m, from world points (K, 2) to the nearest static wall
        pixel (0 outside the map: the outside counts as wall)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        col = np.floor((pts[:, 0] - self.origin[0]) / self.resolution).astype(np.int64)
        row = self.height - 1 - np.floor(
            (pts[:, 1] - self.origin[1]) / self.resolution).astype(np.int64)
        inside = (row >= 0) & (row < self.height) & (col >= 0) & (col < self.width)
        out = np.zeros(len(pts), dtype=np.float64)
        out[inside] = self._dist[row[inside], col[inside]]
        # The EDT is pixel-centre to pixel-centre; a hit lies on a wall's
        # surface, half a pixel from its centre.
        return np.maximum(out - 0.5 * self.resolution, 0.0)

    def filter(self, points: np.ndarray,
               exclude: Iterable[tuple[float, float, float]] = ()) -> np.ndarray:
        """Keep the (K, 2) world points that are neither near a static wall nor
        inside any ``exclude`` disc (x m, y m, radius m)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        keep = self.distance_to_wall(pts) > self.wall_tolerance
        for ex, ey, er in exclude:
            keep &= np.hypot(pts[:, 0] - ex, pts[:, 1] - ey) > er
        return pts[keep]

    def detect_points(self, scan: np.ndarray, pose: tuple[float, float, float],
                      exclude: Iterable[tuple[float, float, float]] = ()) -> np.ndarray:
        """(K, 2) float64 world points, m, of the scan's hits that the map does
        not explain.  ``pose`` is the sensor pose (x m, y m, yaw rad) at scan
        time (use the localisation estimate); ``exclude`` discs (x, y, r) drop
        hits on known things such as the other robots (pass r ~ radius + 0.1 m)."""
        return self.filter(scan_to_points(scan, pose, self.lidar_params, include_too_close=False), exclude)

    def detect(self, scan: np.ndarray, pose: tuple[float, float, float],
               exclude: Iterable[tuple[float, float, float]] = ()) -> list[tuple[float, float]]:
        """:meth:`detect_points` as a list of (x, y) tuples."""
        return [(float(x), float(y)) for x, y in self.detect_points(scan, pose, exclude)]


def detected_obstacles(scan: np.ndarray, pose: tuple[float, float, float],
                       detector: ObstacleDetector | None = None,
                       exclude: Iterable[tuple[float, float, float]] = ()
                       ) -> list[tuple[float, float]]:
    """Lidar hits in world coordinates (x m, y m); with a ``detector`` only
    those not explained by the static map (see :class:`ObstacleDetector`)."""
    if detector is not None:
        return detector.detect(scan, pose, exclude)
    pts = scan_to_points(scan, pose, include_too_close=False)
    exclude = list(exclude)
    if exclude:
        keep = np.ones(len(pts), dtype=bool)
        for ex, ey, er in exclude:
            keep &= np.hypot(pts[:, 0] - ex, pts[:, 1] - ey) > er
        pts = pts[keep]
    return [(float(x), float(y)) for x, y in pts]
