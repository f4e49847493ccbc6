"""Asyncio client library for the RCE client protocol (docs/design.md, section 3).

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
of the password (:mod:`rce_client.dial`). Requests (CC, DC, CN, CX) are fire-and-forget as in the RCE alpha:
the cloud answers a refused request with an ER string (:meth:`Connection.on_error`)
and reports interface and node states with ST (:meth:`Connection.on_status`).
:meth:`Connection.barrier` waits until the cloud has processed everything sent before.

The connection's jobs live in their modules and :class:`Connection` composes them:
:mod:`rce_client.dial` (login, handshake, the one mapping of a refused handshake to an error),
:mod:`rce_client.verbs` (sending, CC/DC/CN/CX and the barrier), :mod:`rce_client.handles` (typed
endpoints: :meth:`Connection.publisher`, :meth:`Connection.subscriber`, :meth:`Connection.service`,
:meth:`Connection.service_provider`) and :mod:`rce_client.reconnect` (reconnect, resume, move). The
protocol's rules (binary parts, msgID tables, the barrier, ER attribution) are
:class:`rce.protocol.session.ClientSession`'s; this module is the asyncio shell around it.

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
import inspect
import ssl
import time
from typing import Any, Awaitable, Callable, Iterable

from websockets.asyncio.client import ClientConnection
from websockets.exceptions import ConnectionClosed

from rce.protocol import frames

from rce.transport import tls
from rce.plumbing.errors import Unavailable
from rce.plumbing.log import get_logger
from rce.protocol.events import (BarrierFailed, BarrierPassed, CallFailed, Detached, Dropped, ErrorReceived,
                                 InterfaceChanged, MessageReceived, ResponseReceived, SessionStatus, StatusReceived,
                                 unhandled)
from rce.interfaces.pacer import Pacing
from rce.protocol.resume import DEFAULT_RESUME_BUFFER
from rce.protocol.session import ClientSession
from rce.plumbing.tasks import Tasks
from rce_client.dial import (CLIENT_VERSION, CONNECT_TIMEOUT, close_quietly, close_text, hash_password, login,
                             open_robot_link)
from rce_client.handles import (DEFAULT_CALL_TIMEOUT, Handles, Message, Publisher, ServiceClient, ServiceProvider,
                                Subscriber)
from rce_client.reconnect import (ENDPOINT_GONE_AFTER, LINK_EVENTS, RECONNECT_WAIT, RECONNECT_WAIT_MAX, Reconnect,
                                  Reconnecting)
from rce_client.lanes import BulkLane
from rce_client.routes import Routes
from rce_client.verbs import WAIT_TIMEOUT, Verbs

__all__ = ["CLIENT_VERSION", "CONNECT_TIMEOUT", "DEFAULT_CALL_TIMEOUT", "RECONNECT_WAIT", "RECONNECT_WAIT_MAX",
           "WAIT_TIMEOUT", "Connection", "Message", "Publisher", "Reconnect", "ServiceClient", "ServiceProvider",
           "Subscriber", "hash_password", "login"]

log = get_logger("rce.client")

CLOSE_TIMEOUT = 5.0              # s close() waits for the reader to see the closing handshake
EXPIRY_CHECK_MIN, EXPIRY_CHECK_MAX = 0.05, 5.0   # s between expiry checks: a quarter of the expiry, within these
ERRORS_KEPT = 100                # ERs kept in Connection.errors
ACK_TICK_FRACTION = 0.5          # with resume, ticks come at least every ack delay x this: AKs go out on time

StatusCallback = Callable[[dict], Any]
ErrorCallback = Callable[[str], Any]


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


class Connection(Verbs, Handles, Reconnecting):
    """One robot's connection to the cloud: the websocket shell of a
    :class:`~rce.protocol.session.ClientSession` (which holds the rules). Create with :meth:`connect`.

    Attributes: ``user_id``, ``robot_id``, ``ws_url``; ``interfaces``: iTag -> last ST ``iu``
    status (bool); ``errors``: every ER string received (most recent last, the last
    :data:`ERRORS_KEPT`); ``dropped``: DMs with no handler, malformed frames and expired binary parts;
    ``reconnect``: the :class:`Reconnect` settings, None without ``allow_reconnect``; ``resumes``:
    sessions resumed; ``connected``: False while a lost link is being replaced; ``moves``: fresh sessions
    opened on another endpoint after the first one died; ``moved_lost``: messages to the cloud lost
    with a dead endpoint (in flight or sent during the gap); ``session.superseded``: state and bulk
    messages to the cloud dropped while no link was up for a newer one of their interface (the cloud's
    count the other way is in each ``on_resumed`` ST's ``superseded``); ``relogin``: (master URL, password,
    version) of a connection made by a login, which lets it move."""

    def __init__(self, ws: ClientConnection, user_id: str, robot_id: str, ws_url: str,
                 expiry: float = frames.DEFAULT_EXPIRY, reconnect: Reconnect | None = None):
        self.ws, self.user_id, self.robot_id, self.ws_url = ws, user_id, robot_id, ws_url
        self.reconnect = reconnect
        self.session = ClientSession(expiry=expiry, resume=reconnect is not None,
                                     resume_buffer=reconnect.resume_buffer if reconnect else DEFAULT_RESUME_BUFFER)
        self.resumes = self.moves = self.moved_lost = 0
        self.relogin: tuple[str, str, str] | None = None
        self.ssl_context: ssl.SSLContext | None = None     # verifies a wss:// endpoint (open's ssl_context)
        self.max_lag: float | None = None                 # s: the maxLag it asked for (open), also after a move
        self.routes: Routes | None = None                 # a follower's paths: direct, else a relay (open)
        self.mptcp = False                                # every dial over Multipath TCP where offered (open)
        self.errors: list[str] = []
        self.unhandled = 0                          # DMs for an iTag with no handler
        self.close_reason: str | None = None
        self._handlers: dict[str, Subscriber | ServiceProvider] = {}
        self._status_cbs: list[StatusCallback] = []
        self._error_cbs: list[ErrorCallback] = []
        self._link_cbs: dict[str, list[Callable[[Any], Any]]] = {e: [] for e in LINK_EVENTS}
        self._changed = asyncio.Event()
        self._barrier_ok = True
        self._send_lock = asyncio.Lock()
        self._closed = asyncio.Event()
        self._kicked = False                        # a writer task is due to send what the session produced
        self._session_evt = asyncio.Event()         # the session's state changed (started, resumed, moved, closed)
        self.bulk: BulkLane | None = None           # the bulk link, with lanes (rce_client.lanes)
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
                            expiry: float = frames.DEFAULT_EXPIRY, allow_reconnect: bool = False,
                            max_reconnect_attempts: int | None = None, reconnect_time_wait: float = RECONNECT_WAIT,
                            max_reconnect_wait: float = RECONNECT_WAIT_MAX, resume_buffer: int = DEFAULT_RESUME_BUFFER,
                            endpoint_gone_after: int = ENDPOINT_GONE_AFTER, ssl_context: ssl.SSLContext | None = None,
                            max_lag: float | None = None, routes: Routes | None = None, lanes: bool = False,
                            bulk_rate: Pacing | None = None, mptcp: bool = False) -> "Connection":
        """Log in at the master and open the robot's websocket.

        - ``master_url``: ``http://HOST:9000/`` (or ``https://``); ``password`` in clear (hashed here).
        - ``version``: the client protocol version the login names (default the RCE alpha's).
        - ``timeout``: s for each of the login and the websocket handshake (and each reconnect's dial).
        - ``expiry``: s an incomplete message from the cloud waits for its binary parts.
        - ``allow_reconnect``: ask for session resume and outlive a lost link (reconnect, resume, and
          move to another endpoint when this one died; :mod:`rce_client.reconnect`).
        - ``max_reconnect_attempts``: dials per gap (None: until the session's grace has passed).
        - ``reconnect_time_wait``: s before the second dial, doubling after each failure up to
          ``max_reconnect_wait`` s.
        - ``resume_buffer``: messages kept until the cloud acks them (past it the oldest are lost, counted).
        - ``endpoint_gone_after``: dials refused in a row after which the endpoint counts as dead and
          the connection logs in again to move.
        - ``ssl_context``: verifies an ``https://`` master and a ``wss://`` endpoint (default
          :func:`rce.transport.tls.client_context`: ``$RCE_CA_FILE``, else the system's CAs).
        - ``max_lag``: s the endpoint may lag behind this connection before it sheds its topic messages
          (``maxLag``, docs/INTERNALS.md "A peer that does not keep up"); 0 for never; None: the
          endpoint's default.
        - ``routes``: a follower's paths to the cloud (:class:`~rce_client.routes.Routes`): its own path
          first, else the first relay that answers, for the login and every dial; with
          ``allow_reconnect`` it moves between relays and the direct path by session resume
          (docs/relays.md).
        - ``lanes``: open a bulk link beside the session's link (docs/lanes.md, :mod:`rce_client.lanes`):
          the session's link becomes the control lane; needs ``allow_reconnect`` (the session's token) and
          a direct path (not through a relay).
        - ``bulk_rate``: how the bulk link is paced (docs/lanes.md "Pacing"): bytes/s (a little below the
          uplink), ``"auto"`` or None (under the rate estimated for the uplink's path), ``"off"`` (not paced).
        - ``mptcp``: connect over Multipath TCP where the kernel offers it, else TCP (every link, every dial).

        Raises :class:`AuthError` (bad credentials: HTTP or handshake 401/403, with the cloud's reason)
        or :class:`Unavailable`; ValueError for ``lanes`` without ``allow_reconnect``."""
        ws_url = await login(master_url, user_id, version, timeout, ssl_context, routes, robot_id)
        conn = await cls.open(ws_url, user_id, password, robot_id, timeout=timeout, expiry=expiry,
                              allow_reconnect=allow_reconnect, max_reconnect_attempts=max_reconnect_attempts,
                              reconnect_time_wait=reconnect_time_wait, max_reconnect_wait=max_reconnect_wait,
                              resume_buffer=resume_buffer, endpoint_gone_after=endpoint_gone_after,
                              ssl_context=ssl_context, max_lag=max_lag, routes=routes, lanes=lanes,
                              bulk_rate=bulk_rate, mptcp=mptcp)
        conn.relogin = (master_url, password, version)
        return conn

    @classmethod
    async def open(cls, ws_url: str, user_id: str, password: str, robot_id: str, *,
                   timeout: float = CONNECT_TIMEOUT, expiry: float = frames.DEFAULT_EXPIRY,
                   allow_reconnect: bool = False, max_reconnect_attempts: int | None = None,
                   reconnect_time_wait: float = RECONNECT_WAIT, max_reconnect_wait: float = RECONNECT_WAIT_MAX,
                   resume_buffer: int = DEFAULT_RESUME_BUFFER,
                   endpoint_gone_after: int = ENDPOINT_GONE_AFTER,
                   ssl_context: ssl.SSLContext | None = None, max_lag: float | None = None,
                   routes: Routes | None = None, lanes: bool = False,
                   bulk_rate: Pacing | None = None, mptcp: bool = False) -> "Connection":
        """Open the websocket at a known robot endpoint ``ws_url`` (skips the login); the keywords are
        :meth:`login_connect`'s. Raises :class:`AuthError` or :class:`Unavailable` as :meth:`login_connect`."""
        if lanes and not allow_reconnect:
            raise ValueError("lanes need allow_reconnect: the bulk link joins the session with its token")
        reconnect = Reconnect(max_reconnect_attempts, reconnect_time_wait, max_reconnect_wait, resume_buffer,
                              timeout, endpoint_gone_after) if allow_reconnect else None
        ssl_context = ssl_context or tls.client_context()
        ws = await open_robot_link(ws_url, user_id, password, robot_id, timeout=timeout, ssl_context=ssl_context,
                                   resume=allow_reconnect, max_lag=max_lag, routes=routes, mptcp=mptcp)
        log.info("connected", user=user_id, robot=robot_id, url=ws_url, resume=allow_reconnect,
                 via=routes.relay if routes else None)
        conn = cls(ws, user_id, robot_id, ws_url, expiry, reconnect)
        conn.ssl_context, conn.max_lag, conn.routes, conn.mptcp = ssl_context, max_lag, routes, mptcp
        if lanes:
            conn.bulk = BulkLane(conn, bulk_rate)
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
        if self.bulk is not None:
            await self.bulk.close()
        await close_quietly(self.ws)
        try:
            async with asyncio.timeout(CLOSE_TIMEOUT):
                await asyncio.shield(self._reader)
        except (TimeoutError, asyncio.CancelledError):
            self._reader.cancel()
        await self._finish()

    async def _finish(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self._session_evt.set()
        if self.bulk is not None:
            await self.bulk.tasks.cancel_all()
        self.session.close(self.close_reason or "closed")
        self.session.events_received()           # call_failed/barrier_failed: their waiters have the error
        self._changed.set()
        await self.tasks.cancel_all()
        if self.routes is not None:
            await self.routes.close()
        await close_quietly(self.ws)            # a link a reconnect had just opened

    async def __aenter__(self) -> "Connection":
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    #: ``await Connection.connect(master_url, user_id, password, robot_id)`` logs in
    #: (:meth:`login_connect`); ``await conn.connect(tag_a, tag_b)`` wires two interfaces
    #: (:meth:`connect_interfaces`).
    connect = _ClassOrInstance(login_connect, Verbs.connect_interfaces)

    # -- status ------------------------------------------------------------------------------
    def on_status(self, cb: StatusCallback) -> None:
        """Call ``cb(data)`` (sync or async) for every ST: ``{"topic": "iu", "iTag", "status"}``
        or ``{"topic": "node", "cTag", "nTag", "status", ...}``."""
        self._status_cbs.append(cb)

    def on_error(self, cb: ErrorCallback) -> None:
        """Call ``cb(reason)`` (sync or async) for every ER from the cloud. With a callback the
        connection logs them at DEBUG only (the caller reports them), without one at WARNING."""
        self._error_cbs.append(cb)

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
                    raise TimeoutError
                async with asyncio.timeout(left):
                    await self._changed.wait()
            except TimeoutError:
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
            reason = close_text(ws)
        except ConnectionClosed as e:
            reason = close_text(e)
        except Exception as e:   # the reader never dies silently
            reason = f"reader failed: {type(e).__name__}: {e}"
            log.exception("client reader failed", robot=self.robot_id)
        finally:
            if ws is self.ws and not self._closed.is_set() and not self._resuming(ws, reason):
                self.close_reason = self.close_reason or reason
                if self.close_reason != "closed by the client":
                    log.info("connection closed", robot=self.robot_id, reason=self.close_reason)
                await self._finish()

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
                    self._session_evt.set()
                    if data.get("status") == "resumed":
                        self.resumes += 1
                        log.info("session resumed", robot=self.robot_id, dropped=data.get("dropped"),
                                 superseded=data.get("superseded", 0), superseded_to_cloud=self.session.superseded)
                        for cb in self._link_cbs["resumed"]:
                            self._run_cb(cb, data)
                case ResponseReceived() | BarrierPassed() | BarrierFailed() | Detached():
                    pass                                # their waiters have them (the session's pending table)
                case _:
                    unhandled(ev)
        self._kick()

    async def _session_changed(self) -> None:
        """Wait until the session's state changes (it starts, resumes, moves or closes)."""
        self._session_evt.clear()
        await self._session_evt.wait()

    def _on_error(self, reason: str) -> None:
        self.errors.append(reason)
        del self.errors[:-ERRORS_KEPT]
        if self._error_cbs:         # whoever asked to be told reports it: the error shows once
            log.debug("error from the cloud", reason=reason)
        else:
            log.warning("error from the cloud", reason=reason)
        self._changed.set()
        for cb in self._error_cbs:
            self._run_cb(cb, reason)


async def _awaited(aw: Awaitable) -> Any:
    return await aw
