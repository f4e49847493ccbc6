"""A Foxglove WebSocket server (:mod:`rce.foxglove.protocol`) on the ``websockets`` library's asyncio server,
in the process's event loop: the shell around :class:`~rce.foxglove.protocol.ClientState`.

Why not ``foxglove-sdk``: its server runs on its own Rust (tokio) runtime and threads, outside the
process's asyncio loop, and takes every connection that speaks the subprotocol: it has no hook where the
handshake could be refused before the websocket opens, so rce's login (the same as the operator page's
and every robot's) could not guard it, and its queues are not rce's outbox policy with drops counted.
The protocol is small (a dozen JSON ops, two binary layouts); this shell is about 300 lines.

What it does:

- The login: ``authenticate(query)`` (the handshake's query parameters, a dict of str) is awaited before
  the websocket opens; it returns who the client is (kept as :attr:`FoxgloveClient.principal`) or raises
  :class:`~rce.plumbing.errors.AuthError` (HTTP 401), :class:`~rce.plumbing.errors.NotFound` (404) or another
  :class:`~rce.plumbing.errors.RCEError` (403), with a one-line reason in the body.
- ``GET /metrics`` (no upgrade) answers the server's counters as Prometheus text; given ``authorize_metrics(query,
  headers)``, only once that returned (its :class:`~rce.plumbing.errors.RCEError` refuses it as the login's does).
- A client that does not offer ``foxglove.websocket.v1`` is accepted without a subprotocol, sent a
  ``status`` error naming the subprotocol and closed with 1002 (protocol error).
- Channels (:meth:`FoxgloveServer.add_channel`) are advertised to every client; a ``latched`` channel keeps
  its newest message and sends it to each new subscriber (a map, chargers). :meth:`FoxgloveServer.publish`
  queues a message for each client subscribed to its channel.
- Each client has one :class:`~rce.protocol.outbox.Outbox` (rce's one policy: per channel the newest is
  kept; past ``queue_size`` messages the busiest channel's oldest is dropped, counted), a writer task, and
  a bound on its control messages (statuses past :data:`CONTROL_MAX` waiting are dropped, counted).
- With ``per_client``, each client has channels and services of its own (what one user's container has), made by
  ``on_connect(client)`` with :meth:`FoxgloveClient.add_channel` and :meth:`FoxgloveClient.add_service` and fed with
  :meth:`FoxgloveClient.publish`; ``on_subscribe(client, channel)`` and ``on_unsubscribe`` say when a client starts
  and stops wanting a channel, ``on_disconnect(client)`` when it is gone.
- Client publishing and service calls go to ``on_publish(client, channel, payload)`` and
  ``on_service_call(client, service, encoding, payload) -> (encoding, payload)``; an
  :class:`~rce.plumbing.errors.RCEError` from either is a ``status`` error (a failed call: a
  ``serviceCallFailure``) to that client alone.
- A client's messages are taken in turn with everyone else's (the loop gets a turn after each), so a
  flood of ops costs its sender only; a message over :data:`MAX_FRAME` bytes closes the link with 1009,
  one over the protocol's limits (:data:`rce.foxglove.protocol.MAX_CLIENT_PAYLOAD`) is answered with a
  ``status`` error and dropped.
"""
from __future__ import annotations

import asyncio
import itertools
import ssl
import time
from collections.abc import Awaitable, Callable
from http import HTTPStatus
from typing import Any
from urllib.parse import parse_qs, urlsplit

from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Response

from rce.plumbing.errors import AuthError, NotFound, RCEError
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce.protocol.outbox import Outbox

from . import protocol as fp
from .protocol import Channel, ClientChannel, ClientState, FoxgloveService

log = get_logger("rce.foxglove")

QUEUE_SIZE = 256          # messages waiting for one client's websocket before the busiest channel's oldest drops
CONTROL_MAX = 1024        # control messages (statuses) waiting for one client before further statuses drop
MAX_FRAME = 16 << 20      # bytes of one websocket message from a client (larger: close 1009)
MAX_CLIENTS = 64          # clients at once (more: HTTP 503)
PING_INTERVAL = 20.0      # s between websocket pings
PING_TIMEOUT = 60.0       # s a ping may wait for its pong
READ_AHEAD = 16           # client messages read ahead of the handler
CLOSE_PROTOCOL = 1002     # close code: protocol error (RFC 6455)

Authenticate = Callable[[dict[str, str]], Awaitable[Any]]
AuthorizeMetrics = Callable[[dict[str, str], Headers], Awaitable[None]]
OnPublish = Callable[["FoxgloveClient", ClientChannel, bytes], Awaitable[None]]
OnServiceCall = Callable[["FoxgloveClient", FoxgloveService, str, bytes], Awaitable[tuple[str, bytes]]]
OnClient = Callable[["FoxgloveClient"], Awaitable[None]]
OnChannel = Callable[["FoxgloveClient", Channel], Awaitable[None]]
COUNTERS = {"messages_out": "Messages queued for Foxglove clients",
            "dropped": "Messages to Foxglove clients dropped (a client's queue full)",
            "status_errors": "status errors sent to Foxglove clients (bad input, refused publishes)",
            "status_dropped": "status messages to Foxglove clients dropped (a client's control queue full)",
            "published_in": "Messages Foxglove clients published",
            "service_calls": "Service calls from Foxglove clients",
            "clients_total": "Foxglove clients accepted"}


class FoxgloveClient:
    """One connected client: its websocket, :attr:`state` (subscriptions, client channels), :attr:`principal`
    (what ``authenticate`` returned), its outbox and counters (:attr:`dropped`, :attr:`status_dropped`)."""

    def __init__(self, server: "FoxgloveServer", ws: ServerConnection, principal: Any, queue_size: int):
        self.server, self.ws, self.principal = server, ws, principal
        self.channels: dict[int, Channel] = {} if server.per_client else server.channels
        self.services: dict[int, FoxgloveService] = {} if server.per_client else server.services
        self.state = ClientState(self.channels, self.services, client_publish=server.on_publish is not None,
                                 encodings=server.client_encodings)
        self.by_topic: dict[str, Channel] = {}
        self.session: Any = None          # what ``on_connect`` keeps for this client
        self.outbox: Outbox[str | bytes] = Outbox(queue_size)
        self.status_dropped = 0
        self._ready = asyncio.Event()

    @property
    def dropped(self) -> int:
        """Messages dropped for this client: its queue was full."""
        return self.outbox.dropped

    def add_channel(self, topic: str, schema_name: str, schema: str, *, encoding: str = fp.ROS1,
                    schema_encoding: str = fp.ROS1MSG) -> Channel:
        """A channel of this client alone (``per_client`` servers), advertised to it; returns it."""
        ch = Channel(next(self.server._ids), topic, schema_name, schema, encoding, schema_encoding)
        self.channels[ch.id] = self.by_topic[topic] = ch
        self.send_control(fp.advertise([ch]))
        return ch

    def add_service(self, name: str, type_: str, request_schema: str, response_schema: str) -> FoxgloveService:
        """A service of this client alone (``per_client`` servers), advertised to it; returns it."""
        s = FoxgloveService(next(self.server._service_ids), name, type_, request_schema, response_schema)
        self.services[s.id] = s
        self.send_control(fp.advertise_services([s]))
        return s

    def publish(self, channel_id: int, payload: bytes, stamp_ns: int | None = None) -> bool:
        """Queue ``payload`` on this client's ``channel_id`` if it is subscribed to it; returns whether it was."""
        sid = self.state.by_channel.get(channel_id)
        if sid is None:
            return False
        self.send_data(channel_id, fp.message_data(sid, time.time_ns() if stamp_ns is None else stamp_ns, payload))
        self.server.counts["messages_out"] += 1
        return True

    def send_control(self, frame: str | bytes, *, droppable: bool = False) -> bool:
        """Queue a control message (advertise, status, a service response); ``droppable`` ones (statuses)
        are dropped, counted, while :data:`CONTROL_MAX` wait. Returns whether it was queued."""
        if droppable and self.outbox.control >= CONTROL_MAX:
            self.status_dropped += 1
            return False
        self.outbox.put(frame)
        self._ready.set()
        return True

    def status(self, level: int, message: str) -> None:
        """Send this client a ``status`` message."""
        if level == fp.ERROR:
            self.server.counts["status_errors"] += 1
        if not self.send_control(fp.status(level, message), droppable=True):
            self.server.counts["status_dropped"] += 1

    def send_data(self, channel_id: int, frame: bytes) -> None:
        """Queue a ``MESSAGE_DATA`` frame of ``channel_id`` (kept newest-per-channel; drops counted)."""
        before = self.outbox.dropped
        self.outbox.put_data(channel_id, frame, time.monotonic())
        self.server.counts["dropped"] += self.outbox.dropped - before
        self._ready.set()

    async def write(self) -> None:
        """Send what is queued, in order, until the link closes."""
        try:
            while True:
                frame = self.outbox.take()
                if frame is None:
                    self._ready.clear()
                    await self._ready.wait()
                    continue
                await self.ws.send(frame)
        except ConnectionClosed:
            pass


class FoxgloveServer:
    """A Foxglove WebSocket server named ``name`` (module docstring). ``authenticate``: the login (None:
    every client is let in, for tests of the protocol alone); ``on_publish`` (None: no ``clientPublish``);
    ``on_service_call`` (None: no ``services``); ``queue_size``: messages per client (:data:`QUEUE_SIZE`);
    ``metric_prefix``: the names of ``/metrics``' counters (``PREFIX_dropped`` ...); ``authorize_metrics``: who may
    read them (None: anyone); ``per_client``,
    ``on_connect``, ``on_disconnect``, ``on_subscribe``, ``on_unsubscribe``: channels of each client's own (module
    docstring); ``client_encodings``: what clients may publish and call services in (``supportedEncodings``)."""

    def __init__(self, name: str, *, authenticate: Authenticate | None = None, on_publish: OnPublish | None = None,
                 on_service_call: OnServiceCall | None = None, queue_size: int = QUEUE_SIZE,
                 max_clients: int = MAX_CLIENTS, metric_prefix: str = "rce_foxglove", per_client: bool = False,
                 on_connect: OnClient | None = None, on_disconnect: OnClient | None = None,
                 on_subscribe: OnChannel | None = None, on_unsubscribe: OnChannel | None = None,
                 authorize_metrics: AuthorizeMetrics | None = None,
                 client_encodings: tuple[str, ...] = fp.CLIENT_ENCODINGS):
        self.name, self.authenticate, self.authorize_metrics = name, authenticate, authorize_metrics
        self.on_publish, self.on_service_call = on_publish, on_service_call
        self.per_client, self.on_connect, self.on_disconnect = per_client, on_connect, on_disconnect
        self.on_subscribe, self.on_unsubscribe = on_subscribe, on_unsubscribe
        self.queue_size, self.max_clients, self.metric_prefix = queue_size, max_clients, metric_prefix
        self.client_encodings = client_encodings          # what clients may publish and call in (supportedEncodings)
        self.channels: dict[int, Channel] = {}
        self.services: dict[int, FoxgloveService] = {}
        self.by_topic: dict[str, Channel] = {}
        self.latched: dict[int, tuple[int, bytes]] = {}       # channel id -> (stamp ns, payload) of latched ones
        self._latching: set[int] = set()
        self.clients: set[FoxgloveClient] = set()
        self.counts = dict.fromkeys(COUNTERS, 0)
        self.port = 0
        self._ids = itertools.count(1)
        self._service_ids = itertools.count(1)
        self._server: Any = None

    # -- channels and services ----------------------------------------------------------------------------
    def add_channel(self, topic: str, schema_name: str, schema: str, *, encoding: str = fp.ROS1,
                    schema_encoding: str = fp.ROS1MSG, latched: bool = False) -> Channel:
        """Advertise ``topic`` (``schema_name`` ``pkg/Name`` defined by ``schema``) to every client; returns
        the channel. Raises ValueError when ``topic`` has a channel already."""
        if topic in self.by_topic:
            raise ValueError(f"topic {topic} has a channel already ({self.by_topic[topic].id})")
        ch = Channel(next(self._ids), topic, schema_name, schema, encoding, schema_encoding)
        self.channels[ch.id] = self.by_topic[topic] = ch
        if latched:
            self._latching.add(ch.id)
        frame = fp.advertise([ch])
        for c in self.clients:
            c.send_control(frame)
        return ch

    def remove_channel(self, channel_id: int) -> None:
        """Withdraw a channel (``unadvertise``); its subscriptions end. Unknown ids are ignored."""
        ch = self.channels.pop(channel_id, None)
        if ch is None:
            return
        self.by_topic.pop(ch.topic, None)
        self.latched.pop(channel_id, None)
        self._latching.discard(channel_id)
        frame = fp.unadvertise([channel_id])
        for c in self.clients:
            c.state.forget_channel(channel_id)
            c.send_control(frame)

    def add_service(self, name: str, type_: str, request_schema: str, response_schema: str) -> FoxgloveService:
        """Advertise service ``name`` of ``type_`` (``pkg/Name``) to every client; returns it."""
        s = FoxgloveService(next(self._service_ids), name, type_, request_schema, response_schema)
        self.services[s.id] = s
        for c in self.clients:
            c.send_control(fp.advertise_services([s]))
        return s

    def subscribed(self, channel_id: int) -> int:
        """Clients subscribed to ``channel_id`` now (a source may skip making messages nobody takes)."""
        return sum(1 for c in self.clients if channel_id in c.state.by_channel)

    def publish(self, channel_id: int, payload: bytes, stamp_ns: int | None = None) -> int:
        """Queue ``payload`` (in the channel's encoding) on ``channel_id`` for every client subscribed to it,
        received at ``stamp_ns`` (ns since the epoch; default now). Returns the clients it went to. A latched
        channel keeps it for later subscribers. Raises KeyError for an unknown channel."""
        if channel_id not in self.channels:
            raise KeyError(f"unknown channel {channel_id}")
        stamp = time.time_ns() if stamp_ns is None else stamp_ns
        if channel_id in self._latching:
            self.latched[channel_id] = (stamp, payload)
        n = 0
        for c in self.clients:
            sid = c.state.by_channel.get(channel_id)
            if sid is not None:
                c.send_data(channel_id, fp.message_data(sid, stamp, payload))
                n += 1
        self.counts["messages_out"] += n
        return n

    # -- the server ---------------------------------------------------------------------------------------
    async def start(self, bind: str = "127.0.0.1", port: int = 0, ssl_context: ssl.SSLContext | None = None) -> int:
        """Listen on ``bind``:``port`` (0: ephemeral), wss:// with ``ssl_context``; returns the port (also
        :attr:`port`)."""
        self._server = await serve(self._serve, bind, port, process_request=self._handshake,
                                   select_subprotocol=_select, compression=None, max_size=MAX_FRAME,
                                   max_queue=READ_AHEAD, ping_interval=PING_INTERVAL, ping_timeout=PING_TIMEOUT,
                                   server_header=None, ssl=ssl_context)
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("Foxglove WebSocket server up", name=self.name, port=self.port)
        return self.port

    async def stop(self) -> None:
        """Close the server and every client."""
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    def stats(self) -> dict[str, int]:
        """:data:`COUNTERS` and ``clients`` (connected now)."""
        return {**self.counts, "clients": len(self.clients)}

    def metrics_text(self) -> str:
        """The counters as Prometheus text (``GET /metrics``)."""
        p = self.metric_prefix
        lines = []
        for key, doc in COUNTERS.items():
            lines += [f"# HELP {p}_{key} {doc}", f"# TYPE {p}_{key} counter", f"{p}_{key} {self.counts[key]}"]
        lines += [f"# HELP {p}_clients Foxglove clients connected", f"# TYPE {p}_clients gauge",
                  f"{p}_clients {len(self.clients)}"]
        return "\n".join(lines) + "\n"

    async def _handshake(self, connection: ServerConnection, request) -> Response | None:
        parts = urlsplit(request.path)
        query = {k: v[0] for k, v in parse_qs(parts.query).items()}
        if parts.path == "/metrics" and "upgrade" not in request.headers.get("Connection", "").lower():
            try:
                if self.authorize_metrics is not None:
                    await self.authorize_metrics(query, request.headers)
            except RCEError as e:
                return _refuse(connection, e, "metrics")
            return Response(200, "OK", Headers([("Content-Type", "text/plain; version=0.0.4; charset=utf-8"),
                                                ("Cache-Control", "no-store")]), self.metrics_text().encode())
        if len(self.clients) >= self.max_clients:
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, f"over {self.max_clients} Foxglove clients\n")
        if self.authenticate is None:
            connection.rce_principal = None
            return None
        try:
            connection.rce_principal = await self.authenticate(query)
            return None
        except RCEError as e:
            return _refuse(connection, e, "client", user=query.get("userID"))

    async def _serve(self, ws: ServerConnection) -> None:
        client = FoxgloveClient(self, ws, getattr(ws, "rce_principal", None), self.queue_size)
        if ws.subprotocol != fp.SUBPROTOCOL:
            await ws.send(fp.status(fp.ERROR, f"this server speaks the {fp.SUBPROTOCOL} subprotocol; the client "
                                              f"offered {ws.request.headers.get('Sec-WebSocket-Protocol') or 'none'}"))
            self.counts["status_errors"] += 1
            await ws.close(CLOSE_PROTOCOL, f"subprotocol {fp.SUBPROTOCOL} required")
            if self.on_disconnect is not None:      # what the login took (a robot session) is given back
                await self.on_disconnect(client)
            return
        self.clients.add(client)
        self.counts["clients_total"] += 1
        caps = (["clientPublish"] if self.on_publish else []) + (["services"] if self.on_service_call else [])
        client.send_control(fp.server_info(self.name, caps, supported_encodings=list(self.client_encodings)))
        client.send_control(fp.advertise(list(client.channels.values())))
        if client.services:
            client.send_control(fp.advertise_services(list(client.services.values())))
        log.info("Foxglove client connected", peer=str(ws.remote_address), principal=str(client.principal))
        writer = Tasks("foxglove writer")
        writer.spawn(client.write(), name="writer")
        try:
            if self.on_connect is not None:
                await self.on_connect(client)
            async for msg in ws:
                events = client.state.receive_text(msg) if isinstance(msg, str) else client.state.receive_binary(msg)
                for ev in events:
                    await self._event(client, ev)
                await asyncio.sleep(0)          # a flood of ops costs its sender, not the others
        except ConnectionClosed:
            pass
        except RCEError as e:           # on_connect refused: say why, then close
            client.status(fp.ERROR, e.message)
            await asyncio.sleep(0)
        finally:
            self.clients.discard(client)
            if self.on_disconnect is not None:
                await self.on_disconnect(client)
            await writer.cancel_all()
            log.info("Foxglove client disconnected", peer=str(ws.remote_address), dropped=client.dropped,
                     status_dropped=client.status_dropped)

    async def _event(self, client: FoxgloveClient, ev: fp.Event) -> None:
        match ev:
            case fp.Problem(message=message, level=level):
                client.status(level, message)
            case fp.Subscribed(subscription_id=sid, channel_id=cid):
                if cid in self.latched:
                    stamp, payload = self.latched[cid]
                    client.send_data(cid, fp.message_data(sid, stamp, payload))
                await self._hook(self.on_subscribe, client, client.channels.get(cid))
            case fp.Unsubscribed(channel_id=cid):
                await self._hook(self.on_unsubscribe, client, client.channels.get(cid))
            case fp.Published(channel=ch, payload=payload):
                self.counts["published_in"] += 1
                try:
                    await self.on_publish(client, ch, payload)
                except RCEError as e:
                    client.status(fp.ERROR, f"{ch.topic}: {e.message}")
            case fp.ServiceCalled():
                await self._call(client, ev)

    @staticmethod
    async def _hook(hook: OnChannel | None, client: FoxgloveClient, channel: Channel | None) -> None:
        if hook is not None and channel is not None:
            try:
                await hook(client, channel)
            except RCEError as e:
                client.status(fp.ERROR, f"{channel.topic}: {e.message}")

    async def _call(self, client: FoxgloveClient, ev: fp.ServiceCalled) -> None:
        self.counts["service_calls"] += 1
        service = client.services[ev.service_id]
        try:
            encoding, payload = await self.on_service_call(client, service, ev.encoding, ev.payload)
        except RCEError as e:
            client.send_control(fp.service_call_failure(ev.service_id, ev.call_id, e.message))
            return
        client.send_control(fp.service_call_response(ev.service_id, ev.call_id, encoding, payload))


def _refuse(connection: ServerConnection, e: RCEError, what: str, **fields) -> Response:
    """The HTTP answer to a refused login: 401 (AuthError), 404 (NotFound), else 403, its reason in the body."""
    status = (HTTPStatus.UNAUTHORIZED if isinstance(e, AuthError) else
              HTTPStatus.NOT_FOUND if isinstance(e, NotFound) else HTTPStatus.FORBIDDEN)
    log.info(f"Foxglove {what} refused", status=int(status), reason=e.message, **fields)
    return connection.respond(status, e.message + "\n")


def _select(_connection: ServerConnection, offered) -> str | None:
    """The subprotocol: ``foxglove.websocket.v1`` when offered, else none (the handler then refuses it)."""
    return fp.SUBPROTOCOL if fp.SUBPROTOCOL in offered else None
