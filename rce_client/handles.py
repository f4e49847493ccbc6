"""The typed endpoints of a client connection, bound to the robot's own (robot-side) interfaces,
named on the side where they act (docs/INTERNALS.md), and the routing of the cloud's DMs to them:

=========================================  ============================================
robot-side interface (eTag = robotID)      client endpoint
=========================================  ============================================
``SubscriberConverter/Forwarder``          :meth:`Handles.publisher` (robot -> cloud)
``PublisherConverter/Forwarder``           :meth:`Handles.subscriber` (cloud -> robot)
``ServiceProviderConverter/Forwarder``     :meth:`Handles.service` (robot calls the cloud)
``ServiceClientConverter/Forwarder``       :meth:`Handles.service_provider` (cloud calls the robot)
=========================================  ============================================

A Converter carries messages as JSON objects (:mod:`rce.messages` JSON form); a Forwarder carries
ROS 1 serialized bytes as the binary part ``msg*``. Either way a ``bytes`` message is sent as a
binary part and a received binary part arrives as ``bytes``.
"""
from __future__ import annotations

import inspect
from typing import Any, Callable, Protocol

from rce.protocol import frames
from rce.plumbing.errors import RCEError, Timeout
from rce.plumbing.log import get_logger
from rce.protocol.events import MessageReceived
from rce.interfaces.lanes import Lane, interface_lane, message_lane
from rce.protocol.session import ClientSession
from rce.plumbing.tasks import Tasks

log = get_logger("rce.client")

DEFAULT_CALL_TIMEOUT = 30.0      # s a service call waits for the cloud's response

Message = dict | bytes            # JSON-form message (Converter) or serialized bytes (Forwarder)


class ConnectionLike(Protocol):
    """What an endpoint uses of its :class:`~rce_client.connection.Connection`."""

    session: ClientSession
    bulk: Any                  # rce_client.lanes.BulkLane | None
    _handlers: dict[str, Any]

    async def send(self, type_: str, data: Any, newest_of: str | None = None) -> None:
        """Send one message (:meth:`rce_client.verbs.Verbs.send`)."""

    async def _write(self) -> None:
        """Write what the session has to send."""


class Publisher:
    """Sends messages to a robot-side ``SubscriberConverter``/``SubscriberForwarder``; ``lane``: the lane the
    interface was given (docs/lanes.md; None: from ``cls``)."""

    def __init__(self, conn: ConnectionLike, itag: str, cls: str, lane: str | Lane | None = None):
        self.conn, self.itag, self.cls = conn, itag, cls
        self.lane, self.lane_set = interface_lane(cls, False, lane), lane is not None
        self.sent = 0

    async def publish(self, msg: Message) -> None:
        """Send one message: a JSON-form dict (Converter) or ROS 1 serialized bytes
        (Forwarder; sent as binary part ``msg*``). A bulk message goes on the connection's bulk link while it
        is up (queued: each interface keeps its newest), else on the session's link; there, while no link is
        up, a state or bulk message supersedes the interface's older one (a control one waits with every
        other). Raises :class:`Unavailable` when closed."""
        bulk = self.conn.bulk
        size = len(msg) if isinstance(msg, (bytes, bytearray, memoryview)) else 0
        lane = message_lane(self.lane, self.lane_set, size)
        if bulk is not None and bulk.up and lane is Lane.BULK:
            bulk.put(self.itag, self.cls, msg)
        else:
            await self.conn.send(frames.DM, {"iTag": self.itag, "type": self.cls, "msg": msg},
                                 newest_of=None if lane is Lane.CONTROL else self.itag)
        self.sent += 1


class Subscriber:
    """Receives messages from a robot-side ``PublisherConverter``/``PublisherForwarder``:
    ``callback(msg)`` (sync or async) gets a dict (Converter) or bytes (Forwarder)."""

    def __init__(self, conn: ConnectionLike, itag: str, cls: str, callback: Callable[[Message], Any]):
        self.conn, self.itag, self.cls, self.callback = conn, itag, cls, callback
        self.received = 0

    def close(self) -> None:
        """Stop receiving (later DMs for this iTag are logged as unhandled)."""
        if self.conn._handlers.get(self.itag) is self:
            del self.conn._handlers[self.itag]


class ServiceClient:
    """Calls the cloud through a robot-side ``ServiceProviderConverter``/``ServiceProviderForwarder``."""

    def __init__(self, conn: ConnectionLike, itag: str, srv_cls: str):
        self.conn, self.itag, self.srv_cls = conn, itag, srv_cls
        self.calls = 0

    async def call(self, request: Message | None = None, timeout: float | None = DEFAULT_CALL_TIMEOUT) -> Message:
        """Send ``DM {iTag, type, msgID, msg: request}`` with a fresh msgID and return the ``msg``
        of the response DM with the same msgID (dict for a Converter, bytes for a Forwarder).

        Raises :class:`rce.plumbing.errors.Timeout` (a :class:`TimeoutError`) after ``timeout`` s (None: no
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

    def __init__(self, conn: ConnectionLike, itag: str, srv_cls: str, handler: Callable[[Message], Any]):
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
        await self.conn.send(frames.DM, out)


class Handles:
    """The typed endpoints of a :class:`~rce_client.connection.Connection` (mixed into it): one handler
    per iTag in :attr:`_handlers`; :attr:`unhandled` counts DMs for an iTag with no handler."""

    _handlers: dict[str, Subscriber | ServiceProvider]
    unhandled: int
    tasks: Tasks
    _run_cb: Callable[[Callable, Any], None]

    def publisher(self, itag: str, cls: str, lane: str | Lane | None = None) -> Publisher:
        """Bind to robot-side ``SubscriberConverter``/``Forwarder`` ``itag`` of message class ``cls``; ``lane``:
        as the interface was given (None: from ``cls``). Raises ProtocolError for an unknown lane."""
        return Publisher(self, itag, cls, lane)

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
