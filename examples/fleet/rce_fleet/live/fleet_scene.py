"""The fleet as messages Foxglove (and Lichtblick, RViz) draw without plugins, all in frame ``map``:

=========================  ===============================  ==========================================
topic                      class                            what
=========================  ===============================  ==========================================
``/map``                   ``nav_msgs/OccupancyGrid``       the map (row 0 at the map's origin, as ROS)
``/fleet/places``          ``visualization_msgs/MarkerArray`` pick-ups, drop-offs, chargers, parking
``/fleet/task_markers``    ``visualization_msgs/MarkerArray`` each open task's errands (a line from its
                                                            robot), blocked cells
``/RobotN/pose``           ``geometry_msgs/PoseStamped``    the robot's pose estimate
``/RobotN/path``           ``nav_msgs/Path``                the cells still to traverse, by centre
=========================  ===============================  ==========================================

Built from the fleet's own messages (``fleet/FleetState``, ``fleet/TaskList``, in their JSON form) and the
map; every function returns ROS 1 serialized bytes. Sans I/O.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..maps.geometry import GridGeometry
from ..operations.places import Places

FRAME = "map"
POSE, PATH, GRID, MARKERS = ("geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Path", "nav_msgs/msg/OccupancyGrid",
                             "visualization_msgs/msg/MarkerArray")
CUBE, CYLINDER, LINE_STRIP, TEXT, DELETEALL = 1, 3, 4, 9, 3
PLACE_COLOURS = {"charger": (0.1, 0.8, 0.2), "pickup": (0.2, 0.4, 1.0), "dropoff": (1.0, 0.55, 0.1),
                 "parking": (0.55, 0.55, 0.55)}
TASK_COLOUR, QUEUED_COLOUR, BLOCKED_COLOUR = (0.9, 0.2, 0.9), (0.9, 0.8, 0.2), (0.9, 0.1, 0.1)
OPEN_STATES = ("queued", "assigned", "active")


def _stamp(t: float) -> dict:
    secs = max(0, int(t))
    return {"secs": secs, "nsecs": int((t - secs) * 1e9)}


def _header(t: float) -> dict:
    return {"frame_id": FRAME, "stamp": _stamp(t)}


def _pose(x: float, y: float, yaw: float = 0.0, z: float = 0.0) -> dict:
    return {"position": {"x": x, "y": y, "z": z},
            "orientation": {"z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}}


def _colour(rgb: tuple[float, float, float], a: float = 0.8) -> dict:
    return {"r": rgb[0], "g": rgb[1], "b": rgb[2], "a": a}


class FleetScene:
    """Messages of one fleet: ``geo`` (its grid), ``occ`` (its :class:`~rce_fleet.maps.occupancy.OccupancyMap`),
    ``places``, ``reg`` (a :class:`~rce.messages.MessageRegistry`)."""

    def __init__(self, geo: GridGeometry, occ, places: Places | None, reg):
        self.geo, self.occ, self.places, self.reg = geo, occ, places, reg
        self.cell = min(geo.cell_w_m, geo.cell_h_m)

    def occupancy_grid(self) -> bytes:
        """``/map``: the map as ``nav_msgs/OccupancyGrid`` (-1 unknown, 0 - 100 occupancy)."""
        o = self.occ
        ox, oy, yaw = o.origin
        msg = self.reg.from_json(GRID, {"header": _header(0.0), "info": {
            "resolution": float(o.resolution), "width": int(o.width), "height": int(o.height),
            "origin": _pose(float(ox), float(oy), float(yaw))}, "data": []})
        data = np.ascontiguousarray(np.flipud(np.asarray(o.occupancy, dtype=np.int8))).reshape(-1)
        return self.reg.serialize(GRID, dataclasses.replace(msg, data=data))

    def place_markers(self) -> bytes:
        """``/fleet/places``: a cylinder and a label per place, coloured by kind."""
        markers = []
        places = [p for k in PLACE_COLOURS for p in self.places.of_kind(k)] if self.places else []
        for place in places:
            x, y = self.geo.center(place.cell)
            rgb = PLACE_COLOURS[place.kind]
            markers.append({"header": _header(0.0), "ns": f"places/{place.kind}", "id": place.cell,
                            "type": CYLINDER, "pose": _pose(x, y, z=0.05), "color": _colour(rgb, 0.5),
                            "scale": {"x": self.cell * 0.6, "y": self.cell * 0.6, "z": 0.1}})
            markers.append({"header": _header(0.0), "ns": "places/labels", "id": place.cell, "type": TEXT,
                            "pose": _pose(x, y, z=0.4), "color": _colour(rgb, 1.0),
                            "scale": {"z": self.cell * 0.3}, "text": place.name})
        return self.reg.json_to_bytes(MARKERS, {"markers": markers})

    def robot_pose(self, r: dict, t: float) -> bytes:
        """``/RobotN/pose`` of one robot of a ``fleet/FleetState`` (its ``x``, ``y``, ``yaw``)."""
        return self.reg.json_to_bytes(POSE, {"header": _header(t), "pose": _pose(r["x"], r["y"], r["yaw"])})

    def robot_path(self, r: dict, t: float) -> bytes:
        """``/RobotN/path``: the robot, then the centres of the cells still to traverse."""
        hdr = _header(t)
        poses = [{"header": hdr, "pose": _pose(r["x"], r["y"], r["yaw"])}]
        for c in list(r.get("path", []))[1:]:
            x, y = self.geo.center(int(c))
            poses.append({"header": hdr, "pose": _pose(x, y)})
        return self.reg.json_to_bytes(PATH, {"header": hdr, "poses": poses})

    def task_markers(self, state: dict | None, tasks: dict | None, t: float) -> bytes:
        """``/fleet/task_markers``: each open task's errands (from its robot when it has one) and the blocked
        cells, after a DELETEALL of the previous ones."""
        hdr = _header(t)
        markers: list[dict] = [{"header": hdr, "ns": "tasks", "id": 0, "action": DELETEALL}]
        where = {r["robot"]: (r["x"], r["y"]) for r in (state or {}).get("robots", [])}
        for i, task in enumerate((tasks or {}).get("tasks", [])):
            if task.get("state") not in OPEN_STATES:
                continue
            cells = list(task.get("cells", []))[max(0, int(task.get("next_errand", 0))):]
            pts = [self.geo.center(int(c)) for c in cells if self.geo.valid(int(c))]
            if task.get("robot") in where:
                pts.insert(0, where[task["robot"]])
            if not pts:
                continue
            rgb = TASK_COLOUR if task.get("robot") else QUEUED_COLOUR
            markers.append({"header": hdr, "ns": "tasks", "id": i + 1, "type": LINE_STRIP if len(pts) > 1 else CUBE,
                            "pose": _pose(0.0, 0.0) if len(pts) > 1 else _pose(*pts[0], z=0.1),
                            "scale": {"x": self.cell * 0.08, "y": self.cell * 0.3, "z": self.cell * 0.3},
                            "color": _colour(rgb, 0.9), "text": str(task.get("id", "")),
                            "points": [{"x": x, "y": y, "z": 0.1} for x, y in pts] if len(pts) > 1 else []})
        for j, c in enumerate((state or {}).get("blocked", [])):
            x, y = self.geo.center(int(c))
            markers.append({"header": hdr, "ns": "blocked", "id": j, "type": CUBE, "pose": _pose(x, y, z=0.15),
                            "scale": {"x": self.cell * 0.9, "y": self.cell * 0.9, "z": 0.3},
                            "color": _colour(BLOCKED_COLOUR, 0.6)})
        return self.reg.json_to_bytes(MARKERS, {"markers": markers})
