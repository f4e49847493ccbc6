"""The robot task set: the websocket server robots connect to (DESIGN section 3), one
:class:`~rce_robot.namespace.RobotNamespace` per robot, the robot-side interfaces and
this process's data-plane endpoint."""
from __future__ import annotations

import asyncio
import hashlib
from collections import Counter
from http import HTTPStatus
from urllib.parse import parse_qs, urlsplit

from aiohttp import web
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Gauge, generate_latest
from prometheus_client.core import CounterMetricFamily
from websockets.asyncio.server import serve

from rce import rpc
from rce.dataplane import DataPlane
from rce.errors import AuthError, NotFound, RCEError
from rce.log import get_logger
from rce.messages import default_registry
from rce.package_path import load_package_types
from rce.protocol.frames import DEFAULT_EXPIRY
from rce.protocol.session import DEFAULT_MAX_MESSAGE, DEFAULT_QUEUE_SIZE, RobotSession, robot_interface_type
from rce_robot.interfaces import RobotInterface
from rce_robot.namespace import RobotNamespace

log = get_logger("rce.robot")
# s of master silence before this task set gives up on it. Longer than the master's own 4 s
# verdict on task sets: a busy master is not a lost one, and giving up tears containers down.
MASTER_SILENCE = 15.0
PING_INTERVAL = 20.0     # s between websocket pings to a robot
PING_TIMEOUT = 60.0      # s a robot may leave a ping unanswered before its link counts as lost (slow links)
WS_MAX_QUEUE = 64        # frames the websocket reads ahead of the session


def normalise_password(p: str) -> str:
    """The hex SHA-256 digest from the ``password`` query value. The RCE alpha client sent the raw
    32-byte digest (URL-encoded); DESIGN section 3.2 sends its hex form. Both are accepted."""
    if len(p) == 64 and all(c in "0123456789abcdefABCDEF" for c in p):
        return p.lower()
    raw = p.encode("latin-1", errors="replace")
    return raw.hex() if len(raw) == 32 else hashlib.sha256(b"\0invalid").hexdigest()


# RobotSession counter -> (Prometheus counter, help), summed over the sessions, live and ended
SESSION_COUNTERS = {"msgs_in": ("rce_robot_messages_in", "Messages from robots"),
                    "msgs_out": ("rce_robot_messages_out", "Messages to robots"),
                    "dropped": ("rce_robot_dropped", "Messages to robots dropped (queue full)"),
                    "dropped_in": ("rce_robot_dropped_in", "Messages from robots refused (queue full)"),
                    "errors": ("rce_robot_errors", "ER messages sent to robots")}


class Metrics:
    """The endpoint's Prometheus metrics: session counters (those of ended sessions are kept in
    ``ended``), connections, interfaces, the data plane, the outgoing queue depth."""

    def __init__(self, ep: "RobotEndpoint"):
        self.ep = ep
        self.ended: Counter[str] = Counter()
        self.registry = r = CollectorRegistry()
        r.register(self)
        Gauge("rce_robot_connections", "Connected robots", registry=r).set_function(lambda: len(ep.namespaces))
        Gauge("rce_robot_interfaces", "Robot-side interfaces", registry=r).set_function(
            lambda: sum(len(n.interfaces) for n in ep.namespaces.values()))
        for k in ("msgs_in", "msgs_out", "bytes_in", "bytes_out", "dropped"):
            Gauge(f"rce_robot_dataplane_{k}", f"Data plane {k}", registry=r).set_function(
                lambda k=k: getattr(ep.plane, k))
        Gauge("rce_robot_queue_depth", "Data messages waiting to go to robots", registry=r).set_function(
            lambda: sum(n.session.out_data for n in ep.namespaces.values()))

    def session_ended(self, session: RobotSession) -> None:
        stats = session.stats()
        self.ended.update({k: stats[k] for k in SESSION_COUNTERS})

    def collect(self):
        """(prometheus_client collector) The session counters."""
        live = [n.session.stats() for n in self.ep.namespaces.values()]
        for key, (name, doc) in SESSION_COUNTERS.items():
            yield CounterMetricFamily(name, doc, value=self.ended[key] + sum(s[key] for s in live))


class RobotEndpoint:
    """One robot task set. ``max_message``: largest websocket frame taken (bytes; larger ones get
    an ER); ``queue_size``: bound of each of a robot's queues (:class:`RobotSession`); ``expiry``: s for
    binary parts."""

    def __init__(self, *, name: str, advertise_host: str, max_message: int = DEFAULT_MAX_MESSAGE,
                 queue_size: int = DEFAULT_QUEUE_SIZE, expiry: float = DEFAULT_EXPIRY):
        self.name, self.advertise_host = name, advertise_host
        self.max_message, self.queue_size, self.expiry = max_message, queue_size, expiry
        self.registry = default_registry()
        load_package_types(self.registry)
        self.plane = DataPlane(f"robot:{name}")
        self.namespaces: dict[tuple[str, str], RobotNamespace] = {}
        self.by_iid: dict[int, RobotInterface] = {}
        self.master: rpc.RpcPeer | None = None
        self.metrics = Metrics(self)
        self.ws_port = 0
        self.metrics_port = 0
        self._ws_server = None
        self._http: web.AppRunner | None = None
        self.stopped = asyncio.Event()

    async def start(self, master_host: str, master_port: int, bind: str, port: int, data_port: int,
                    metrics_port: int | None = None) -> None:
        await self.plane.listen(bind, data_port, self.advertise_host)
        # frames up to twice the limit are read and refused with an ER; beyond that the socket closes
        self._ws_server = await serve(self._session, bind, port, process_request=self._handshake,
                                      max_size=2 * self.max_message + 1024, compression=None,
                                      ping_interval=PING_INTERVAL, ping_timeout=PING_TIMEOUT,
                                      max_queue=WS_MAX_QUEUE)
        self.ws_port = self._ws_server.sockets[0].getsockname()[1]
        host = f"[{self.advertise_host}]" if ":" in self.advertise_host else self.advertise_host
        handlers = {op: getattr(self, "_op_" + op) for op in
                    ("add_interface", "remove_interface", "connect", "disconnect", "notify", "close_robot")}
        self.master = await rpc.connect(master_host, master_port, handlers, name="master",
                                        on_close=lambda _p: self.stopped.set())
        self.master.keepalive(timeout=MASTER_SILENCE)
        await self.master.call("register", kind="robot", name=self.name, host=self.advertise_host,
                               ws_url=f"ws://{host}:{self.ws_port}/", data_addr=self.plane.addr)
        if metrics_port is not None:
            app = web.Application()
            app.router.add_get("/metrics", self._metrics)
            self._http = web.AppRunner(app, access_log=None)
            await self._http.setup()
            site = web.TCPSite(self._http, bind, metrics_port)
            await site.start()
            self.metrics_port = site._server.sockets[0].getsockname()[1]
        log.info("robot endpoint up", ws_port=self.ws_port, data_addr=self.plane.addr)

    async def stop(self) -> None:
        if self._ws_server:
            self._ws_server.close()
            await self._ws_server.wait_closed()
        if self.master:
            await self.master.close()
        await self.plane.close()
        if self._http:
            await self._http.cleanup()

    async def _metrics(self, request: web.Request) -> web.Response:
        return web.Response(body=generate_latest(self.metrics.registry), headers={"Content-Type": CONTENT_TYPE_LATEST})

    # -- websocket -------------------------------------------------------------------------------
    async def _handshake(self, connection, request):
        """Authenticate ``?userID=U&robotID=R&password=P`` before the websocket opens."""
        q = {k: v[0] for k, v in parse_qs(urlsplit(request.path).query, encoding="latin-1").items()}
        missing = [k for k in ("userID", "robotID", "password") if not q.get(k)]
        if missing:
            return connection.respond(HTTPStatus.BAD_REQUEST, f"missing query parameter(s): {', '.join(missing)}\n")
        user, robot = q["userID"], q["robotID"]
        try:
            await self.master.call("auth", user=user, robot=robot, password=normalise_password(q["password"]))
        except AuthError as e:
            return connection.respond(HTTPStatus.UNAUTHORIZED, e.message + "\n")
        except RCEError as e:
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, e.message + "\n")
        try:
            await self.master.call("robot_connected", user=user, robot=robot)
        except RCEError as e:
            return connection.respond(HTTPStatus.CONFLICT, e.message + "\n")
        connection.rce_identity = (user, robot)
        return None

    async def _session(self, ws) -> None:
        user, robot = ws.rce_identity
        session = RobotSession(robot, max_message=self.max_message, queue_size=self.queue_size, expiry=self.expiry)
        ns = RobotNamespace(ws, user, robot, self.master, session)
        self.namespaces[(user, robot)] = ns
        log.info("robot connected", user=user, robot=robot, peer=str(ws.remote_address))
        try:
            await ns.run()
        finally:
            self.namespaces.pop((user, robot), None)
            self.metrics.session_ended(session)
            for iid in [i for i, itf in self.by_iid.items() if itf.link is ns]:
                del self.by_iid[iid]
            try:
                await self.master.call("robot_disconnected", user=user, robot=robot)
            except RCEError as e:
                log.warning("could not report disconnect", robot=robot, reason=str(e))
            log.info("robot disconnected", user=user, robot=robot)

    # -- master ops --------------------------------------------------------------------------------
    def _ns(self, a: dict) -> RobotNamespace:
        ns = self.namespaces.get((a["user"], a["robot"]))
        if ns is None:
            raise NotFound(f"robot {a['robot']!r} is not connected to this endpoint")
        return ns

    def _iface(self, iid: int) -> RobotInterface:
        iface = self.by_iid.get(iid)
        if iface is None:
            raise NotFound(f"no robot-side interface with id {iid}")
        return iface

    async def _op_add_interface(self, a: dict) -> dict:
        ns = self._ns(a)
        kind, side = robot_interface_type(a["itype"])
        iface = RobotInterface(ns, self.plane, self.registry, a["iid"], a["itag"], kind, side, a["cls"])
        await iface.start()
        ns.add_interface(iface)
        self.by_iid[iface.iid] = iface
        return {}

    async def _op_remove_interface(self, a: dict) -> dict:
        iface = self.by_iid.pop(a["iid"], None)
        if iface:
            iface.link.remove_interface(iface)
            await iface.stop()
            iface.on_peers_changed()
        return {}

    async def _op_connect(self, a: dict) -> dict:
        self._iface(a["iid"]).connect(a["peer_iid"], a["peer_addr"])
        return {}

    async def _op_disconnect(self, a: dict) -> dict:
        iface = self.by_iid.get(a["iid"])
        if iface:
            iface.disconnect(a["peer_iid"])
        return {}

    async def _op_notify(self, a: dict) -> None:
        ns = self.namespaces.get((a["user"], a["robot"]))
        if ns is None:
            return
        if a["type"] == "ER":
            ns.send_error(str(a["data"]))
        else:
            ns.send_status(a["data"])

    async def _op_close_robot(self, a: dict) -> dict:
        await self._ns(a).close(a.get("reason", "closed by the master"))
        return {}
