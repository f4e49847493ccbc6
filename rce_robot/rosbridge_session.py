"""One rosbridge v2 client's session: the ops of RobotWebTools' rosbridge protocol
(``ROSBRIDGE_PROTOCOL.md`` of rosbridge_suite, v2.0) on one container's graph.

The session is a robot namespace of its own (robot ``robotID`` of its user): each topic the
client advertises or subscribes to, and each service it calls or provides, becomes a pair of interfaces
the master creates on the session's behalf, as a robot's CN/CX would (``robot_request``): a
container interface on the container's bus with ``addr`` = the topic or service name, and a
robot-side converter in this session, connected to it. The converters are ordinary
:class:`~rce_robot.interfaces.RobotInterface` objects; this session is their
:class:`~rce_robot.interfaces.RobotLink` and turns what they send into rosbridge ``publish``
ops (and calls from the container into ``call_service`` ops). docs/INTERNALS.md "rosbridge v2" has the table of ops.

Bad input (not JSON, an unknown op, a missing field, a message that does not fit its type, a
refused request) gets a ``status`` op with ``level: error`` naming what was wrong; the session
goes on.
"""
from __future__ import annotations

import asyncio
import json
import time
from collections import deque
from dataclasses import dataclass, field
from collections.abc import Awaitable
from typing import Any

from rce.errors import MessageError, ProtocolError, RCEError, Timeout
from rce.log import get_logger
from rce.masterlink import MasterLink
from rce.message_forms import JsonForms
from rce.tasks import Tasks
from rce_robot.interfaces import RobotInterface
from rce_robot.namespace import REQUEST_TIMEOUT
from rce_robot.rosbridge_rosapi import ROSAPI, rosapi_answer

log = get_logger("rce.rosbridge")

OUTBOX_SIZE = 256          # messages waiting for the client's websocket; past it a message is dropped (counted)
INTERFACE_UP_WAIT = 10.0   # s a new topic or service waits for its interfaces to connect before the op goes on
DESCRIBE_TIMEOUT = 15.0    # s a look-up of the container's graph (types, rosapi) waits for the master
# role -> (container interface type, robot-side interface type); the role letter starts the robot-side tag
ROLES = {"p": ("PublisherInterface", "SubscriberConverter"),      # the client advertises and publishes
         "s": ("SubscriberInterface", "PublisherConverter"),      # the client subscribes
         "c": ("ServiceClientInterface", "ServiceProviderConverter"),   # the client calls a service
         "v": ("ServiceProviderInterface", "ServiceClientConverter")}   # the client provides a service


@dataclass
class Bridge:
    """One topic or service of the container's graph reached through a pair of interfaces:
    ``itag`` (robot side, in this session) and ``ctag_itag`` (on the container's bus)."""
    role: str
    name: str
    cls: str
    itag: str
    ctag_itag: str
    up: asyncio.Event = field(default_factory=asyncio.Event)


class Subscription:
    """A client's ``subscribe`` ``sid`` to a topic: ``throttle_rate`` (ms) is the least time
    between two messages sent; messages arriving sooner wait in a queue of ``queue_length``
    (at least 1; the oldest is dropped and counted when it is full), as rosbridge does."""

    def __init__(self, sid: str, throttle_rate: float, queue_length: int):
        self.sid = sid
        self.throttle = max(0.0, throttle_rate) / 1000.0          # s
        self.pending: deque[Any] = deque(maxlen=max(1, queue_length))
        self.last = float("-inf")                                  # monotonic s of the last message sent
        self.timer: asyncio.TimerHandle | None = None
        self.dropped = 0


def _field(op: dict, name: str, kind: type = str) -> Any:
    v = op.get(name)
    if not isinstance(v, kind) or (kind is str and not v):
        raise ProtocolError(f"op {op.get('op')!r}: field {name!r} must be a non-empty {kind.__name__}, got {v!r}")
    return v


class RosbridgeSession:
    """The session of a rosbridge client as robot ``robot`` of ``user`` on container ``ctag``;
    ``master``: the control link its requests go through. What it sends the client goes to
    :attr:`outbox` (bounded: :data:`OUTBOX_SIZE`; drops counted in :attr:`dropped`).
    Implements :class:`rce_robot.interfaces.RobotLink`."""

    def __init__(self, user: str, robot: str, ctag: str, master: MasterLink):
        self.user, self.robot, self.ctag, self.master = user, robot, ctag, master
        self.forms = JsonForms()            # rosbridge's ROS 1 JSON: time and duration as {secs, nsecs}
        self.interfaces: dict[str, RobotInterface] = {}
        self.bridges: dict[tuple[str, str], Bridge] = {}          # (role, name) -> its interfaces
        self.by_itag: dict[str, Bridge] = {}
        self.subs: dict[str, dict[str, Subscription]] = {}         # topic -> subscription id -> subscription
        self.outbox: asyncio.Queue[dict] = asyncio.Queue(OUTBOX_SIZE)
        self.tasks = Tasks(f"rosbridge {user}/{robot}")
        self.ops = {"advertise": self._advertise, "unadvertise": self._unadvertise, "publish": self._publish,
                    "subscribe": self._subscribe, "unsubscribe": self._unsubscribe,
                    "call_service": self._call_service, "advertise_service": self._advertise_service,
                    "unadvertise_service": self._unadvertise_service, "service_response": self._service_response}
        self.dropped = self.errors = self._n = 0

    # -- to the client ---------------------------------------------------------------------------------
    def send(self, msg: dict) -> bool:
        """Queue ``msg`` for the client; False (counted in :attr:`dropped`) when the outbox is full."""
        try:
            self.outbox.put_nowait(msg)
        except asyncio.QueueFull:
            self.dropped += 1
            return False
        return True

    def status(self, level: str, text: str, op_id: Any = None) -> None:
        """A rosbridge ``status`` op (``level``: error, warning, info)."""
        if level == "error":
            self.errors += 1
            log.info("rosbridge status error", user=self.user, robot=self.robot, reason=text)
        msg = {"op": "status", "level": level, "msg": text}
        if op_id is not None:
            msg["id"] = op_id
        self.send(msg)

    # -- RobotLink -------------------------------------------------------------------------------------
    def add_interface(self, iface: RobotInterface) -> None:
        """Robot-side interface ``iface`` now exists (the master's ``add_interface``)."""
        self.interfaces[iface.itag] = iface

    def remove_interface(self, iface: RobotInterface) -> None:
        if self.interfaces.get(iface.itag) is iface:
            del self.interfaces[iface.itag]

    def send_dm(self, itag: str, cls: str, msg_id: Any, msg: Any, data: bool = False) -> bool:
        """A message from the container on a subscribed topic: to each subscription of it; or a
        call from the container to a service the client provides: a ``call_service`` to the client."""
        bridge = self.by_itag.get(itag)
        if bridge is not None and bridge.role == "v":
            return self.send({"op": "call_service", "id": msg_id, "service": bridge.name, "args": msg})
        if bridge is None or bridge.role != "s":
            self.dropped += 1
            return False
        for sub in list(self.subs.get(bridge.name, {}).values()):
            self._deliver(bridge.name, sub, msg)
        return True

    def send_status(self, data: dict) -> None:
        bridge = self.by_itag.get(data.get("iTag", ""))
        if data.get("topic") == "iu" and bridge is not None:
            (bridge.up.set if data.get("status") else bridge.up.clear)()

    def send_error(self, reason: str) -> None:
        self.status("error", reason)

    # -- subscriptions -----------------------------------------------------------------------------------
    def _deliver(self, topic: str, sub: Subscription, msg: Any) -> None:
        now = time.monotonic()
        if not sub.pending and now - sub.last >= sub.throttle:
            sub.last = now
            self.send({"op": "publish", "topic": topic, "msg": msg})
            return
        if len(sub.pending) == sub.pending.maxlen:
            sub.dropped += 1
            self.dropped += 1
        sub.pending.append(msg)
        if sub.timer is None:
            sub.timer = asyncio.get_running_loop().call_later(max(0.0, sub.last + sub.throttle - now),
                                                              self._flush, topic, sub)

    def _flush(self, topic: str, sub: Subscription) -> None:
        sub.timer = None
        if sub.pending and self.subs.get(topic, {}).get(sub.sid) is sub:     # not unsubscribed or replaced
            sub.last = time.monotonic()
            self.send({"op": "publish", "topic": topic, "msg": sub.pending.popleft()})
            if sub.pending:
                sub.timer = asyncio.get_running_loop().call_later(sub.throttle, self._flush, topic, sub)

    # -- from the client ---------------------------------------------------------------------------------
    async def handle(self, text: str | bytes) -> None:
        """Take one websocket message from the client; bad input gets a ``status`` error."""
        op: Any = None
        try:
            if isinstance(text, bytes):
                raise ProtocolError("binary messages are not taken (no cbor or png compression); send JSON text")
            try:
                op = json.loads(text)
            except ValueError as e:
                raise ProtocolError(f"message is not JSON: {e}") from None
            if not isinstance(op, dict):
                raise ProtocolError(f"message must be a JSON object, got {type(op).__name__}")
            handler = self.ops.get(op.get("op"))
            if handler is None:
                raise ProtocolError(f"unknown op {op.get('op')!r}; this endpoint takes {', '.join(self.ops)}")
            await handler(op)
        except RCEError as e:
            self.status("error", e.message, op.get("id") if isinstance(op, dict) else None)

    async def _advertise(self, op: dict) -> None:
        await self._bridge("p", _field(op, "topic"), _field(op, "type"))

    def _advertised(self, role: str, key: str, op: dict) -> Bridge:
        """The bridge the client advertised (``role`` p or v) under ``op[key]``; else ProtocolError."""
        bridge = self.bridges.get((role, _field(op, key)))
        if bridge is None:
            raise ProtocolError(f"{op['op']}: {key} {op[key]!r} is not advertised (advertise it first)")
        return bridge

    def _iface(self, bridge: Bridge) -> RobotInterface:
        """The converter of ``bridge``; RCEError when the master has removed it (its container went away)."""
        iface = self.interfaces.get(bridge.itag)
        if iface is None:
            raise RCEError(f"{bridge.name!r}: its interface was removed (is container {self.ctag!r} still there?)")
        return iface

    async def _unadvertise(self, op: dict) -> None:
        await self._drop(self._advertised("p", "topic", op))

    async def _publish(self, op: dict) -> None:
        self._iface(self._advertised("p", "topic", op)).from_robot({"msg": _field(op, "msg", dict)})

    async def _subscribe(self, op: dict) -> None:
        topic = _field(op, "topic")
        cls = op.get("type") or await self._type_of("topics", topic)
        compression = op.get("compression")
        if compression not in (None, "none"):
            self.status("warning", f"subscribe {topic!r}: compression {compression!r} is not supported; "
                                   "messages go as JSON", op.get("id"))
        throttle, queue = op.get("throttle_rate") or 0, op.get("queue_length") or 0
        if not isinstance(throttle, (int, float)) or not isinstance(queue, int) or throttle < 0 or queue < 0:
            raise ProtocolError(f"subscribe {topic!r}: throttle_rate (ms) and queue_length must be numbers >= 0, "
                                f"got {throttle!r}, {queue!r}")
        await self._bridge("s", topic, str(cls))
        sid = str(op.get("id") or f"subscribe:{topic}")
        self.subs.setdefault(topic, {})[sid] = Subscription(sid, float(throttle), queue)

    async def _unsubscribe(self, op: dict) -> None:
        topic = _field(op, "topic")
        subs = self.subs.get(topic, {})
        for sid in [s for s in subs if op.get("id") in (None, s)]:
            sub = subs.pop(sid)
            if sub.timer is not None:
                sub.timer.cancel()
        if not subs and ("s", topic) in self.bridges:
            self.subs.pop(topic, None)
            await self._drop(self.bridges[("s", topic)])

    async def _call_service(self, op: dict) -> None:
        service = _field(op, "service")
        args = op.get("args") or {}
        if not isinstance(args, (dict, list)):
            raise ProtocolError(f"call_service {service!r}: args must be an object, got {args!r}")
        if service in ROSAPI:
            self.tasks.spawn(self._reply(service, op.get("id"), self._rosapi(service, args)), name=service)
            return
        bridge = await self._bridge("c", service, op.get("type") or await self._type_of("services", service))
        self.tasks.spawn(self._reply(service, op.get("id"), self._call(bridge, args)), name=f"call {service}")

    async def _advertise_service(self, op: dict) -> None:
        await self._bridge("v", _field(op, "service"), _field(op, "type"))

    async def _unadvertise_service(self, op: dict) -> None:
        await self._drop(self._advertised("v", "service", op))

    async def _service_response(self, op: dict) -> None:
        """The client's answer to a call from the container (``id`` as it was sent). ``result:
        false`` fails the call: the caller gets the refusal of ``values`` as its error."""
        iface = self._iface(self._advertised("v", "service", op))
        if op.get("result", True) is not False:
            iface.from_robot({"msgID": op.get("id"), "msg": op.get("values")})
            return
        try:                       # a refusal: no response fits its class, so the call fails with that error
            iface.from_robot({"msgID": op.get("id"), "msg": None})
        except MessageError:
            pass

    async def _call(self, bridge: Bridge, args: Any) -> Any:
        return await self._iface(bridge).call_from_robot({"msg": args})

    async def _rosapi(self, service: str, args: Any) -> dict:
        return rosapi_answer(service, args, await self.describe())

    async def _reply(self, service: str, op_id: Any, values: Awaitable[Any]) -> None:
        """A ``service_response``: ``values`` awaited (``result: true``), or its error's text (false)."""
        reply: dict = {"op": "service_response", "service": service}
        if op_id is not None:
            reply["id"] = op_id
        try:
            reply.update(values=await values, result=True)
        except RCEError as e:
            reply.update(values=e.message, result=False)
        self.send(reply)

    # -- the graph through the master --------------------------------------------------------------------
    async def describe(self) -> dict:
        """The container's bus (:meth:`rce.bus.core.Bus.describe`), through the master."""
        return await self.master.call("container_bus", timeout=DESCRIBE_TIMEOUT, user=self.user, ctag=self.ctag)

    async def _type_of(self, kind: str, name: str) -> str:
        """The type of topic or service ``name`` on the container's bus (``kind``: topics, services)."""
        for entry in (await self.describe()).get(kind, []):
            if entry.get("name") == name and entry.get("type"):
                return str(entry["type"])
        raise ProtocolError(f"{kind[:-1]} {name!r} is not on container {self.ctag!r}'s graph; give its type")

    async def _request(self, type_: str, data: dict) -> None:
        await self.master.call("robot_request", timeout=REQUEST_TIMEOUT, user=self.user, robot=self.robot,
                               type=type_, data=data)

    async def _bridge(self, role: str, name: str, cls: str) -> Bridge:
        """The interfaces of ``name`` in ``role`` (:data:`ROLES`), created and connected through the
        master on first use; waits up to :data:`INTERFACE_UP_WAIT` s for them to connect."""
        bridge = self.bridges.get((role, name))
        if bridge is not None:
            if bridge.cls != cls.strip("/"):
                raise ProtocolError(f"{name!r} is already used with type {bridge.cls!r}, not {cls!r}")
            return bridge
        self._n += 1
        itag = f"{role}{self._n}"
        bridge = Bridge(role, name, cls.strip("/"), itag, f"rosbridge.{self.robot}.{itag}")
        container_type, robot_type = ROLES[role]
        self.by_itag[itag] = bridge
        try:
            await self._request("CN", {"addInterfaces": [
                {"endpointTag": self.ctag, "interfaceTag": bridge.ctag_itag, "interfaceType": container_type,
                 "className": bridge.cls, "addr": name},
                {"endpointTag": self.robot, "interfaceTag": itag, "interfaceType": robot_type,
                 "className": bridge.cls}]})
        except RCEError:
            del self.by_itag[itag]
            raise
        self.bridges[(role, name)] = bridge
        try:
            await self._request("CX", {"connect": [{"tagA": f"{self.ctag}/{bridge.ctag_itag}",
                                                    "tagB": f"{self.robot}/{itag}"}]})
            try:
                await asyncio.wait_for(bridge.up.wait(), INTERFACE_UP_WAIT)
            except asyncio.TimeoutError:
                raise Timeout(f"{name!r}: its interfaces did not connect within {INTERFACE_UP_WAIT:g} s") from None
        except RCEError:
            await self._drop_quietly(bridge)     # a later op on the name starts afresh
            raise
        return bridge

    async def _drop(self, bridge: Bridge) -> None:
        """Remove the interfaces of ``bridge`` through the master."""
        self.bridges.pop((bridge.role, bridge.name), None)
        self.by_itag.pop(bridge.itag, None)
        await self._request("CN", {"removeInterfaces": [
            {"endpointTag": self.ctag, "interfaceTag": bridge.ctag_itag},
            {"endpointTag": self.robot, "interfaceTag": bridge.itag}]})

    async def close(self) -> None:
        """End the session: its calls stop, its interfaces are removed through the master (quietly:
        the master may be away; the robot's disconnect forgets the robot-side ones anyway)."""
        await self.tasks.cancel_all()
        for subs in self.subs.values():
            for sub in subs.values():
                if sub.timer is not None:
                    sub.timer.cancel()
        for bridge in list(self.bridges.values()):
            await self._drop_quietly(bridge)

    async def _drop_quietly(self, bridge: Bridge) -> None:
        try:
            await self._drop(bridge)
        except RCEError as e:
            log.info("could not remove a rosbridge interface", name=bridge.name, reason=e.message)
