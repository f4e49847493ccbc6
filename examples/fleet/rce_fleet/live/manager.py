"""The fleet manager: the cloud side's operator client (robotID ``fleetManager``).

An RCE client like any robot (login, websocket, CC/CN/CX requests, the client library of
:mod:`rce_client.connection`). It

1. creates the fleet container ``cTag_01`` (the paper: one container for all),
2. sets the parameters ``/fleet/grid`` (:class:`rce_fleet.maps.geometry.GridGeometry`) and
   ``/fleet/robots``,
3. starts the ``fleet/global_planner`` node,
4. adds the operator interfaces and connects them:

   =========================  ==========================  ========================
   container side (cTag_01)   manager side                topic, class
   =========================  ==========================  ========================
   fleetGoalReceiver  PubIf   fleetGoalSender  SubConv    /fleet/goal  fleet/RobotGoal
   fleetBlockReceiver PubIf   fleetBlockSender SubConv    /fleet/block fleet/CellBlock
   fleetStateSender   SubIf   fleetStateReceiver PubConv  /fleet/state fleet/FleetState
   =========================  ==========================  ========================

The manager's interfaces are Converters (JSON), as a browser's would be.

It also sets ``/fleet/places`` (:mod:`rce_fleet.operations.places`) and ``/fleet/battery``
(:mod:`rce_fleet.operations.battery`) when given, and attaches a :class:`rce_fleet.operations.tasks_client.TaskChannel`
(``tasks``): the operators' task API that ``rce-fleet serve``'s HTTP API and the demo's task
generator use. ``task_stats`` keeps what a warehouse manager watches (tasks done per minute,
queue length, utilisation), for the page's plots and the Prometheus metrics.

Stalls. Each ``fleet/TaskList`` names, per robot, the stall alert the dispatcher raised
(:mod:`rce_fleet.operations.dispatcher`: a robot that holds work and makes no progress): the manager
logs each new alert as a warning, and the robot's return to progress; ``alerts`` keeps the newest
(bounded) for the run's report, and ``on_alert(robot, text)`` hears them.
"""
from __future__ import annotations

import asyncio
from collections import deque
from typing import Callable

from rce.plumbing.errors import RCEError, Unavailable
from rce.plumbing.log import get_logger
from rce_client.connection import Connection

from ..configs import FLEET_CTAG, PASSWORD, USER
from ..operations.battery import BATTERY_PARAM, BatteryParams
from ..maps.geometry import GRID_PARAM, ROBOTS_PARAM, GridGeometry
from ..operations.places import PLACES_PARAM, Places
from ..operations.tasks_client import TaskChannel

log = get_logger("fleet.manager")

MANAGER_ID = "fleetManager"
SETUP_TIMEOUT_S = 60.0   # s for the fleet container, its planner and the operator interfaces to come up
CLOSE_TIMEOUT_S = 5.0    # s the cloud gets to confirm the container's removal at close
MAX_ALERTS = 200         # stall alerts kept in ``FleetManager.alerts`` (the oldest go first, counted)

_IFACES = [  # container iTag, container type, manager iTag, manager type, class, topic
    ("fleetGoalReceiver", "PublisherInterface", "fleetGoalSender", "SubscriberConverter", "fleet/RobotGoal",
     "/fleet/goal"),
    ("fleetBlockReceiver", "PublisherInterface", "fleetBlockSender", "SubscriberConverter", "fleet/CellBlock",
     "/fleet/block"),
    ("fleetStateSender", "SubscriberInterface", "fleetStateReceiver", "PublisherConverter", "fleet/FleetState",
     "/fleet/state"),
]


class FleetManager:
    """Create the fleet's cloud side and talk to its global planner.

    ``on_state(state_dict)`` receives every ``/fleet/state``; ``latest`` keeps the last one.
    ``container_cpu``: cores the fleet container asks for (its ``containerData`` ``cpu``: the
    cores the master reserves for it, its CPU quota and its weight when every core is busy;
    None: no request, the weight of one process). ``on_alert(robot, text)``: a robot's new stall
    alert (module docstring)."""

    def __init__(self, master_url: str, geometry: GridGeometry, robots: list[str], *, user: str = USER,
                 password: str = PASSWORD, robot_id: str = MANAGER_ID, ctag: str = FLEET_CTAG,
                 planner_args: str = "", on_state: Callable[[dict], None] | None = None,
                 container_cpu: float | None = None, places: Places | None = None,
                 battery: BatteryParams | None = None, on_tasks: Callable[[dict], None] | None = None,
                 on_alert: Callable[[str, str], None] | None = None):
        self.master_url, self.geo, self.robots = master_url, geometry, list(robots)
        self.user, self.password, self.robot_id, self.ctag = user, password, robot_id, ctag
        self.planner_args = planner_args
        self.container_cpu = container_cpu
        self.on_state = on_state
        self.places, self.battery, self.on_tasks, self.on_alert = places, battery, on_tasks, on_alert
        self.alerts: deque[dict] = deque(maxlen=MAX_ALERTS)   # {"t": fleet s, "robot", "text"}, newest last
        self.alerts_dropped = 0
        self._alert_of: dict[str, str] = {}                  # robot -> its current alert
        self.tasks: TaskChannel | None = None
        self.conn: Connection | None = None
        self.latest: dict | None = None
        self.states = 0
        self.errors: list[str] = []
        self._goal_pub = self._block_pub = None
        self._state_event = asyncio.Event()

    async def start(self, timeout: float = SETUP_TIMEOUT_S) -> None:
        """Log in (with session resume: the connection rides out a lost link, ``allow_reconnect``;
        ``max_lag=0``: goals and blocks are commands, which the robot endpoint never sheds even when it
        lags behind), create the container, the planner and the operator interfaces; returns when the
        interfaces are up (within ``timeout`` s). Raises :class:`RCEError` with the cloud's
        reason."""
        conn = self.conn = await Connection.connect(self.master_url, self.user, self.password, self.robot_id,
                                                    allow_reconnect=True, max_lag=0)
        conn.on_error(self._on_error)
        conn.on_status(self._on_status)
        await conn.create_container(self.ctag, cpu=self.container_cpu)
        await conn.set_param(self.ctag, GRID_PARAM, self.geo.to_param())
        await conn.set_param(self.ctag, ROBOTS_PARAM, self.robots)
        if self.places is not None:
            await conn.set_param(self.ctag, PLACES_PARAM, self.places.to_param())
        if self.battery is not None:
            await conn.set_param(self.ctag, BATTERY_PARAM, self.battery.to_param())
        await conn.add_node(self.ctag, "global_planner", "fleet", "global_planner", args=self.planner_args)
        adds, links = [], []
        for c_tag, c_type, m_tag, m_type, cls, topic in _IFACES:
            adds.append({"endpointTag": self.ctag, "interfaceTag": c_tag, "interfaceType": c_type,
                         "className": cls, "addr": topic})
            adds.append({"endpointTag": self.robot_id, "interfaceTag": m_tag, "interfaceType": m_type,
                         "className": cls})
            links.append({"tagA": f"{self.ctag}/{c_tag}", "tagB": f"{self.robot_id}/{m_tag}"})
        conn.subscriber("fleetStateReceiver", "fleet/FleetState", self._on_fleet_state)
        self._goal_pub = conn.publisher("fleetGoalSender", "fleet/RobotGoal")
        self._block_pub = conn.publisher("fleetBlockSender", "fleet/CellBlock")
        await conn.configure({"addInterfaces": adds})
        await conn.send("CX", {"connect": links})
        n = len(self.errors)
        await conn.barrier(timeout)
        if len(self.errors) > n:
            raise Unavailable(f"fleet manager setup refused: {self.errors[n]}")
        await conn.wait_interfaces_up([m for _, _, m, _, _, _ in _IFACES], timeout)
        self.tasks = TaskChannel(conn, self.robot_id, self.ctag, source="manager", on_tasks=self._on_task_list)
        await self.tasks.attach(timeout)
        log.info("fleet container up", ctag=self.ctag, robots=len(self.robots))

    def _on_task_list(self, task_list: dict) -> None:
        """Log the robots' new stall alerts and their returns to progress, then pass the list on."""
        stamp = task_list.get("header", {}).get("stamp", {})
        t = float(stamp.get("secs", 0)) + float(stamp.get("nsecs", 0)) / 1e9
        for r in task_list.get("robots", []):
            name, text = r.get("robot", ""), str(r.get("alert", ""))
            before = self._alert_of.get(name, "")
            if text == before:
                continue
            self._alert_of[name] = text
            if text:
                log.warning("robot stalled", robot=name, stalled_s=round(float(r.get("stalled_s", 0.0)), 1),
                            t_fleet=round(t, 1), alert=text)
                self.alerts_dropped += len(self.alerts) == self.alerts.maxlen
                self.alerts.append({"t": round(t, 2), "robot": name, "text": text})
                if self.on_alert:
                    self.on_alert(name, text)
            else:
                log.info("robot makes progress again", robot=name, t_fleet=round(t, 1))
        if self.on_tasks:
            self.on_tasks(task_list)

    def _on_error(self, reason: str) -> None:
        self.errors.append(reason)
        log.warning("error from the cloud", reason=reason)

    def _on_status(self, st: dict) -> None:
        if st.get("topic") == "node" and st.get("status") not in ("started",):
            log.warning("node status", node=st.get("nTag"), status=st.get("status"),
                        **{k: st[k] for k in ("code", "signal", "reason") if st.get(k) is not None})

    def _on_fleet_state(self, msg) -> None:
        if not isinstance(msg, dict):
            return
        self.latest = msg
        self.states += 1
        self._state_event.set()
        if self.on_state:
            self.on_state(msg)

    async def wait_state(self, pred: Callable[[dict], bool], timeout: float) -> dict:
        """The first fleet state (current or later) for which ``pred`` holds; raises
        :class:`Unavailable` after ``timeout`` s."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            if self.latest is not None and pred(self.latest):
                return self.latest
            left = deadline - loop.time()
            if left <= 0:
                raise Unavailable(f"fleet state condition not met within {timeout:g} s")
            self._state_event.clear()
            try:
                async with asyncio.timeout(left):
                    await self._state_event.wait()
            except TimeoutError:
                pass

    async def set_goal(self, robot: str, cell: int) -> None:
        """Publish a ``fleet/RobotGoal`` on ``/fleet/goal`` (-1 drops the goal)."""
        await self._goal_pub.publish({"robot": robot, "cell": int(cell)})

    async def block(self, cell: int, blocked: bool = True, source: str = "operator") -> None:
        """Publish a ``fleet/CellBlock`` on ``/fleet/block``."""
        await self._block_pub.publish({"cell": int(cell), "blocked": bool(blocked), "source": source})

    async def close(self, destroy: bool = True) -> None:
        """Destroy the fleet container (unless ``destroy`` is False) and close the connection."""
        conn = self.conn
        if conn is None or conn.closed:
            return
        try:
            if destroy:
                await conn.destroy_container(self.ctag)
                await conn.barrier(CLOSE_TIMEOUT_S)
        except RCEError as e:
            log.warning("teardown incomplete", reason=e.message)
        finally:
            await conn.close()
