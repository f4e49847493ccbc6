"""``rce-fleet serve --foxglove-port P``: the live fleet for Foxglove and Lichtblick, over the Foxglove
WebSocket protocol (:mod:`rce.foxglove`).

Open ``wss://HOST:P/?token=TOKEN`` (``ws://`` without TLS) in Foxglove ("Open connection", "Foxglove
WebSocket"), ``TOKEN`` a bearer token of the operator page's ``POST /api/login`` (docs/task-api.md): the
port is one more door of the page's server, on its address (``--web-bind``), its TLS (``--tls-cert``) and its
credentials. A viewer may watch; publishing needs an operator. No password or digest of one is taken here
(a token expires and can be revoked; a password's digest works at every rce door). ``GET /metrics`` needs a
viewer's token too (``Authorization: Bearer`` or ``?token=``), unless ``--metrics-public``.

Advertised, with their full ROS 1 definitions (encoding ``ros1``, schema encoding ``ros1msg``): the
fleet's own ``/fleet/state`` (``fleet/FleetState``) and ``/fleet/tasks`` (``fleet/TaskList``) as the
global planner publishes them, and what Foxglove's 3D panel draws without plugins
(:mod:`rce_fleet.live.fleet_scene`): ``/map``, ``/fleet/places`` and ``/fleet/task_markers``, each robot's
``/RobotN/pose`` and ``/RobotN/path``. ``/map`` and ``/fleet/places`` are latched.

Clients may publish (``clientPublish``), in ``ros1`` or ``json``, on the operator's topics: ``/fleet/goal``
(``fleet/RobotGoal``), ``/fleet/block`` (``fleet/CellBlock``), ``/fleet/task`` (``fleet/Task``) and
``/fleet/task_cancel`` (``fleet/TaskCancel``); and ``/RobotN/goal_pose`` (``geometry_msgs/PoseStamped``, what the
3D panel's "Publish pose" sends, in frame ``map``): RobotN's goal is the grid cell of that point. Anything else is
answered with a ``status`` error. Who did it is the server's to say: the ``source`` of a task, a cancel or a block
is set to ``foxglove:USER`` of the client's token, whatever the client sent.

The fleet's messages come through one RCE client of the fleet's internal user, robotID ``fleetFoxglove``: container
``SubscriberInterface`` -> ``PublisherForwarder`` for the two fleet topics, ``SubscriberForwarder`` ->
``PublisherInterface`` for the four operator topics, so messages go as the engine carries them (ROS 1
bytes), never re-encoded.
"""
from __future__ import annotations

import itertools
import re
import time

import orjson

from rce.foxglove.protocol import JSON, ClientChannel, ros1_schema
from rce.foxglove.server import FoxgloveServer
from rce.plumbing.errors import AuthError, MessageError, RCEError, RequestError
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_client.connection import Connection

from ..configs import FLEET_CTAG
from ..operations.api_auth import Identity, allows
from .fleet_scene import GRID, MARKERS, PATH, POSE, FleetScene

log = get_logger("fleet.foxglove")

ROBOT_ID = "fleetFoxglove"           # robotID of the server's RCE client
SETUP_TIMEOUT_S = 30.0               # s for the server's interfaces to come up
CLOSE_TIMEOUT_S = 5.0                # s the cloud gets to confirm the removal of the server's interfaces
FLEET_TOPICS = (("/fleet/state", "fleet/FleetState"), ("/fleet/tasks", "fleet/TaskList"))
GOAL_POSE = re.compile(r"^/(Robot\d+)/goal_pose$")   # a robot's goal as a pose (Foxglove's "Publish pose")
OPERATOR_TOPICS = {"/fleet/goal": "fleet/RobotGoal", "/fleet/block": "fleet/CellBlock", "/fleet/task": "fleet/Task",
                   "/fleet/task_cancel": "fleet/TaskCancel"}
STAMPED = {"/fleet/block", "/fleet/task", "/fleet/task_cancel"}    # their ``source`` is the server's to set
CLOSE_POLICY = 1008                  # websocket close code: the session's credential no longer holds
REVOKED = "the user's tokens were revoked: connect again with a new token"


class FleetFoxglove:
    """The fleet's Foxglove server (module docstring): ``master_url`` and ``user``/``password`` (the fleet's
    internal user, whose client it runs as), ``scene`` (:class:`~rce_fleet.live.fleet_scene.FleetScene`),
    ``robots`` (``Robot1`` ...), ``auth`` (the page's :class:`~rce_fleet.operations.http_api.ApiAuth`: its tokens
    are this port's credentials; None: a replay's, on loopback, where anyone may watch and no one publish),
    ``bind``, ``port`` and ``ssl_context`` (wss://) as the page's. When a user's tokens are revoked (a new
    role or password, a removal, an admin's revocation), its sessions here are closed with 1008, so no one
    keeps a role they no longer have."""

    def __init__(self, master_url: str, scene: FleetScene, robots: list[str], *, user: str, password: str, auth=None,
                 ctag: str = FLEET_CTAG, bind: str = "127.0.0.1", port: int = 0, ssl_context=None):
        self.master_url, self.scene, self.robots = master_url, scene, list(robots)
        self.user, self.password, self.ctag, self.bind, self.port = user, password, ctag, bind, port
        self.auth, self.ssl_context = auth, ssl_context
        self.reg = scene.reg
        self.server = FoxgloveServer("rce-fleet", authenticate=self._login, on_publish=self._publish,
                                     metric_prefix="rce_fleet_foxglove", authorize_metrics=self._metrics)
        self.conn: Connection | None = None
        self.pubs: dict = {}
        self.ch: dict[str, int] = {}             # topic -> channel id
        self._state: dict | None = None
        self._tasks: dict | None = None
        self._logins = itertools.count(1)
        self._closing = Tasks("fleet-foxglove")
        self.url = ""
        if auth is not None:
            auth.on_revoke.append(self.end_user)

    def end_user(self, user: str) -> None:
        """``user``'s tokens were revoked: close its sessions with 1008 (:data:`REVOKED`)."""
        for client in list(self.server.clients):
            who = client.principal
            if isinstance(who, Identity) and who.user == user:
                log.info("Foxglove session closed: its user's tokens were revoked", user=user)
                self._closing.spawn(client.ws.close(CLOSE_POLICY, REVOKED), name="foxglove-revoked")

    async def start(self, timeout: float = SETUP_TIMEOUT_S) -> str:
        """Connect to the fleet container, advertise the channels and listen; returns the URL to open
        (without the password). Raises RCEError with the cloud's reason, TimeoutError after ``timeout`` s."""
        store = self.reg.store
        for topic, cls in FLEET_TOPICS:
            self._channel(topic, cls)
        for topic, typename, latched in (("/map", GRID, True), ("/fleet/places", MARKERS, True),
                                         ("/fleet/task_markers", MARKERS, False)):
            self.ch[topic] = self.server.add_channel(topic, _wire(typename), ros1_schema(store, typename),
                                                     latched=latched).id
        for r in self.robots:
            self._channel(f"/{r}/pose", _wire(POSE))
            self._channel(f"/{r}/path", _wire(PATH))
        self.server.publish(self.ch["/map"], self.scene.occupancy_grid())
        self.server.publish(self.ch["/fleet/places"], self.scene.place_markers())
        await self._connect(timeout)
        await self.server.start(self.bind, self.port, self.ssl_context)
        self.port = self.server.port
        host = f"[{self.bind}]" if ":" in self.bind else self.bind
        self.url = f"{'wss' if self.ssl_context else 'ws'}://{host}:{self.port}/?token=TOKEN"
        log.info("Foxglove server up", url=self.url)
        return self.url

    def _channel(self, topic: str, cls: str) -> None:
        typename = self.reg.msg_type(cls)
        self.ch[topic] = self.server.add_channel(topic, cls, ros1_schema(self.reg.store, typename)).id

    async def _connect(self, timeout: float) -> None:
        c = self.conn = await Connection.connect(self.master_url, self.user, self.password, ROBOT_ID,
                                                 allow_reconnect=True)
        adds, links = [], []
        for i, (topic, cls) in enumerate(FLEET_TOPICS):
            tag = f"{ROBOT_ID}_in{i}"
            adds += [{"endpointTag": self.ctag, "interfaceTag": tag, "interfaceType": "SubscriberInterface",
                      "className": cls, "addr": topic},
                     {"endpointTag": ROBOT_ID, "interfaceTag": tag, "interfaceType": "PublisherForwarder",
                      "className": cls}]
            c.subscriber(tag, cls, self._on_state if topic == "/fleet/state" else self._on_tasks)
            links.append(tag)
        for i, (topic, cls) in enumerate(OPERATOR_TOPICS.items()):
            tag = f"{ROBOT_ID}_out{i}"
            adds += [{"endpointTag": self.ctag, "interfaceTag": tag, "interfaceType": "PublisherInterface",
                      "className": cls, "addr": topic},
                     {"endpointTag": ROBOT_ID, "interfaceTag": tag, "interfaceType": "SubscriberForwarder",
                      "className": cls}]
            self.pubs[topic] = c.publisher(tag, cls)
            links.append(tag)
        await c.configure({"addInterfaces": adds})
        await c.send("CX", {"connect": [{"tagA": f"{self.ctag}/{t}", "tagB": f"{ROBOT_ID}/{t}"} for t in links]})
        await c.barrier(timeout)
        await c.wait_interfaces_up(links, timeout)
        self._tags = links

    async def close(self) -> None:
        """Stop serving, remove the server's interfaces from the fleet container and log out."""
        await self.server.stop()
        await self._closing.cancel_all()
        if self.conn is not None and not self.conn.closed:
            try:
                await self.conn.configure({"removeInterfaces": [{"endpointTag": self.ctag, "interfaceTag": t}
                                                                for t in getattr(self, "_tags", [])]})
                await self.conn.barrier(CLOSE_TIMEOUT_S)
            except RCEError:
                pass
            await self.conn.close()

    # -- the fleet's messages --------------------------------------------------------------------------
    def _on_state(self, raw: bytes) -> None:
        now = time.time_ns()
        self.server.publish(self.ch["/fleet/state"], raw, now)
        try:
            st = self._state = self.reg.bytes_to_json("fleet/msg/FleetState", raw)
        except MessageError as e:
            log.warning("a fleet state that does not decode", reason=e.message)
            return
        stamp = st["header"]["stamp"]
        t = stamp["secs"] + stamp["nsecs"] * 1e-9
        for r in st["robots"]:
            pose, path = self.ch.get(f"/{r['robot']}/pose"), self.ch.get(f"/{r['robot']}/path")
            if pose is None or r["cell"] < 0:
                continue
            if self.server.subscribed(pose):
                self.server.publish(pose, self.scene.robot_pose(r, t), now)
            if self.server.subscribed(path):
                self.server.publish(path, self.scene.robot_path(r, t), now)
        self._markers(t, now)

    def _on_tasks(self, raw: bytes) -> None:
        now = time.time_ns()
        self.server.publish(self.ch["/fleet/tasks"], raw, now)
        try:
            self._tasks = self.reg.bytes_to_json("fleet/msg/TaskList", raw)
        except MessageError as e:
            log.warning("a task list that does not decode", reason=e.message)

    def _markers(self, t: float, now: int) -> None:
        cid = self.ch["/fleet/task_markers"]
        if self.server.subscribed(cid):
            self.server.publish(cid, self.scene.task_markers(self._state, self._tasks, t), now)

    # -- clients ---------------------------------------------------------------------------------------
    async def _login(self, query: dict[str, str]):
        """A client's login: ``token``, a bearer token of the page's (a viewer's at least). Returns its
        :class:`~rce_fleet.operations.api_auth.Identity`; raises AuthError (401) or RequestError (403)."""
        if self.auth is None:
            return Identity("replay", "viewer", "none")
        if "password" in query and "token" not in query:
            raise AuthError("this port takes no password: log in at the page's POST /api/login and open "
                            "?token=TOKEN")
        return self.auth.bearer(query.get("token", ""), "viewer")

    async def _metrics(self, query: dict[str, str], headers) -> None:
        """Who may read ``/metrics``: anyone with ``--metrics-public``, else a viewer's token."""
        if self.auth is None or self.auth.metrics_public:
            return
        scheme, _, value = headers.get("Authorization", "").partition(" ")
        self.auth.bearer(value.strip() if scheme.lower() == "bearer" else query.get("token", ""), "viewer")

    async def _publish(self, client, ch: ClientChannel, payload: bytes) -> None:
        who = client.principal
        if not allows(who.role, "operator"):
            raise RequestError(f"user {who.user!r} is {who.role}: publishing needs operator or above")
        if (m := GOAL_POSE.match(ch.topic)) and m.group(1) in self.robots:
            payload = self._goal_of_pose(m.group(1), ch, payload)
            ch = ClientChannel(ch.id, "/fleet/goal", "ros1", "fleet/RobotGoal")
        cls = OPERATOR_TOPICS.get(ch.topic)
        if cls is None:
            raise RequestError(f"not a topic this fleet takes; publish on one of {', '.join(OPERATOR_TOPICS)} or "
                               f"/RobotN/goal_pose")
        if ch.schema_name not in (cls, self.reg.msg_type(cls)):
            raise MessageError(f"the fleet takes {cls} here, not {ch.schema_name}")
        typename = self.reg.msg_type(cls)
        if ch.encoding == JSON:
            try:
                msg = orjson.loads(payload)
            except orjson.JSONDecodeError as e:
                raise MessageError(f"not JSON: {e}") from None
            if ch.topic in STAMPED and isinstance(msg, dict):
                msg["source"] = f"foxglove:{who.user}"
            payload = self.reg.json_to_bytes(typename, msg)
        else:
            self.reg.check_structure(typename, payload)
            if ch.topic in STAMPED:
                msg = self.reg.bytes_to_json(typename, payload)
                msg["source"] = f"foxglove:{who.user}"
                payload = self.reg.json_to_bytes(typename, msg)
        await self.pubs[ch.topic].publish(payload)
        log.info("Foxglove client published", topic=ch.topic, user=who.user, bytes=len(payload))


    def _goal_of_pose(self, robot: str, ch: ClientChannel, payload: bytes) -> bytes:
        """The ``fleet/RobotGoal`` (ROS 1 bytes) of a ``geometry_msgs/PoseStamped`` on ``/RobotN/goal_pose``: the cell
        of its position. Raises MessageError for another class, a pose that does not decode or is off the grid."""
        if ch.schema_name not in (_wire(POSE), POSE):
            raise MessageError(f"the fleet takes {_wire(POSE)} here, not {ch.schema_name}")
        try:
            pose = orjson.loads(payload) if ch.encoding == JSON else self.reg.bytes_to_json(POSE, payload)
            x, y = float(pose["pose"]["position"]["x"]), float(pose["pose"]["position"]["y"])
        except (orjson.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            raise MessageError(f"not a {_wire(POSE)}: {e}") from None
        cell = self.scene.geo.cell_of(x, y)
        if cell is None:
            raise MessageError(f"({x:.2f}, {y:.2f}) is outside the grid")
        return self.reg.json_to_bytes("fleet/msg/RobotGoal", {"robot": robot, "cell": cell})


def _wire(typename: str) -> str:
    """``pkg/msg/Name`` -> ``pkg/Name``."""
    return typename.replace("/msg/", "/")

