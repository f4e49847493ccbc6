"""Asyncio client library for the RCE client protocol (DESIGN section 3).

::

    conn = await Connection.connect("http://127.0.0.1:9000/", "testUser", "testUser", "testRobot")
    await conn.create_container("cTag_01")
    await conn.add_node("cTag_01", "strEcho", "Test", "stringEcho.py")
    await conn.add_interface("cTag_01", "stringEchoService", "ServiceClientInterface",
                             "Test/StringEcho", "/stringEchoService")
    await conn.add_interface("testRobot", "stringEchoService", "ServiceProviderConverter", "Test/StringEcho")
    await conn.connect("cTag_01/stringEchoService", "testRobot/stringEchoService")
    await conn.wait_interfaces_up(["stringEchoService"], timeout=30)
    svc = conn.service("stringEchoService", "Test/StringEcho")
    print(await svc.call({"data": "hello"}))        # {'data': 'hello'}
    await conn.close()

Login is ``GET master_url?userID=U&version=V`` (JSON ``{"url": ws_url, "current"?}``),
then a websocket to ``ws_url?userID=U&robotID=R&password=P`` with ``P`` the hex SHA-256
of the password. Requests (CC, DC, CN, CX) are fire-and-forget as in the RCE alpha:
the cloud answers a refused request with an ER string (:meth:`Connection.on_error`)
and reports interface and node states with ST (:meth:`Connection.on_status`).
:meth:`Connection.barrier` waits until the cloud has processed everything sent before.

Typed endpoints are bound to the robot's own (robot-side) interfaces, named on the
side where they act (docs/INTERNALS.md):

=========================================  ============================================
robot-side interface (eTag = robotID)      client endpoint
=========================================  ============================================
``SubscriberConverter/Forwarder``          :meth:`Connection.publisher` (robot -> cloud)
``PublisherConverter/Forwarder``           :meth:`Connection.subscriber` (cloud -> robot)
``ServiceProviderConverter/Forwarder``     :meth:`Connection.service` (robot calls the cloud)
``ServiceClientConverter/Forwarder``       :meth:`Connection.service_provider` (cloud calls the robot)
=========================================  ============================================

A Converter carries messages as JSON objects (:mod:`rce.messages` JSON form); a
Forwarder carries ROS 1 serialized bytes as the binary part ``msg*``. Either way a
``bytes`` message is sent as a binary part and a received binary part arrives as
``bytes``. The protocol's rules (binary parts, msgID tables, the barrier, ER attribution)
are :class:`rce.protocol.session.ClientSession`'s; this module is the asyncio shell around it.

With ``allow_reconnect=True`` the connection asks for session resume (docs/INTERNALS.md
"Session resume") and, as nats.py does, outlives a lost link: it dials the same robot
endpoint again with backoff and resumes the session with its token. Messages sent meanwhile
are kept and sent after the resume, calls and barriers in flight stay pending, and what the
cloud sent meanwhile arrives; :meth:`Connection.on_disconnected`, :meth:`Connection.on_reconnected`
and :meth:`Connection.on_resumed` tell the application. The connection closes (as today) when
the cloud refuses the resume (the grace passed) or it could not reconnect in time. A connection
made by a login whose robot endpoint died (its dials refused ``endpoint_gone_after`` times in a
row) logs in again and moves to the endpoint the master names, in a fresh session, where the cloud
re-creates its interfaces and connections; what was in flight is lost and counted
(:meth:`Connection.on_moved`, docs/INTERNALS.md "Moving to another endpoint")::

    conn = await Connection.connect(master, "testUser", "testUser", "testRobot", allow_reconnect=True)
    conn.on_resumed(lambda st: print("resumed; lost", st["dropped"]))
"""
from __future__ import annotations

import asyncio
import hashlib
import inspect
import ssl
import json
import time
from dataclasses import dataclass
from typing import Any, Awaitable, Callable, Iterable
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import aiohttp
from websockets.asyncio.client import ClientConnection, connect as ws_connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus, InvalidURI

from rce import protocol, tls
from rce.errors import AuthError, RCEError, Timeout, Unavailable, http_reason
from rce.log import get_logger
from rce.masterlink import Backoff
from rce.protocol.resume import DEFAULT_GRACE, DEFAULT_RESUME_BUFFER
from rce.protocol.events import (BarrierFailed, BarrierPassed, CallFailed, Detached, Dropped, ErrorReceived,
                                 InterfaceChanged, MessageReceived, ResponseReceived, SessionStatus, StatusReceived,
                                 unhandled)
from rce.protocol.session import ClientSession
from rce.tasks import Tasks

log = get_logger("rce.client")

CLIENT_VERSION = "20130902"      # the RCE alpha client protocol version
DEFAULT_CALL_TIMEOUT = 30.0      # s a service call waits for the cloud's response
CONNECT_TIMEOUT = 10.0           # s for each of the login and the websocket handshake
WAIT_TIMEOUT = 30.0              # s a barrier or wait_interfaces_up waits for the cloud by default
CLOSE_TIMEOUT = 5.0              # s close() waits for the reader to see the closing handshake
EXPIRY_CHECK_MIN, EXPIRY_CHECK_MAX = 0.05, 5.0   # s between expiry checks: a quarter of the expiry, within these
MAX_FRAME = 256 * 1024 * 1024    # bytes, largest websocket frame accepted
ERRORS_KEPT = 100                # ERs kept in Connection.errors
RECONNECT_WAIT = 0.05            # s before the second attempt to reconnect; it doubles after each failure ...
RECONNECT_WAIT_MAX = 1.0         # s ... up to this: a robot endpoint that is reachable again is found within 1 s
ACK_TICK_FRACTION = 0.5          # with resume, ticks come at least every ack delay x this: AKs go out on time
ENDPOINT_GONE_AFTER = 5         # dials refused in a row (connection refused or reset: nothing listens) after which
                                # the robot endpoint counts as dead and the robot logs in again to move to another
                                # one: about 0.75 s of backoff (0.05 + 0.1 + 0.2 + 0.4 s), jitter aside
FINAL_CLOSE = (1000, 1008)       # close codes by which the cloud ends a session: nothing to resume

Message = dict | bytes            # JSON-form message (Converter) or serialized bytes (Forwarder)
StatusCallback = Callable[[dict], Any]
ErrorCallback = Callable[[str], Any]


def hash_password(password: str) -> str:
    """The wire form of a password: hex SHA-256 of its UTF-8 bytes (64 chars)."""
    return hashlib.sha256(password.encode()).hexdigest()


def _with_query(url: str, **params: str) -> str:
    parts = urlsplit(url)
    query = dict(parse_qsl(parts.query))
    query.update(params)
    return urlunsplit((parts.scheme, parts.netloc, parts.path or "/", urlencode(query), parts.fragment))


async def login(master_url: str, user_id: str, version: str = CLIENT_VERSION,
                timeout: float = CONNECT_TIMEOUT, ssl_context: ssl.SSLContext | None = None) -> str:
    """Ask the master for this user's robot endpoint; returns its websocket URL.

    ``GET master_url?userID=U&version=V`` -> ``{"url": ws_url, "current"?: V'}`` (``current``
    only when this client is outdated: logged as a warning). An ``https://`` master is verified
    with ``ssl_context`` (default :func:`rce.tls.client_context`: ``$RCE_CA_FILE``, else the
    system's CAs). Raises :class:`AuthError` (HTTP 401/403) or :class:`Unavailable` (any other
    HTTP error, an unreachable or untrusted master, a malformed answer) with the master's
    one-line reason."""
    url = _with_query(master_url, userID=user_id, version=version)
    try:
        async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=timeout)) as http:
            async with http.get(url, ssl=ssl_context or tls.client_context()) as resp:
                body = await resp.read()
                if resp.status in (401, 403):
                    reason = http_reason(body, resp.reason or "unauthorized")
                    raise AuthError(f"login refused by {master_url}: {reason}")
                if resp.status >= 400:
                    raise Unavailable(f"login at {master_url} failed (HTTP {resp.status}): "
                                      f"{http_reason(body, resp.reason or 'error')}")
    except (aiohttp.ClientError, asyncio.TimeoutError, OSError) as e:
        raise Unavailable(f"cannot reach the master at {master_url}: "
                          f"{tls.tls_failure(e, master_url) or e or type(e).__name__}") from None
    try:
        answer = json.loads(body)
        ws_url = answer["url"]
        if not isinstance(ws_url, str) or not ws_url:
            raise ValueError
    except (ValueError, KeyError, TypeError):
        raise Unavailable(f"login at {master_url}: answer has no websocket 'url': {body[:200]!r}") from None
    if answer.get("current"):
        log.warning("client protocol version is outdated", version=version, current=answer["current"])
    return ws_url


class _ClassOrInstance:
    """A method that does one thing on the class and another on an instance: the RCE alpha
    names both the login (``Connection.connect(...)``) and the CX request (``conn.connect(a, b)``)."""

    def __init__(self, on_class: classmethod, on_instance: Callable):
        self.on_class, self.on_instance = on_class, on_instance
        self.__doc__ = (f"On the class: {on_class.__func__.__doc__}\n\n"
                        f"On an instance: {on_instance.__doc__}")

    def __get__(self, obj: Any, objtype: type | None = None) -> Callable:
        if obj is None:
            return self.on_class.__get__(None, objtype)
        return self.on_instance.__get__(obj, objtype)


class Publisher:
    """Sends messages to a robot-side ``SubscriberConverter``/``SubscriberForwarder``."""

    def __init__(self, conn: "Connection", itag: str, cls: str):
        self.conn, self.itag, self.cls = conn, itag, cls
        self.sent = 0

    async def publish(self, msg: Message) -> None:
        """Send one message: a JSON-form dict (Converter) or ROS 1 serialized bytes
        (Forwarder; sent as binary part ``msg*``). Raises :class:`Unavailable` when closed."""
        await self.conn.send(protocol.DM, {"iTag": self.itag, "type": self.cls, "msg": msg})
        self.sent += 1


class Subscriber:
    """Receives messages from a robot-side ``PublisherConverter``/``PublisherForwarder``:
    ``callback(msg)`` (sync or async) gets a dict (Converter) or bytes (Forwarder)."""

    def __init__(self, conn: "Connection", itag: str, cls: str, callback: Callable[[Message], Any]):
        self.conn, self.itag, self.cls, self.callback = conn, itag, cls, callback
        self.received = 0

    def close(self) -> None:
        """Stop receiving (later DMs for this iTag are logged as unhandled)."""
        if self.conn._handlers.get(self.itag) is self:
            del self.conn._handlers[self.itag]


class ServiceClient:
    """Calls the cloud through a robot-side ``ServiceProviderConverter``/``ServiceProviderForwarder``."""

    def __init__(self, conn: "Connection", itag: str, srv_cls: str):
        self.conn, self.itag, self.srv_cls = conn, itag, srv_cls
        self.calls = 0

    async def call(self, request: Message | None = None, timeout: float | None = DEFAULT_CALL_TIMEOUT) -> Message:
        """Send ``DM {iTag, type, msgID, msg: request}`` with a fresh msgID and return the ``msg``
        of the response DM with the same msgID (dict for a Converter, bytes for a Forwarder).

        Raises :class:`rce.errors.Timeout` (a :class:`TimeoutError`) after ``timeout`` s (None: no
        limit), :class:`Unavailable` when the connection closes, :class:`RequestError` when the
        cloud answers the call with an ER naming it."""
        session = self.conn.session
        msg_id = session.call(self.itag, self.srv_cls, {} if request is None else request)
        self.calls += 1
        try:
            await self.conn._write()
            return await session.pending.wait(msg_id, timeout)
        except Timeout:
            raise Timeout(f"service {self.itag!r} ({self.srv_cls}) did not answer within {timeout:g} s") from None
        finally:
            session.pending.forget(msg_id)


class ServiceProvider:
    """Serves calls from the cloud arriving at a robot-side ``ServiceClientConverter``/
    ``ServiceClientForwarder``: ``handler(request)`` (sync or async) returns the response
    (dict or bytes), sent back as a DM with the request's msgID. A handler that raises
    gets no reply (the cloud's caller times out); the failure is logged and counted."""

    def __init__(self, conn: "Connection", itag: str, srv_cls: str, handler: Callable[[Message], Any]):
        self.conn, self.itag, self.srv_cls, self.handler = conn, itag, srv_cls, handler
        self.served = self.failed = 0

    def close(self) -> None:
        if self.conn._handlers.get(self.itag) is self:
            del self.conn._handlers[self.itag]

    async def _on_dm(self, call: MessageReceived) -> None:
        msg_id = call.msg_id
        try:
            resp = self.handler(call.msg)
            if inspect.isawaitable(resp):
                resp = await resp
        except Exception as e:
            self.failed += 1
            reason = e.message if isinstance(e, RCEError) else f"{type(e).__name__}: {e}"
            log.warning("service call from the cloud failed", itag=self.itag, msg_id=msg_id, reason=reason)
            return
        self.served += 1
        out = {"iTag": self.itag, "type": call.type or self.srv_cls, "msg": resp}
        if msg_id is not None:
            out["msgID"] = msg_id
        await self.conn.send(protocol.DM, out)


@dataclass(frozen=True)
class Reconnect:
    """How a connection with ``allow_reconnect`` reconnects and resumes (the knobs of nats.py's
    ``connect``): ``max_attempts`` dials per gap (None: until the session's grace, which the cloud
    gives, has passed since the drop); ``time_wait``: s before the second dial, doubling after each
    failure up to ``max_wait`` s (with jitter, :class:`rce.masterlink.Backoff`); ``resume_buffer``:
    messages kept until the cloud acks them (past it the oldest are lost and counted);
    ``timeout``: s for each dial's handshake; ``gone_after``: dials refused in a row after which the
    endpoint counts as dead, and a connection made by a login moves to the endpoint the master names."""

    max_attempts: int | None = None
    time_wait: float = RECONNECT_WAIT
    max_wait: float = RECONNECT_WAIT_MAX
    resume_buffer: int = DEFAULT_RESUME_BUFFER
    timeout: float = CONNECT_TIMEOUT
    gone_after: int = ENDPOINT_GONE_AFTER


class _Refused(Exception):
    """A websocket handshake refused with an HTTP status (and the endpoint's reason)."""

    def __init__(self, status: int, reason: str):
        super().__init__(f"HTTP {status}: {reason}")
        self.status, self.reason = status, reason


class _Unreachable(Unavailable):
    """Nothing listens at the robot endpoint's address (connection refused or reset)."""


class Connection:
    """One robot's connection to the cloud: the websocket shell of a
    :class:`~rce.protocol.session.ClientSession` (which holds the rules). Create with :meth:`connect`.

    Attributes: ``user_id``, ``robot_id``, ``ws_url``; ``interfaces``: iTag -> last ST ``iu``
    status (bool); ``errors``: every ER string received (most recent last, the last
    :data:`ERRORS_KEPT`); ``dropped``: DMs with no handler, malformed frames and expired binary parts;
    ``reconnect``: the :class:`Reconnect` settings, None without ``allow_reconnect``; ``resumes``:
    sessions resumed; ``connected``: False while a lost link is being replaced; ``moves``: fresh sessions
    opened on another endpoint after the first one died; ``moved_lost``: messages to the cloud lost
    with a dead endpoint (in flight or sent during the gap); ``relogin``: (master URL, password,
    version) of a connection made by a login, which lets it move."""

    def __init__(self, ws: ClientConnection, user_id: str, robot_id: str, ws_url: str,
                 expiry: float = protocol.DEFAULT_EXPIRY, reconnect: Reconnect | None = None):
        self.ws, self.user_id, self.robot_id, self.ws_url = ws, user_id, robot_id, ws_url
        self.reconnect = reconnect
        self.session = ClientSession(expiry=expiry, resume=reconnect is not None,
                                     resume_buffer=reconnect.resume_buffer if reconnect else DEFAULT_RESUME_BUFFER)
        self.resumes = self.moves = self.moved_lost = 0
        self.relogin: tuple[str, str, str] | None = None
        self.ssl_context: ssl.SSLContext | None = None     # verifies a wss:// endpoint (open's ssl_context)
        self.max_lag: float | None = None                 # s: the maxLag it asked for (open), also after a move
        self.errors: list[str] = []
        self.unhandled = 0                          # DMs for an iTag with no handler
        self.close_reason: str | None = None
        self._handlers: dict[str, Subscriber | ServiceProvider] = {}
        self._status_cbs: list[StatusCallback] = []
        self._error_cbs: list[ErrorCallback] = []
        self._link_cbs: dict[str, list[Callable[[Any], Any]]] = {"disconnected": [], "reconnected": [], "resumed": [],
                                                                 "moved": []}
        self._changed = asyncio.Event()
        self._barrier_ok = True
        self._send_lock = asyncio.Lock()
        self._closed = asyncio.Event()
        self._kicked = False                        # a writer task is due to send what the session produced
        self.tasks = Tasks(f"rce-client {robot_id}")
        self._reader = self.tasks.spawn(self._read_loop(ws), name="reader")
        self.tasks.spawn(self._expire_loop(), name="expire")

    @property
    def connected(self) -> bool:
        """Is the session on a live link (False while it waits for a resume, and once closed)?"""
        return not self.closed and self.session.state not in ("detached", "resuming")

    @property
    def interfaces(self) -> dict[str, bool]:
        """iTag -> last ST ``iu`` status."""
        return self.session.interfaces

    @property
    def dropped(self) -> int:
        """DMs with no handler, malformed frames, expired binary parts, unexpected messages."""
        return self.session.dropped + self.unhandled

    # -- connect / close ---------------------------------------------------------------------
    @classmethod
    async def login_connect(cls, master_url: str, user_id: str, password: str, robot_id: str, *,
                            version: str = CLIENT_VERSION, timeout: float = CONNECT_TIMEOUT,
                            **options: Any) -> "Connection":
        """Log in at the master and open the robot's websocket.

        ``master_url``: ``http://HOST:9000/``; ``password`` in clear (hashed here);
        ``timeout``: s for each of login and handshake; ``options``: those of :meth:`open`
        (``expiry``, ``allow_reconnect``, ...). Raises :class:`AuthError` (bad credentials: HTTP or
        handshake 401/403, with the cloud's reason) or :class:`Unavailable`."""
        ws_url = await login(master_url, user_id, version, timeout, options.get("ssl_context"))
        conn = await cls.open(ws_url, user_id, password, robot_id, timeout=timeout, **options)
        conn.relogin = (master_url, password, version)
        return conn

    @classmethod
    async def open(cls, ws_url: str, user_id: str, password: str, robot_id: str, *,
                   timeout: float = CONNECT_TIMEOUT, expiry: float = protocol.DEFAULT_EXPIRY,
                   allow_reconnect: bool = False, max_reconnect_attempts: int | None = None,
                   reconnect_time_wait: float = RECONNECT_WAIT, max_reconnect_wait: float = RECONNECT_WAIT_MAX,
                   resume_buffer: int = DEFAULT_RESUME_BUFFER,
                   endpoint_gone_after: int = ENDPOINT_GONE_AFTER,
                   ssl_context: ssl.SSLContext | None = None, max_lag: float | None = None) -> "Connection":
        """Open the websocket at a known robot endpoint ``ws_url`` (skips the login).

        ``ssl_context`` verifies a ``wss://`` endpoint (and an ``https://`` master on a login; default
        :func:`rce.tls.client_context`: ``$RCE_CA_FILE``, else the system's CAs).

        ``expiry``: s an incomplete message waits for its binary parts. ``allow_reconnect``: ask for
        session resume and reconnect after a lost link (:class:`Reconnect` gives the other settings;
        ``endpoint_gone_after`` is its ``gone_after``). ``max_lag``: s the endpoint may lag behind
        this connection before it sheds its topic messages (``maxLag``, docs/INTERNALS.md "A peer that
        does not keep up"); 0 for never, as an operator sending commands on topics wants; None: the
        endpoint's default.
        Raises :class:`AuthError` or :class:`Unavailable` as :meth:`connect`."""
        reconnect = Reconnect(max_reconnect_attempts, reconnect_time_wait, max_reconnect_wait, resume_buffer,
                              timeout, endpoint_gone_after) if allow_reconnect else None
        query = {"userID": user_id, "robotID": robot_id, "password": hash_password(password), "refusal": "http",
                 **({"maxLag": f"{max_lag:g}"} if max_lag is not None else {})}
        ssl_context = ssl_context or tls.client_context()
        try:
            ws = await _dial(_with_query(ws_url, **query, **({"resume": "1"} if allow_reconnect else {})), timeout,
                             ssl_context)
        except _Refused as e:
            if e.status in (401, 403):
                raise AuthError(f"robot endpoint {ws_url} refused {user_id}/{robot_id}: {e.reason}") from None
            raise Unavailable(f"robot endpoint {ws_url} refused the connection (HTTP {e.status}): {e.reason}") from None
        except Unavailable as e:
            raise Unavailable(f"cannot connect to the robot endpoint {ws_url}: {e.message}") from None
        log.info("connected", user=user_id, robot=robot_id, url=ws_url, resume=allow_reconnect)
        conn = cls(ws, user_id, robot_id, ws_url, expiry, reconnect)
        conn.ssl_context, conn.max_lag = ssl_context, max_lag
        return conn

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    async def wait_closed(self) -> str:
        """Wait until the connection ends (either side); returns the reason."""
        await self._closed.wait()
        return self.close_reason or "closed"

    async def close(self) -> None:
        """Close the websocket (which ends the session: the cloud does not keep it for a resume);
        pending service calls fail with :class:`Unavailable`."""
        if self.close_reason is None:
            self.close_reason = "closed by the client"
        await _close_quietly(self.ws)
        try:
            await asyncio.wait_for(asyncio.shield(self._reader), CLOSE_TIMEOUT)
        except (asyncio.TimeoutError, asyncio.CancelledError):
            self._reader.cancel()
        await self._finish()

    async def _finish(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self.session.close(self.close_reason or "closed")
        self.session.events_received()           # call_failed/barrier_failed: their waiters have the error
        self._changed.set()
        await self.tasks.cancel_all()
        await _close_quietly(self.ws)            # a link a reconnect had just opened

    async def __aenter__(self) -> "Connection":
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    # -- sending -----------------------------------------------------------------------------
    async def send(self, type_: str, data: Any) -> None:
        """Send one message ``{"type": type_, "data": data}``; ``bytes`` values anywhere in
        ``data`` go as binary parts (JSON frame first, then one binary frame per part).
        Raises :class:`Unavailable` when the connection is closed."""
        self.session.send(type_, data)
        await self._write()

    async def _write(self) -> None:
        """Write what the session has to send, in order, on the current link (one writer at a time:
        frames leave in the order the session made them). Raises :class:`Unavailable` when the link
        closed, unless the session is kept for a resume (it then sends what the cloud did not get)."""
        async with self._send_lock:
            while frames := self.session.data_to_send():
                ws = self.ws
                try:
                    for f in frames:
                        await ws.send(f)
                except ConnectionClosed as e:
                    if self.reconnect is not None and self.session.state != "off":
                        return
                    raise Unavailable(f"connection to the cloud closed: {_close_text(e)}") from None

    def _kick(self) -> None:
        """Frames the reader or a timer made (AKs, a resume's resend) go out, from a task."""
        if self.session.outbox and not self._kicked:
            self._kicked = True
            self.tasks.spawn(self._kicked_write(), name="write")

    async def _kicked_write(self) -> None:
        self._kicked = False
        try:
            await self._write()
        except Unavailable:      # the reader sees the closed link too
            pass

    async def create_container(self, tag: str, group: str | None = None, **container_data: Any) -> None:
        """CC: create container ``tag``. ``container_data`` keys: ``groupIp``, ``size``, ``cpu``
        (cores), ``memory`` (MiB), ``bandwidth``, ``specialFeatures`` (None values are left out)."""
        cd = {k: v for k, v in {"group": group, **container_data}.items() if v is not None}
        data: dict = {"containerTag": tag}
        if cd:
            data["containerData"] = cd
        await self.send(protocol.CC, data)

    async def destroy_container(self, tag: str) -> None:
        """DC: destroy container ``tag`` (with its nodes, interfaces and connections)."""
        await self.send(protocol.DC, {"containerTag": tag})

    async def configure(self, cn_data: dict) -> None:
        """CN with raw data: any of ``addNodes``, ``removeNodes``, ``setParam``, ``deleteParam``,
        ``addInterfaces``, ``removeInterfaces``, each a list of components."""
        await self.send(protocol.CN, cn_data)

    async def add_node(self, ctag: str, ntag: str, pkg: str, exe: str, args: str | list[str] = "",
                       name: str | None = None, namespace: str | None = None,
                       respawn: bool | dict | None = None) -> None:
        """CN addNodes: launch ``pkg``/``exe`` with ``args`` in container ``ctag`` as node ``ntag``."""
        node = {"containerTag": ctag, "nodeTag": ntag, "pkg": pkg, "exe": exe}
        for k, v in (("args", args), ("name", name), ("namespace", namespace), ("respawn", respawn)):
            if v not in (None, ""):
                node[k] = v
        await self.configure({"addNodes": [node]})

    async def remove_node(self, ctag: str, ntag: str) -> None:
        """CN removeNodes: stop node ``ntag`` of container ``ctag``."""
        await self.configure({"removeNodes": [{"containerTag": ctag, "nodeTag": ntag}]})

    async def set_param(self, ctag: str, name: str, value: Any) -> None:
        """CN setParam: set parameter ``name`` of container ``ctag`` to a JSON value."""
        await self.configure({"setParam": [{"containerTag": ctag, "name": name, "value": value}]})

    async def delete_param(self, ctag: str, name: str) -> None:
        """CN deleteParam: delete parameter ``name`` of container ``ctag``."""
        await self.configure({"deleteParam": [{"containerTag": ctag, "name": name}]})

    async def add_interface(self, etag: str, itag: str, itype: str, cls: str, addr: str | None = None) -> None:
        """CN addInterfaces: interface ``itag`` of type ``itype`` (e.g. ``PublisherInterface``,
        ``SubscriberConverter``) and message/service class ``cls`` on endpoint ``etag`` (a
        container tag, or this robot's ID for robot-side interfaces); ``addr`` is the topic or
        service name on that endpoint's bus."""
        itf = {"endpointTag": etag, "interfaceTag": itag, "interfaceType": itype, "className": cls}
        if addr:
            itf["addr"] = addr
        await self.configure({"addInterfaces": [itf]})

    async def remove_interface(self, etag: str, itag: str) -> None:
        """CN removeInterfaces: remove interface ``etag/itag``."""
        await self.configure({"removeInterfaces": [{"endpointTag": etag, "interfaceTag": itag}]})

    async def connect_interfaces(self, tag_a: str, tag_b: str) -> None:
        """CX connect: wire interfaces ``tag_a`` and ``tag_b`` (each ``endpointTag/interfaceTag``)."""
        await self.send(protocol.CX, {"connect": [{"tagA": tag_a, "tagB": tag_b}]})

    #: ``await Connection.connect(master_url, user_id, password, robot_id)`` logs in
    #: (:meth:`login_connect`); ``await conn.connect(tag_a, tag_b)`` wires two interfaces
    #: (:meth:`connect_interfaces`).
    connect = _ClassOrInstance(login_connect, connect_interfaces)

    async def disconnect(self, tag_a: str, tag_b: str) -> None:
        """CX disconnect: remove the connection between ``tag_a`` and ``tag_b``."""
        await self.send(protocol.CX, {"disconnect": [{"tagA": tag_a, "tagB": tag_b}]})

    async def barrier(self, timeout: float = WAIT_TIMEOUT) -> bool:
        """Wait until the cloud has processed every request sent before this call.

        The protocol has no acks, but the master handles a robot's requests one at a time,
        in order, and answers each refusal with an ER: this sends a CX between two interfaces
        that cannot exist and waits for the ER naming them (which is not passed to
        :meth:`on_error` callbacks). Returns True when passed; False when the cloud did not
        answer within ``timeout`` s, after which barriers are skipped (return False at once)
        for the rest of the connection. Raises :class:`Unavailable` when the connection closes."""
        if not self._barrier_ok:
            return False
        token = self.session.barrier()
        try:
            await self._write()
            await self.session.pending.wait(token, timeout)
            return True
        except Timeout:
            self._barrier_ok = False
            log.warning("the cloud did not answer a sync probe; barriers disabled", timeout=timeout)
            return False
        finally:
            self.session.pending.forget(token)

    # -- typed endpoints ---------------------------------------------------------------------
    def publisher(self, itag: str, cls: str) -> Publisher:
        """Bind to robot-side ``SubscriberConverter``/``Forwarder`` ``itag`` of message class ``cls``."""
        return Publisher(self, itag, cls)

    def subscriber(self, itag: str, cls: str, callback: Callable[[Message], Any]) -> Subscriber:
        """Receive the DMs of robot-side ``PublisherConverter``/``Forwarder`` ``itag``; one
        handler per iTag (a new one replaces the old)."""
        sub = Subscriber(self, itag, cls, callback)
        self._handlers[itag] = sub
        return sub

    def service(self, itag: str, srv_cls: str) -> ServiceClient:
        """Bind to robot-side ``ServiceProviderConverter``/``Forwarder`` ``itag`` (calls to the cloud)."""
        return ServiceClient(self, itag, srv_cls)

    def service_provider(self, itag: str, srv_cls: str, handler: Callable[[Message], Any]) -> ServiceProvider:
        """Serve the cloud's calls arriving at robot-side ``ServiceClientConverter``/``Forwarder``
        ``itag``; one handler per iTag."""
        prov = ServiceProvider(self, itag, srv_cls, handler)
        self._handlers[itag] = prov
        return prov

    # -- status ------------------------------------------------------------------------------
    def on_status(self, cb: StatusCallback) -> None:
        """Call ``cb(data)`` (sync or async) for every ST: ``{"topic": "iu", "iTag", "status"}``
        or ``{"topic": "node", "cTag", "nTag", "status", ...}``."""
        self._status_cbs.append(cb)

    def on_error(self, cb: ErrorCallback) -> None:
        """Call ``cb(reason)`` (sync or async) for every ER from the cloud (they are logged too)."""
        self._error_cbs.append(cb)

    def on_disconnected(self, cb: Callable[[str], Any]) -> None:
        """(``allow_reconnect``) Call ``cb(reason)`` when the link is lost and the session kept: the
        connection reconnects and resumes; sends and calls wait meanwhile."""
        self._link_cbs["disconnected"].append(cb)

    def on_reconnected(self, cb: Callable[[str], Any]) -> None:
        """(``allow_reconnect``) Call ``cb(ws_url)`` when a new link is open (the resume follows)."""
        self._link_cbs["reconnected"].append(cb)

    def on_resumed(self, cb: Callable[[dict], Any]) -> None:
        """(``allow_reconnect``) Call ``cb(data)`` when the session is resumed: ``data`` is the cloud's
        ``ST {"topic": "session", "status": "resumed", "ack", "dropped", ...}`` (``dropped``: messages to
        the robot the cloud's buffer lost)."""
        self._link_cbs["resumed"].append(cb)

    def on_moved(self, cb: Callable[[dict], Any]) -> None:
        """(``allow_reconnect``, made by a login) Call ``cb({"ws_url", "lost"})`` when the robot endpoint
        died and a fresh session is open on the one the master named (``ws_url``): the cloud re-creates the
        robot's interfaces and connections there (``iu true``); ``lost``: messages to the cloud that
        were in flight or sent during the gap, lost with the dead endpoint. Calls in flight failed."""
        self._link_cbs["moved"].append(cb)

    async def wait_interfaces_up(self, itags: Iterable[str], timeout: float = WAIT_TIMEOUT) -> None:
        """Wait until the last ST ``iu`` status of every iTag in ``itags`` is true.

        Raises :class:`Unavailable` after ``timeout`` s naming the interfaces still down
        (with the last ER received, if any), or when the connection closes."""
        itags = list(itags)
        deadline = asyncio.get_running_loop().time() + timeout
        while True:
            down = [t for t in itags if not self.interfaces.get(t)]
            if not down:
                return
            if self.closed:
                raise Unavailable(f"connection to the cloud closed ({self.close_reason}) while interfaces "
                                  f"{', '.join(down)} were down")
            left = deadline - asyncio.get_running_loop().time()
            self._changed.clear()
            try:
                if left <= 0:
                    raise asyncio.TimeoutError
                await asyncio.wait_for(self._changed.wait(), left)
            except asyncio.TimeoutError:
                hint = f"; last error from the cloud: {self.errors[-1]}" if self.errors else ""
                raise Unavailable(f"interfaces still down after {timeout:g} s: {', '.join(down)}{hint}") from None

    # -- receiving ---------------------------------------------------------------------------
    async def _read_loop(self, ws: ClientConnection) -> None:
        reason = "connection lost"
        try:
            async for frame in ws:
                if isinstance(frame, str):
                    self.session.receive_text(frame, time.monotonic())
                else:
                    self.session.receive_binary(frame, time.monotonic())
                self._dispatch()
            reason = _close_text(ws)
        except ConnectionClosed as e:
            reason = _close_text(e)
        except Exception as e:   # the reader never dies silently
            reason = f"reader failed: {type(e).__name__}: {e}"
            log.exception("client reader failed", robot=self.robot_id)
        finally:
            if ws is self.ws and not self._closed.is_set() and not self._resuming(ws, reason):
                self.close_reason = self.close_reason or reason
                if self.close_reason != "closed by the client":
                    log.info("connection closed", robot=self.robot_id, reason=self.close_reason)
                await self._finish()

    def _resuming(self, ws: ClientConnection, reason: str) -> bool:
        """The link is lost: keep the session and start reconnecting, when it can be resumed."""
        rcvd = ws.protocol.close_rcvd
        if self.reconnect is None or self.close_reason is not None or (rcvd is not None and rcvd.code in FINAL_CLOSE):
            return False
        if not self.session.detach(reason):
            return False
        self._dispatch()
        log.info("link to the cloud lost; resuming", robot=self.robot_id, reason=reason)
        for cb in self._link_cbs["disconnected"]:
            self._run_cb(cb, reason)
        self.tasks.spawn(self._reconnect(), name="reconnect")
        return True

    async def _reconnect(self) -> None:
        """Dial the robot endpoint with the resume query until it takes it (then the new link's reader
        waits for the cloud's ST resumed), the grace has passed, or it refuses: then the connection closes.
        A connection made by a login whose endpoint refused ``gone_after`` dials in a row moves
        (:meth:`_move`) to the endpoint the master names."""
        r = self.reconnect
        backoff = Backoff(r.time_wait, cap=max(r.time_wait, r.max_wait))
        deadline = time.monotonic() + (self.session.grace or DEFAULT_GRACE)
        attempts = refused = 0
        while True:
            attempts += 1
            url = _with_query(self.ws_url, userID=self.user_id, robotID=self.robot_id, **self.session.resume_query())
            try:
                if self.relogin is not None and refused >= r.gone_after:
                    await self._move()
                    return
                ws = await _dial(url, r.timeout, self.ssl_context)
                break
            except (_Refused, AuthError) as e:  # 401: the session expired (or the token is wrong); 400: bad ack
                self.close_reason = f"the cloud refused to resume the session ({e})"
            except Unavailable as e:
                # once the endpoint counts as dead, a failed move (the master is away, or has not seen it die yet)
                # is tried again after the backoff
                refused = refused + 1 if isinstance(e, _Unreachable) or refused >= r.gone_after else 0
                delay = backoff.next()
                if (r.max_attempts is None or attempts < r.max_attempts) and time.monotonic() + delay < deadline:
                    await asyncio.sleep(delay)      # the backoff, a timer
                    continue
                self.close_reason = f"could not resume the session ({attempts} attempt(s)): {e.message}"
            log.info("connection closed", robot=self.robot_id, reason=self.close_reason)
            await self._finish()
            return
        self.ws = ws
        self.session.attach()
        self._reader = self.tasks.spawn(self._read_loop(ws), name="reader")
        log.info("reconnected; resuming", robot=self.robot_id, url=self.ws_url, attempts=attempts)
        for cb in self._link_cbs["reconnected"]:
            self._run_cb(cb, self.ws_url)

    async def _move(self) -> None:
        """The robot endpoint is dead: log in at the master again and open a fresh session (``resume=1``)
        at the endpoint it names, where the cloud re-creates the robot's interfaces and connections
        (docs/INTERNALS.md "Session resume", "Moving to another endpoint"). What the old session kept
        is lost (counted in :attr:`moved_lost`), its calls and barriers fail. Raises :class:`Unavailable`
        (the master is unreachable or still names the dead endpoint; try again) or :class:`AuthError`."""
        master_url, password, version = self.relogin
        timeout = self.reconnect.timeout
        ws_url = await login(master_url, self.user_id, version, timeout, self.ssl_context)
        if ws_url == self.ws_url:
            raise Unavailable(f"the master still names the dead robot endpoint {ws_url}")
        query = {"userID": self.user_id, "robotID": self.robot_id, "password": hash_password(password), "resume": "1",
                 "refusal": "http",
                 **({"maxLag": f"{self.max_lag:g}"} if self.max_lag is not None else {})}
        try:
            ws = await _dial(_with_query(ws_url, **query), timeout, self.ssl_context)
        except _Refused as e:
            if e.status in (401, 403):
                raise AuthError(f"robot endpoint {ws_url} refused {self.user_id}/{self.robot_id}: {e.reason}") from None
            raise Unavailable(f"robot endpoint {ws_url} refused the connection (HTTP {e.status}): {e.reason}") from None
        old = self.session
        lost = len(old.outgoing) if old.outgoing is not None else 0
        old.close(f"the robot endpoint {self.ws_url} died; the session moved to {ws_url}")
        self._dispatch()                             # calls and barriers in flight fail
        self.session = ClientSession(expiry=old.assembler.expiry, resume=True,
                                     resume_buffer=self.reconnect.resume_buffer)
        self.ws, self.ws_url = ws, ws_url
        self.moves += 1
        self.moved_lost += lost
        self._reader = self.tasks.spawn(self._read_loop(ws), name="reader")
        log.warning("robot endpoint died; moved to another", robot=self.robot_id, url=ws_url, lost=lost)
        for cb in self._link_cbs["moved"]:
            self._run_cb(cb, {"ws_url": ws_url, "lost": lost})

    async def _expire_loop(self) -> None:
        period = max(EXPIRY_CHECK_MIN, min(self.session.assembler.expiry / 4, EXPIRY_CHECK_MAX))
        if self.session.incoming is not None:
            period = min(period, self.session.incoming.ack_delay * ACK_TICK_FRACTION)
        while True:
            await asyncio.sleep(period)   # a timer, not a synchronisation
            self.session.tick(time.monotonic())
            self._dispatch()

    def _run_cb(self, cb: Callable, arg: Any) -> None:
        try:
            r = cb(arg)
            if inspect.isawaitable(r):
                self.tasks.spawn(_awaited(r), name="callback")
        except Exception as e:
            log.warning("client callback failed", reason=repr(e))

    def _dispatch(self) -> None:
        """Do what the session's events say: callbacks, handlers, errors."""
        for ev in self.session.events_received():
            match ev:
                case MessageReceived():
                    self._on_message(ev)
                case StatusReceived(data=data):
                    for cb in self._status_cbs:
                        self._run_cb(cb, data)
                case InterfaceChanged():
                    self._changed.set()
                case ErrorReceived(reason=reason) | CallFailed(reason=reason):   # an ER that failed a call too
                    self._on_error(reason)
                case Dropped(reason=reason):
                    log.warning("dropped a message from the cloud", reason=reason)
                case SessionStatus(data=data):
                    if data.get("status") == "resumed":
                        self.resumes += 1
                        log.info("session resumed", robot=self.robot_id, dropped=data.get("dropped"))
                        for cb in self._link_cbs["resumed"]:
                            self._run_cb(cb, data)
                case ResponseReceived() | BarrierPassed() | BarrierFailed() | Detached():
                    pass                                # their waiters have them (the session's pending table)
                case _:
                    unhandled(ev)
        self._kick()

    def _on_message(self, ev: MessageReceived) -> None:
        handler = self._handlers.get(ev.itag)
        if handler is None:
            self.unhandled += 1
            log.warning("data message for an interface with no handler", itag=ev.itag, msg_id=ev.msg_id)
        elif isinstance(handler, ServiceProvider):
            self.tasks.spawn(handler._on_dm(ev), name="serve")     # calls are served concurrently
        else:
            handler.received += 1                                   # messages are delivered in order
            self._run_cb(handler.callback, ev.msg)

    def _on_error(self, reason: str) -> None:
        self.errors.append(reason)
        del self.errors[:-ERRORS_KEPT]
        log.warning("error from the cloud", reason=reason)
        self._changed.set()
        for cb in self._error_cbs:
            self._run_cb(cb, reason)


async def _awaited(aw: Awaitable) -> Any:
    return await aw


async def _dial(url: str, timeout: float, ssl_context: ssl.SSLContext | None = None) -> ClientConnection:
    """Open a websocket to ``url`` within ``timeout`` s (``wss://``: verified with ``ssl_context``). Raises
    :class:`_Refused` (the endpoint answered the handshake with an HTTP error) or :class:`Unavailable`
    (unreachable, an untrusted certificate, or the handshake failed)."""
    try:
        return await ws_connect(url, open_timeout=timeout, max_size=MAX_FRAME, proxy=None, compression=None,
                                user_agent_header="rce-client", ssl=tls.for_url(url, ssl_context))
    except InvalidStatus as e:
        status = e.response.status_code
        raise _Refused(status, http_reason(e.response.body or b"", e.response.reason_phrase or str(status))) from None
    except (ConnectionRefusedError, ConnectionResetError) as e:
        raise _Unreachable(str(e) or type(e).__name__) from None
    except (InvalidHandshake, InvalidURI, OSError, asyncio.TimeoutError) as e:
        raise Unavailable(tls.tls_failure(e, url.split("?", 1)[0]) or str(e) or type(e).__name__) from None


async def _close_quietly(ws: ClientConnection) -> None:
    try:
        await ws.close()
    except Exception:   # closing a broken socket never raises out of close()
        pass


def _close_text(src: Any) -> str:
    """Human text for a websocket close (an exception or a connection)."""
    rcvd = getattr(src, "rcvd", None) or getattr(src, "close_rcvd", None)
    if rcvd is not None:
        return f"code {rcvd.code}" + (f": {rcvd.reason}" if rcvd.reason else "")
    return "connection lost"
