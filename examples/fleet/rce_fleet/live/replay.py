"""``rce-fleet replay run.mcap``: a recording of ``rce-fleet demo/serve --record run.mcap`` played back onto the
operator page (and, with ``--foxglove-port``, to Foxglove).

The player starts an engine of its own, creates the fleet container (no planner in it: the recording is the
fleet) and publishes the recorded ``/fleet/state`` and ``/fleet/tasks`` into it, in the recorded order
and at the recorded pace (``--speed`` times faster), through forwarders of its client ``fleetReplay``: the
page, logged in as usual, draws them as it draws a live fleet. The map, the grid, the places and the robots
come from the file (``/map`` and the metadata record ``rce-fleet``, :func:`rce_fleet.live.fleet_bag.write_scene`).
At the end of the file it stops (``--loop``: starts again) and keeps the page up until Ctrl-C.

:func:`read_scene` (the file's map and grid) and :func:`recorded` (its messages, in log-time order, read as
they are played, never all in memory) are the reading half, without I/O beyond the file.
"""
from __future__ import annotations

import asyncio
import json
import random
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from rce.plumbing.errors import RCEError
from rce.plumbing.log import get_logger, setup_logging
from rce.plumbing.process import run_loop
from rce.tools.launch import start_engine
from rce_client.connection import Connection

from ..configs import FLEET_CTAG, PASSWORD, USER
from ..maps.geometry import GridGeometry
from ..maps.occupancy import OccupancyMap
from ..operations.places import Places
from .fleet_bag import REPLAY_METADATA

log = get_logger("fleet.replay")

REPLAY_ID = "fleetReplay"        # robotID of the player's client
PLAYED = (("/fleet/state", "fleet/FleetState"), ("/fleet/tasks", "fleet/TaskList"))
SETUP_TIMEOUT_S = 60.0           # s for the container and the player's interfaces
TEARDOWN_TIMEOUT_S = 10.0
EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


class ReplayError(ValueError):
    """A file that is not an rce-fleet recording (not MCAP, or without the map, grid or fleet state)."""


def read_scene(path: Path, reg) -> tuple[OccupancyMap, GridGeometry, Places, list[str]]:
    """The map (from ``/map``), grid, places and robots (from the ``rce-fleet`` metadata record) of the
    recording ``path``. Raises :class:`ReplayError` naming what is missing, OSError when unreadable."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            meta = {m.name: m.metadata for m in reader.iter_metadata()}
            if REPLAY_METADATA not in meta:
                raise ReplayError(f"{path}: no '{REPLAY_METADATA}' metadata: not a recording of rce-fleet --record")
            grid = None
            for _schema, _channel, message in reader.iter_messages(topics=["/map"]):
                grid = reg.deserialize("nav_msgs/msg/OccupancyGrid", message.data)
                break
    except McapError as e:
        raise ReplayError(f"{path}: not an MCAP file: {e}") from None
    if grid is None:
        raise ReplayError(f"{path}: no /map message")
    info, q = grid.info, grid.info.origin.orientation
    yaw = 2 * np.arctan2(q.z, q.w)
    occ = OccupancyMap(np.flipud(np.asarray(grid.data, dtype=np.int8).reshape(info.height, info.width)),
                       info.resolution, (info.origin.position.x, info.origin.position.y, float(yaw)))
    m = meta[REPLAY_METADATA]
    geo = GridGeometry.from_param(json.loads(m["grid"]))
    return occ, geo, Places.from_param(json.loads(m.get("places", "[]")), geo), json.loads(m["robots"])


def recorded(path: Path, topics: list[str]) -> Iterator[tuple[int, str, bytes]]:
    """(log time ns, topic, ROS 1 bytes) of ``topics`` in ``path``, in log-time order."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages(topics=topics, log_time_order=True):
            yield message.log_time, channel.topic, message.data


class Player:
    """Plays ``path`` (module docstring) at ``speed`` times the recorded pace; ``loop``: again from the start."""

    def __init__(self, path: Path, *, speed: float = 1.0, loop: bool = False, web_port: int | None = 8000,
                 foxglove_port: int | None = None, workdir: Path | None = None):
        self.path, self.speed, self.loop = path, speed, loop
        self.web_port, self.foxglove_port = web_port, foxglove_port
        self.workdir = workdir
        self.played = 0
        self.engine = self.conn = self.web = self.foxglove = None
        self._stop = asyncio.Event()

    async def run(self) -> int:
        """Set up, play, keep the page up until Ctrl-C; returns the exit code."""
        from rce.messages import default_registry
        from rce.node.package_path import load_package_types
        reg = default_registry()
        load_package_types(reg)
        try:
            occ, geo, places, robots = read_scene(self.path, reg)
        except (ReplayError, OSError) as e:
            print(f"rce-fleet replay: {e}", file=sys.stderr)
            return EXIT_USAGE
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, self._stop.set)
        own = self.workdir is None
        workdir = Path(tempfile.mkdtemp(prefix="rce-replay-")) if own else self.workdir
        try:
            self.engine = await asyncio.to_thread(start_engine, workdir / "engine",
                                                  admin_token=f"replay-{random.getrandbits(64):016x}")
            pubs = await self._connect()
            await self._serve(occ, geo, places, robots, reg)
            await self._play(pubs)
            print(f"rce-fleet: replay done: {self.played} messages played; Ctrl-C to stop", flush=True)
            await self._stop.wait()
            return EXIT_OK
        except (RCEError, TimeoutError, OSError) as e:
            print(f"rce-fleet replay: {e}", file=sys.stderr)
            return EXIT_FAIL
        finally:
            await self._teardown()
            if own:
                shutil.rmtree(workdir, ignore_errors=True)

    async def _connect(self) -> dict:
        c = self.conn = await Connection.connect(self.engine.master_url, USER, PASSWORD, REPLAY_ID,
                                                 allow_reconnect=True)
        await c.create_container(FLEET_CTAG)
        adds, tags, pubs = [], [], {}
        for i, (topic, cls) in enumerate(PLAYED):
            tag = f"{REPLAY_ID}_{i}"
            adds += [{"endpointTag": FLEET_CTAG, "interfaceTag": tag, "interfaceType": "PublisherInterface",
                      "className": cls, "addr": topic},
                     {"endpointTag": REPLAY_ID, "interfaceTag": tag, "interfaceType": "SubscriberForwarder",
                      "className": cls}]
            pubs[topic] = c.publisher(tag, cls)
            tags.append(tag)
        await c.configure({"addInterfaces": adds})
        await c.send("CX", {"connect": [{"tagA": f"{FLEET_CTAG}/{t}", "tagB": f"{REPLAY_ID}/{t}"} for t in tags]})
        await c.barrier(SETUP_TIMEOUT_S)
        await c.wait_interfaces_up(tags, SETUP_TIMEOUT_S)
        return pubs

    async def _serve(self, occ, geo, places, robots, reg) -> None:
        if self.web_port is not None:
            from .webui import WebUI
            self.web = WebUI(self.engine.master_url, occ, geo, robots, ctag=FLEET_CTAG, user=USER, password=PASSWORD,
                             port=self.web_port, mission=False, places=places, title="rce fleet (replay)")
            url = await self.web.start()
            print(f"rce-fleet: operator page: {url}  (log in as {USER}; replaying {self.path.name})", flush=True)
        if self.foxglove_port is not None:
            from .fleet_scene import FleetScene
            from .foxglove import FleetFoxglove
            self.foxglove = FleetFoxglove(self.engine.master_url, FleetScene(geo, occ, places, reg), robots,
                                          user=USER, password=PASSWORD, port=self.foxglove_port)
            print(f"rce-fleet: Foxglove WebSocket: {await self.foxglove.start()}", flush=True)

    async def _play(self, pubs: dict) -> None:
        while not self._stop.is_set():
            wall0, t0 = time.monotonic(), None
            for t, topic, raw in recorded(self.path, list(pubs)):
                t0 = t if t0 is None else t0
                wait = (t - t0) / 1e9 / self.speed - (time.monotonic() - wall0)
                if wait > 0:
                    try:
                        async with asyncio.timeout(wait):
                            await self._stop.wait()
                        return
                    except TimeoutError:
                        pass
                await pubs[topic].publish(raw)
                self.played += 1
            if not self.loop:
                return

    async def _teardown(self) -> None:
        try:
            for part in (self.foxglove, self.web):
                if part is not None:
                    async with asyncio.timeout(TEARDOWN_TIMEOUT_S):
                        await (part.close() if part is self.foxglove else part.stop())
            if self.conn is not None:
                async with asyncio.timeout(TEARDOWN_TIMEOUT_S):
                    await self.conn.close()
        except (TimeoutError, RCEError, OSError) as e:
            log.warning("teardown incomplete", reason=str(e))
        finally:
            if self.engine is not None:
                await asyncio.to_thread(self.engine.stop)


def run(path: str, *, speed: float, loop: bool, web_port: int | None, foxglove_port: int | None) -> int:
    """``rce-fleet replay``: 0 played and stopped, 1 a failure, 2 a file that is not a recording."""
    setup_logging()
    return run_loop(Player(Path(path), speed=speed, loop=loop, web_port=web_port,
                           foxglove_port=foxglove_port).run())
