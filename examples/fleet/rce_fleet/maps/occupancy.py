"""ROS map_server maps (PGM/PNG image + YAML) as numpy occupancy grids.

The YAML keys and their meaning follow the ROS map_server documentation
(wiki.ros.org/map_server) and Nav2's ``nav2_map_server`` (``map_io.cpp``):

``image``            image file, absolute or relative to the YAML file (required)
``resolution``       metres per pixel (required, > 0)
``origin``           ``[x, y, yaw]`` of the lower-left pixel, m, m, rad (required)
``negate``           0/1 or bool: swap the white=free / black=occupied meaning (default 0)
``occupied_thresh``  occupancy probability above which a pixel is occupied (default 0.65)
``free_thresh``      occupancy probability below which a pixel is free (default 0.196)
``mode``             ``trinary`` (default), ``scale`` or ``raw``

Nav2 requires ``negate``, ``occupied_thresh`` and ``free_thresh``; we default
them to the values ``map_saver`` writes, since a missing threshold has only
one sensible meaning.  Pixel interpretation is Nav2's:

* ``shade`` = mean of the colour channels in [0, 1] (in trinary mode the
  alpha channel, if any, is averaged in too, as ROS 1 and Nav2 do);
  ``occ = shade if negate else 1 - shade``.
* trinary: ``occ > occupied_thresh`` -> 100, ``occ < free_thresh`` -> 0, else -1.
* scale: a non-opaque pixel -> -1; otherwise as trinary, except values between
  the thresholds become ``rint(100 * (occ - free) / (occupied - free))``
  (ROS 1 used ``1 + 98 * ratio``; we follow Nav2).
* raw: ``round(255 * shade)`` when it lies in [0, 100], else -1 (``negate`` is
  ignored, as in Nav2).

The only difference from ``nav_msgs/OccupancyGrid`` is the row order: our
``occupancy[0]`` is the TOP row of the image (as it is stored), whereas
OccupancyGrid stores the bottom row first.  Use ``np.flipud`` to convert.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from rce_fleet.maps.geometry import pixel_f_to_world

__all__ = ["MapError", "OccupancyMap", "load_map", "save_map", "FREE", "OCCUPIED", "UNKNOWN"]

FREE = 0
OCCUPIED = 100
UNKNOWN = -1

#: A pixel whose occupancy value is at least this is treated as an obstacle by
#: :meth:`OccupancyMap.free_mask` (values 1..99 only occur in ``scale``/``raw`` maps).
OCCUPIED_MIN = 50

_MODES = ("trinary", "scale", "raw")
_DEFAULTS = {"negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196, "mode": "trinary"}


class MapError(ValueError):
    """A map YAML or image that cannot be loaded; the message names the file and the key."""


@dataclass(frozen=True, eq=False)
class OccupancyMap:
    """An occupancy grid map.

    occupancy: np.ndarray (H, W) int8, row 0 = TOP of the image; values 0 free,
        100 occupied, -1 unknown, 1..99 partly occupied (scale/raw modes only).
        This is the ROS ``nav_msgs/OccupancyGrid`` convention except the row order.
    resolution: metres per pixel.
    origin: (x, y, yaw) of the lower-left corner of the lower-left pixel, in
        (m, m, rad), as in map_server; yaw rotates the image counter-clockwise
        about that corner.
    image: the image file the map came from, if any (for display only).
    """

    occupancy: np.ndarray
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    image: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        occ = np.asarray(self.occupancy)
        if occ.ndim != 2 or occ.size == 0:
            raise ValueError(f"occupancy must be a non-empty 2-D array, got shape {occ.shape}")
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise ValueError(f"resolution must be a positive number of m/pixel, got {self.resolution!r}")
        occ = occ.astype(np.int8, copy=False)
        occ.setflags(write=False)
        object.__setattr__(self, "occupancy", occ)
        object.__setattr__(self, "resolution", float(self.resolution))
        ox, oy, oyaw = (tuple(float(v) for v in self.origin) + (0.0,))[:3]
        object.__setattr__(self, "origin", (ox, oy, oyaw))

    # -- size -------------------------------------------------------------
    @property
    def height(self) -> int:
        """Image height in pixels (number of rows)."""
        return int(self.occupancy.shape[0])

    @property
    def width(self) -> int:
        """Image width in pixels (number of columns)."""
        return int(self.occupancy.shape[1])

    @property
    def width_m(self) -> float:
        """Map width in metres (columns x resolution)."""
        return self.width * self.resolution

    @property
    def height_m(self) -> float:
        """Map height in metres (rows x resolution)."""
        return self.height * self.resolution

    # -- coordinates ------------------------------------------------------
    def world_to_pixel_f(self, x: float, y: float) -> tuple[float, float]:
        """World (m) -> continuous pixel coordinates (row_f, col_f).

        Pixel (r, c) covers row_f in [r, r + 1) and col_f in [c, c + 1); row_f
        grows downwards (row 0 at the top of the image).
        """
        ox, oy, yaw = self.origin
        dx, dy = x - ox, y - oy
        if yaw:
            cs, sn = math.cos(yaw), math.sin(yaw)
            dx, dy = cs * dx + sn * dy, -sn * dx + cs * dy
        return self.height - dy / self.resolution, dx / self.resolution

    def pixel_f_to_world(self, row_f: float, col_f: float) -> tuple[float, float]:
        """Continuous pixel coordinates (row_f, col_f) -> world (x, y) in metres."""
        return pixel_f_to_world(self.origin, self.resolution, self.height, row_f, col_f)

    def world_to_pixel(self, x: float, y: float) -> tuple[int, int]:
        """World (m) -> (row, col) of the pixel containing the point, row 0 at the top.

        Not clamped: a point outside the map gives indices outside
        ``[0, height) x [0, width)``; check with :meth:`in_bounds`.
        """
        rf, cf = self.world_to_pixel_f(x, y)
        return math.floor(rf), math.floor(cf)

    def pixel_to_world(self, row: int, col: int) -> tuple[float, float]:
        """(row, col) -> world (x, y) in metres of the pixel's centre."""
        return self.pixel_f_to_world(row + 0.5, col + 0.5)

    def in_bounds(self, row: int, col: int) -> bool:
        """True when (row, col) is a pixel of the image."""
        return 0 <= row < self.height and 0 <= col < self.width

    # -- masks ------------------------------------------------------------
    def free_mask(self, unknown_is_occupied: bool = True) -> np.ndarray:
        """(H, W) bool: pixels a robot may occupy.

        Free means ``0 <= value < OCCUPIED_MIN`` (50); unknown (-1) pixels are free
        only when ``unknown_is_occupied`` is False.
        """
        occ = self.occupancy
        free = (occ >= 0) & (occ < OCCUPIED_MIN)
        if not unknown_is_occupied:
            free |= occ < 0
        return free

    def known_bounds(self) -> tuple[int, int, int, int]:
        """(row0, col0, row1, col1), half-open pixel box around all known (!= -1) pixels.

        The whole image when nothing is known.
        """
        known = self.occupancy >= 0
        rows = np.flatnonzero(known.any(axis=1))
        cols = np.flatnonzero(known.any(axis=0))
        if rows.size == 0:
            return 0, 0, self.height, self.width
        return int(rows[0]), int(cols[0]), int(rows[-1]) + 1, int(cols[-1]) + 1


# ---------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------
def _number(meta: dict, key: str, where: Path) -> float:
    v = meta[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise MapError(f"{where}: key '{key}' must be a number, got {v!r}")
    return float(v)


def _parse_meta(meta: object, where: Path) -> dict:
    if not isinstance(meta, dict):
        raise MapError(f"{where}: expected a YAML mapping with keys image, resolution, origin, ...; "
                       f"got {type(meta).__name__}")
    for key in ("image", "resolution", "origin"):
        if key not in meta:
            raise MapError(f"{where}: missing required key '{key}'")
    out: dict = {}
    image = meta["image"]
    if not isinstance(image, str) or not image.strip():
        raise MapError(f"{where}: key 'image' must be a non-empty file name, got {image!r}")
    out["image"] = image
    out["resolution"] = _number(meta, "resolution", where)
    if out["resolution"] <= 0:
        raise MapError(f"{where}: key 'resolution' must be > 0 m/pixel, got {meta['resolution']!r}")
    origin = meta["origin"]
    if (not isinstance(origin, (list, tuple)) or len(origin) != 3
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in origin)):
        raise MapError(f"{where}: key 'origin' must be a list of 3 numbers [x, y, yaw], got {origin!r}")
    out["origin"] = tuple(float(v) for v in origin)
    for key, default in _DEFAULTS.items():
        out[key] = meta.get(key, default)
    neg = out["negate"]
    if isinstance(neg, bool) or neg in (0, 1):
        out["negate"] = bool(neg)
    else:
        raise MapError(f"{where}: key 'negate' must be 0, 1, true or false, got {neg!r}")
    for key in ("occupied_thresh", "free_thresh"):
        if key in meta:
            out[key] = _number(meta, key, where)
        if not 0.0 <= out[key] <= 1.0:
            raise MapError(f"{where}: key '{key}' must be in [0, 1], got {out[key]!r}")
    if out["free_thresh"] >= out["occupied_thresh"]:
        raise MapError(f"{where}: key 'free_thresh' ({out['free_thresh']}) must be smaller than "
                       f"'occupied_thresh' ({out['occupied_thresh']})")
    mode = out["mode"]
    if not isinstance(mode, str) or mode.lower() not in _MODES:
        raise MapError(f"{where}: key 'mode' must be one of {', '.join(_MODES)}, got {mode!r}")
    out["mode"] = mode.lower()
    return out


def _read_image(path: Path, where: Path, mode: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Return (shade (H, W) float64 in [0, 1], alpha (H, W) float64 in [0, 1] or None)."""
    if not path.is_file():
        raise MapError(f"{where}: key 'image' names {path}, which does not exist")
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode == "P":
                im = im.convert("RGBA" if "transparency" in im.info else "RGB")
            elif im.mode == "1":
                im = im.convert("L")
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                arr = np.asarray(im, dtype=np.float64)
                maxval = 65535.0 if arr.max(initial=0) > 255 or im.mode.startswith("I;16") else 255.0
                return np.clip(arr / maxval, 0.0, 1.0), None
            if im.mode not in ("L", "LA", "RGB", "RGBA"):
                im = im.convert("RGBA" if "A" in im.mode else "RGB")
            arr = np.asarray(im, dtype=np.float64) / 255.0
    except MapError:
        raise
    except Exception as exc:  # PIL raises several unrelated types
        raise MapError(f"{where}: key 'image': cannot read {path}: {exc}") from exc
    if arr.ndim == 2:
        return arr, None
    has_alpha = arr.shape[2] in (2, 4)
    colour = arr[..., :-1] if has_alpha else arr
    alpha = arr[..., -1] if has_alpha else None
    if mode == "trinary" and alpha is not None:
        shade = arr.mean(axis=2)     # colour channels and alpha averaged, as map_server does
    else:
        shade = colour.mean(axis=2)
    return shade, alpha


def load_map(yaml_path: str | Path) -> OccupancyMap:
    """Load a map_server map (YAML + image) into an :class:`OccupancyMap`.

    Args:
        yaml_path: the map's YAML file; ``image`` is resolved relative to it.
    Returns:
        The map with occupancy (H, W) int8 in {-1, 0..100}, row 0 at the top.
    Raises:
        MapError (a ValueError): unreadable or invalid YAML, a missing or bad key,
            or a missing/unreadable image; the message names the file and the key.
    """
    where = Path(yaml_path)
    try:
        text = where.read_text()
    except OSError as exc:
        raise MapError(f"{where}: cannot read map YAML: {exc}") from exc
    try:
        meta = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise MapError(f"{where}: invalid YAML: {exc}") from exc
    p = _parse_meta(meta, where)
    image_path = Path(p["image"]).expanduser()
    if not image_path.is_absolute():
        image_path = where.parent / image_path
    shade, alpha = _read_image(image_path, where, p["mode"])
    occ = shade if p["negate"] else 1.0 - shade
    out = np.full(shade.shape, UNKNOWN, dtype=np.int8)
    mode = p["mode"]
    occ_t, free_t = p["occupied_thresh"], p["free_thresh"]
    if mode == "raw":
        val = np.rint(shade * 255.0)
        ok = (val >= 0) & (val <= 100)
        out[ok] = val[ok].astype(np.int8)
    else:
        out[occ < free_t] = FREE
        out[occ > occ_t] = OCCUPIED
        if mode == "scale":
            mid = (occ >= free_t) & (occ <= occ_t)
            out[mid] = np.rint((occ[mid] - free_t) / (occ_t - free_t) * 100.0).astype(np.int8)
            if alpha is not None:
                out[alpha < 1.0] = UNKNOWN
    return OccupancyMap(occupancy=out, resolution=p["resolution"], origin=p["origin"], image=image_path)


def save_map(occupancy: OccupancyMap, yaml_path: str | Path, image_name: str | None = None) -> Path:
    """Write ``occupancy`` as a trinary map_server map (PGM + YAML), as ``map_saver`` does.

    Free -> 254, occupied (>= OCCUPIED_MIN) -> 0, unknown -> 205; thresholds
    0.65 / 0.196. Returns the YAML path. Loading it back gives the same
    free/occupied/unknown classification.
    """
    yaml_path = Path(yaml_path)
    image_name = image_name or yaml_path.with_suffix(".pgm").name
    occ = occupancy.occupancy
    img = np.full(occ.shape, 205, dtype=np.uint8)
    img[(occ >= 0) & (occ < OCCUPIED_MIN)] = 254
    img[occ >= OCCUPIED_MIN] = 0
    Image.fromarray(img, mode="L").save(yaml_path.parent / image_name)
    meta = {
        "image": image_name,
        "mode": "trinary",
        "resolution": occupancy.resolution,
        "origin": [float(v) for v in occupancy.origin],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    yaml_path.write_text(yaml.safe_dump(meta, sort_keys=False, default_flow_style=None))
    return yaml_path
