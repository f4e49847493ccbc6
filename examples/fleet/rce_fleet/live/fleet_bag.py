"""``rce-fleet demo --bag`` and ``--record``: the fleet topics recorded into a ROS 1 bag or an MCAP file
(:func:`rce_client.mcap_recorder.recorder_for`, by the file's suffix).

Every robot's ``amcl_pose``, ``goalNodesList`` and ``cancelGoal`` and ``/fleet/state``, recorded from
the fleet container through forwarders of the client ``fleetRecorder`` (:mod:`rce_client.bag`), and
``/fleet/tasks`` in an MCAP file (what ``rce-fleet replay`` shows besides the fleet state).
"""
from __future__ import annotations

import asyncio

from rce.messages import MessageRegistry
from rce_client.bag import BagRecorder, record_container
from rce_client.connection import Connection
from rce_client.mcap_recorder import McapRecorder, recorder_for

from ..configs import FLEET_CTAG, PASSWORD, USER

RECORDER_ID = "fleetRecorder"   # robotID of the recorder's connection


class FleetBag:
    """One run's recording of the fleet topics at ``path`` (``.bag``: a ROS 1 bag v2.0; ``.mcap``: MCAP),
    by the client ``recorder_id``."""

    def __init__(self, path: str, robots: list[str], recorder_id: str = RECORDER_ID, scene=None):
        self.path = path
        self.robots = robots
        self.recorder_id = recorder_id
        self.scene = scene          # a FleetScene: an MCAP file also gets the map, the places and the grid
        self.bag: BagRecorder | McapRecorder | None = None
        self.recorder: Connection | None = None

    def topics(self) -> list[tuple[str, str]]:
        """(topic, class) of the fleet container's topics recorded."""
        per_robot = [(f"/{r}/{name}", cls) for r in self.robots for name, cls in (
            ("amcl_pose", "geometry_msgs/PoseWithCovarianceStamped"), ("goalNodesList", "std_msgs/Int32MultiArray"),
            ("cancelGoal", "std_msgs/Bool"))]
        tasks = [("/fleet/tasks", "fleet/TaskList")] if str(self.path).lower().endswith(".mcap") else []
        return [*per_robot, ("/fleet/state", "fleet/FleetState"), *tasks]

    async def start(self, master_url: str, reg: MessageRegistry, timeout: float, user: str = USER,
                    password: str = PASSWORD) -> None:
        """Open the bag and connect the recorder, as ``user`` (the fleet container's owner), to the fleet
        container's topics.

        Raises RCEError when the engine refuses the recorder or its interfaces, TimeoutError after
        ``timeout`` s, OSError when the bag cannot be written."""
        self.bag = recorder_for(self.path, reg)
        self.bag.open()
        if isinstance(self.bag, McapRecorder) and self.scene is not None:
            write_scene(self.bag, self.scene, self.robots)
        self.recorder = await Connection.connect(master_url, user, password, self.recorder_id, allow_reconnect=True)
        await record_container(self.recorder, FLEET_CTAG, self.topics(), self.bag, timeout=timeout)

    async def stop(self, timeout: float) -> None:
        """Disconnect the recorder (within ``timeout`` s) and finish the bag; once, again is a no-op."""
        rec, self.recorder = self.recorder, None
        try:
            if rec is not None:
                async with asyncio.timeout(timeout):
                    await rec.close()
        finally:
            if self.bag is not None and self.bag.is_open:
                self.bag.close()
                print(f"rce-fleet: {self.bag.summary()}", flush=True)

    def report(self) -> dict | None:
        """The report's ``bag`` section: the path and the messages per topic (None before ``start``)."""
        return {"path": str(self.bag.path), "messages": dict(self.bag.counts)} if self.bag else None


REPLAY_METADATA = "rce-fleet"     # the MCAP metadata record rce-fleet replay reads: grid, places, robots


def write_scene(rec: McapRecorder, scene, robots: list[str]) -> None:
    """Start an MCAP recording with what a player needs besides the messages: ``/map``
    (``nav_msgs/OccupancyGrid``) and ``/fleet/places`` (``visualization_msgs/MarkerArray``), and the metadata
    record :data:`REPLAY_METADATA` (``grid``: the grid's parameter, ``places``, ``robots``; JSON strings)."""
    import json
    rec.write("/map", "nav_msgs/OccupancyGrid", scene.occupancy_grid())
    rec.write("/fleet/places", "visualization_msgs/MarkerArray", scene.place_markers())
    rec.add_metadata(REPLAY_METADATA, {"grid": json.dumps(scene.geo.to_param()), "robots": json.dumps(robots),
                                       "places": json.dumps(scene.places.to_param() if scene.places else [])})
