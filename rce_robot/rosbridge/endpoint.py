"""The rosbridge v2 endpoint of a robot task set (``rce-robot --rosbridge-port``, 9090 by
default; docs/design.md, section 2.1): a websocket server that speaks RobotWebTools' rosbridge protocol,
so that unmodified roslibpy and roslibjs reach a container's graph.

A client connects to ``ws://HOST:PORT/?userID=U&robotID=R&password=SHA256HEX&container=CTAG``.
Before the websocket opens the master checks the password (``auth``, as for an RCE robot), that
user ``U`` has container ``CTAG`` (``container_bus``) and takes ``R`` as a connected robot
(``robot_connected``); refusals are HTTP 400/401/404/409/503 with a one-line reason. An optional
``&maxLag=S`` sets the client's own lag bound (s; 0: its publish ops are never shed), as for an
RCE robot (docs/INTERNALS.md "A peer that does not keep up"). Each client
is then one :class:`~rce_robot.rosbridge.session.RosbridgeSession`, a robot namespace whose
interfaces the master creates and removes on the session's behalf.
"""
from __future__ import annotations

import ssl
import time
from collections import Counter
from http import HTTPStatus
from typing import Any
from urllib.parse import parse_qs, urlsplit

from websockets.exceptions import ConnectionClosed

from rce.contract import master as to_master
from rce.plumbing.errors import AuthError, NotFound, RCEError, Throttled, Unavailable
from rce.plumbing.log import get_logger
from rce.transport.masterlink import MasterLink
from rce.protocol.limits import DEFAULT_MAX_LAG, parse_max_lag
from rce.plumbing.tasks import Tasks
from rce_robot.front_door import master_away, peer_address, throttled
from rce_robot import ws_link
from rce_robot.interfaces import RobotInterface
from rce_robot.rosbridge.outbox import RosbridgeOutbox
from rce_robot.rosbridge.session import RosbridgeSession

log = get_logger("rce.rosbridge")

ROSBRIDGE_PORT = 9090       # rosbridge_suite's default port (docs/design.md, section 2.1)
PING_INTERVAL = 20.0        # s between websocket pings to a client
PING_TIMEOUT = 60.0         # s a client may leave a ping unanswered before its link counts as lost
WS_MAX_QUEUE = 64           # messages the websocket reads ahead of the session
MAX_MESSAGE = 16 * 1024 * 1024   # bytes of the largest websocket message taken from a client
QUERY = ("userID", "robotID", "password", "container")
# RosbridgeSession.stats() key -> (Prometheus counter, help), summed over the sessions, live and ended
SESSION_COUNTERS = {"ops_in": ("rce_robot_rosbridge_ops_in", "Ops taken from rosbridge clients"),
                    "errors": ("rce_robot_rosbridge_status_errors", "status errors sent to rosbridge clients"),
                    "msgs_out": ("rce_robot_rosbridge_messages_out", "Messages queued for rosbridge clients"),
                    "dropped": ("rce_robot_rosbridge_dropped",
                                "Messages to rosbridge clients dropped (outbox or throttle queue full)"),
                    "fragments_out": ("rce_robot_rosbridge_fragments_out", "fragment ops sent to rosbridge clients"),
                    "fragments_in": ("rce_robot_rosbridge_fragments_in", "fragment ops taken from rosbridge clients"),
                    "fragments_dropped": ("rce_robot_rosbridge_fragments_dropped",
                                          "Client fragments dropped (bounds, expiry, inconsistent)"),
                    "shed": ("rce_robot_rosbridge_shed", "publish ops of rosbridge clients dropped while the endpoint "
                                                         "lagged behind them (max_lag)")}


class RosbridgeServer:
    """The rosbridge websocket server on ``master`` (the task set's control link); ``by_iid``: the
    endpoint's table of robot-side interfaces (a session's are forgotten there when it ends).
    :attr:`sessions` maps (user, robot) to the live sessions: the master's ``add_interface``
    for such a robot makes its converter in that session. ``max_lag``: s the endpoint may stay
    behind a client before it sheds the client's publish ops (:class:`RosbridgeSession`); ``ws_impl``: the
    websocket library that serves it (:data:`rce_robot.ws_link.IMPLS`)."""

    def __init__(self, master: MasterLink, by_iid: dict[int, RobotInterface], max_lag: float | None = DEFAULT_MAX_LAG,
                 ws_impl: str = ws_link.DEFAULT_IMPL):
        self.master, self.by_iid, self.max_lag, self.ws_impl = master, by_iid, max_lag, ws_impl
        self.sessions: dict[tuple[str, str], RosbridgeSession] = {}
        self.ended: Counter[str] = Counter()          # the counters of ended sessions
        self.sessions_total = 0
        self.port = 0
        self._server: Any = None

    def stats(self) -> dict[str, int]:
        """:data:`SESSION_COUNTERS` summed over live and ended sessions, plus ``sessions`` (live)
        and ``sessions_total`` (accepted since start)."""
        total = Counter(self.ended)
        for session in self.sessions.values():
            total.update(session.stats())
        return {**{k: total[k] for k in SESSION_COUNTERS}, "sessions": len(self.sessions),
                "sessions_total": self.sessions_total}

    async def start(self, bind: str, port: int, ssl_context: ssl.SSLContext | None = None) -> None:
        """Listen on ``bind``:``port`` (0: an ephemeral port, then in :attr:`port`); wss:// with
        ``ssl_context`` (:func:`rce.transport.tls.server_context`)."""
        self._server = await ws_link.serve(self.ws_impl, self._serve, bind, port, process_request=self._handshake,
                                           max_size=MAX_MESSAGE, ping_interval=PING_INTERVAL,
                                           ping_timeout=PING_TIMEOUT, max_queue=WS_MAX_QUEUE,
                                           ssl_context=ssl_context)
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("rosbridge endpoint up", port=self.port)

    async def stop(self) -> None:
        """Close the server; each session ends (its interfaces removed, its robot disconnected)."""
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    async def _handshake(self, connection, request):
        """Authenticate the query (module docstring) before the websocket opens. A refusal is
        logged with its status and reason: roslibpy and roslibjs do not show them to their user."""
        q = {k: v[0] for k, v in parse_qs(urlsplit(request.path).query).items()}

        def refuse(status: int, reason: str, resp=None):
            log.info("rosbridge client refused", status=int(status), reason=reason, user=q.get("userID"),
                     robot=q.get("robotID"), container=q.get("container"), peer=peer_address(connection))
            return resp if resp is not None else connection.respond(status, reason + "\n")

        missing = [k for k in QUERY if not q.get(k)]
        if missing:
            return refuse(HTTPStatus.BAD_REQUEST, f"missing query parameter(s): {', '.join(missing)}")
        password = q["password"].lower()
        if len(password) != 64 or any(c not in "0123456789abcdef" for c in password):
            return refuse(HTTPStatus.BAD_REQUEST, "password must be the hex SHA-256 digest (64 digits)")
        try:
            max_lag = self.max_lag if "maxLag" not in q else parse_max_lag(q["maxLag"])
        except ValueError as e:
            return refuse(HTTPStatus.BAD_REQUEST, str(e))
        if (away := master_away(connection, self.master)) is not None:
            return refuse(HTTPStatus.SERVICE_UNAVAILABLE, "the master is unavailable", away)
        user, robot, ctag = q["userID"], q["robotID"], q["container"]
        steps = ((HTTPStatus.UNAUTHORIZED, to_master.Auth(user=user, robot=robot, password=password,
                                                          addr=peer_address(connection))),
                 (HTTPStatus.NOT_FOUND, to_master.ContainerBus(user=user, ctag=ctag)),
                 (HTTPStatus.CONFLICT, to_master.RobotConnected(user=user, robot=robot)))
        for status, msg in steps:
            try:
                await self.master.ask(msg)
            except (AuthError, NotFound) as e:
                return refuse(status, e.message)
            except Throttled as e:
                return refuse(HTTPStatus.TOO_MANY_REQUESTS, e.message, throttled(connection, e))
            except RCEError as e:
                return refuse(status if msg.OP == "robot_connected" else HTTPStatus.SERVICE_UNAVAILABLE, e.message)
        connection.rce_rosbridge, connection.rce_max_lag = (user, robot, ctag), max_lag
        return None

    async def _serve(self, ws) -> None:
        user, robot, ctag = ws.rce_rosbridge
        session = RosbridgeSession(user, robot, ctag, self.master, ws.rce_max_lag)
        session.ws = ws
        self.sessions[(user, robot)] = session
        self.sessions_total += 1
        log.info("rosbridge client connected", user=user, robot=robot, container=ctag, peer=str(ws.remote_address))
        writer = Tasks(f"rosbridge writer {user}/{robot}")
        writer.spawn(_write(ws, session.outbox), name="writer")
        try:
            async for text in ws:
                session.backlog(ws_link.behind(ws), time.monotonic())
                await session.handle(text)
                await ws_link.take_turn(ws)
        except ConnectionClosed:
            pass
        finally:
            await writer.cancel_all()
            await self._end(session)

    async def _end(self, session: RosbridgeSession) -> None:
        """A client left: remove its interfaces, forget them here, tell the master the robot is gone."""
        await session.close()
        if self.sessions.get((session.user, session.robot)) is session:
            del self.sessions[(session.user, session.robot)]
        self.ended.update(session.stats())
        for iid in [i for i, itf in self.by_iid.items() if session.owns(itf)]:
            await self.by_iid.pop(iid).stop()
        try:
            if not self.master.available:         # stopping, or the master is away: its registration learns it
                raise Unavailable("the master is away")
            await self.master.ask(to_master.RobotDisconnected(user=session.user, robot=session.robot))
        except RCEError as e:
            log.warning("could not report a rosbridge disconnect", robot=session.robot, reason=e.message)
        log.info("rosbridge client disconnected", user=session.user, robot=session.robot, **session.stats())


async def _write(ws, outbox: RosbridgeOutbox) -> None:
    """Send what the session queued, in order, until the link closes."""
    try:
        while True:
            for frame in await outbox.get():        # one message: its frames (text, or binary CBOR)
                await ws.send(frame)
    except ConnectionClosed:
        pass
