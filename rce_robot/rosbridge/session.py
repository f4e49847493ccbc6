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

ROS 2: a type named in ROS 2's form (``std_msgs/msg/String``, ``std_srvs/srv/Trigger``), as roslibpy and
roslibjs send them to rosbridge_suite's ROS 2 server, makes a ROS 2 converter: its messages are CDR inside the
engine, and its JSON has ROS 2 rosbridge's forms (time and duration ``{sec, nanosec}``, :data:`ROS2_FORMS`).
The container's end of a name takes the class the container's graph has for it when that is the same type
in the other ROS's form (``std_msgs/String`` for ``std_msgs/msg/String``): the engine converts between the
two ends (:mod:`rce.messages.convert`), so a ROS 2 client reaches ROS 1 nodes and the other way round.
Actions (``send_action_goal``, ``advertise_action``...) are :mod:`rce_robot.rosbridge.actions`.

What a subscription sends may be compressed (``png``, ``cbor``, ``cbor-raw``:
:mod:`rce_robot.rosbridge.compression`) and, as a subscription or a ``call_service`` asks with
``fragment_size``, split into ``fragment`` ops; the client's own ``fragment`` ops are reassembled
within bounds (:mod:`rce_robot.rosbridge.fragments`). The rosapi services are answered here too
(:mod:`rce_robot.rosbridge.rosapi`), parameters through the master.

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
from collections.abc import Awaitable, Callable
from typing import Any

from rce.contract import master as to_master
from rce.plumbing.errors import ProtocolError, RCEError, Timeout, Unavailable
from rce.plumbing.log import get_logger
from rce.transport.masterlink import MasterLink
from rce.interfaces.classes import is_ros2_name, same_type
from rce.interfaces.actions import call_timeout
from rce.messages.forms import JsonForms
from rce.protocol import jsontext
from rce.interfaces.lanes import Lane, interface_lane, parse_lane
from rce.protocol.limits import DEFAULT_MAX_LAG, LagGate
from rce.protocol.schema import validate
from rce.plumbing.tasks import Tasks
from rce_robot.interfaces import RobotInterface
from rce_robot.namespace import CLOSE_POLICY, LAG_LOG, REQUEST_TIMEOUT
from rce_robot.rosbridge.actions import RosbridgeActions
from rce_robot.rosbridge.compression import COMPRESSIONS, cbor_publish, cbor_raw_publish, png_op
from rce_robot.rosbridge.fragments import Defragmenter, fragment_size_of
from rce_robot.rosbridge.outbox import RosbridgeOutbox
from rce_robot.rosbridge.rosapi import ROSAPI, rosapi_answer

log = get_logger("rce.rosbridge")

INTERFACE_UP_WAIT = 10.0   # s a new topic or service waits for its interfaces to connect before the op goes on
DESCRIBE_TIMEOUT = 15.0    # s a look-up of the container's graph (types, rosapi) waits for the master
MAX_CLOSE_REASON = 120     # bytes of a close reason (a websocket close frame carries at most 123)
# role -> (container interface type, robot-side interface type); the role letter starts the robot-side tag
ROLES = {"p": ("PublisherInterface", "SubscriberConverter"),      # the client advertises and publishes
         "s": ("SubscriberInterface", "PublisherConverter"),      # the client subscribes
         "c": ("ServiceClientInterface", "ServiceProviderConverter"),   # the client calls a service
         "v": ("ServiceProviderInterface", "ServiceClientConverter")}   # the client provides a service
ROS2_FORMS = JsonForms(time="sec", duration="sec")     # rosbridge_suite's ROS 2 JSON: builtin_interfaces' own fields
OnMessage = Callable[[Any], None]                      # a bridge's own taker of its topic's messages (JSON)
OnCall = Callable[[Any, Any], None]                    # a bridge's own taker of the container's calls (msgID, request)


@dataclass
class Bridge:
    """One topic or service of the container's graph reached through a pair of interfaces:
    ``itag`` (robot side, in this session, of class ``cls``, the client's) and ``ctag_itag`` (on the
    container's bus, of class ``container_cls``: the graph's, see the module docstring). ``on_message`` /
    ``on_call``: what takes its topic's messages / the container's calls instead of the client's
    subscriptions / a ``call_service`` op to the client (an action's parts, :mod:`rce_robot.rosbridge.actions`)."""
    role: str
    name: str
    cls: str
    itag: str
    ctag_itag: str
    lane: Lane = Lane.STATE           # what its topic data to the client goes in (docs/lanes.md)
    up: asyncio.Event = field(default_factory=asyncio.Event)
    container_cls: str = ""
    on_message: OnMessage | None = None
    on_call: OnCall | None = None


class Ros2Link:
    """A session as its ROS 2 converters see it (:class:`rce_robot.interfaces.RobotLink`): the session itself,
    with JSON in ROS 2 rosbridge's forms (:data:`ROS2_FORMS`) instead of the session's ROS 1 ones."""
    forms = ROS2_FORMS

    def __init__(self, session: "RosbridgeSession"):
        self.session = session

    def __getattr__(self, name: str) -> Any:
        return getattr(self.session, name)


class RosbridgeSubscription:
    """A client's ``subscribe`` ``sid`` to a topic: ``throttle_rate`` (ms) is the least time
    between two messages sent; messages arriving sooner wait in a queue of ``queue_length``
    (at least 1; the oldest is dropped and counted when it is full), as rosbridge does. Each
    message goes with ``compression`` (:data:`~rce_robot.rosbridge.compression.COMPRESSIONS`),
    in fragments of ``fragment_size`` characters (None: whole)."""

    def __init__(self, sid: str, throttle_rate: float, queue_length: int, fragment_size: int | None = None,
                 compression: str = "none"):
        self.sid, self.fragment_size, self.compression = sid, fragment_size, compression
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


def _lane(op: dict) -> Lane | None:
    """The op's ``lane`` field (an rce extension: ``control``, ``state`` or ``bulk``), None when absent.
    Raises :class:`ProtocolError` naming the op for another value."""
    v = op.get("lane")
    return None if v is None else parse_lane(v, f"op {op.get('op')!r}: field 'lane'")


class RosbridgeSession:
    """The session of a rosbridge client as robot ``robot`` of ``user`` on container ``ctag``;
    ``master``: the control link its requests go through. What it sends the client goes to
    :attr:`outbox` (the RCE session's policy: each subscription keeps its newest, drops counted;
    :class:`~rce_robot.rosbridge.outbox.RosbridgeOutbox`); the
    client's ``fragment`` ops are reassembled by :attr:`defrag` (bounded). While the endpoint has
    been behind the client for longer than ``max_lag`` s (:meth:`backlog`), its ``publish`` ops are
    shed as a robot's topic DMs are (:class:`~rce.protocol.limits.LagGate`), and the client is told
    with a ``status`` op (warning when shedding starts, info when it ends). Implements
    :class:`rce_robot.interfaces.RobotLink` and :class:`rce_robot.rosbridge.rosapi.Graph`."""

    def __init__(self, user: str, robot: str, ctag: str, master: MasterLink, max_lag: float | None = DEFAULT_MAX_LAG):
        self.user, self.robot, self.ctag, self.master = user, robot, ctag, master
        self.lag = LagGate(max_lag)         # sheds the client's publish ops while the endpoint lags (backlog)
        self._now = 0.0                     # monotonic s of the op being handled (backlog)
        self.forms = JsonForms()            # rosbridge's ROS 1 JSON: time and duration as {secs, nsecs}
        self.interfaces: dict[str, RobotInterface] = {}
        self.bridges: dict[tuple[str, str], Bridge] = {}          # (role, name) -> its interfaces
        self.by_itag: dict[str, Bridge] = {}
        self.subs: dict[str, dict[str, RosbridgeSubscription]] = {}         # topic -> subscription id -> subscription
        self.outbox = RosbridgeOutbox(max_lag=max_lag)
        self.defrag = Defragmenter()
        self.tasks = Tasks(f"rosbridge {user}/{robot}")
        self.ops = {"advertise": self._advertise, "unadvertise": self._unadvertise, "publish": self._publish,
                    "subscribe": self._subscribe, "unsubscribe": self._unsubscribe,
                    "call_service": self._call_service, "advertise_service": self._advertise_service,
                    "unadvertise_service": self._unadvertise_service, "service_response": self._service_response}
        self.actions = RosbridgeActions(self)
        self.ops.update(self.actions.ops)
        self.ops_in = self.errors = self.queue_dropped = self._n = 0
        self.closing: asyncio.Task | None = None     # closing a client that does not read
        self.ws: Any = None                 # the client's websocket (set by the server)

    @property
    def dropped(self) -> int:
        """Messages to the client dropped: by the outbox (a subscription's oldest past the bound, or
        older than ``max_lag``), a full throttle queue."""
        return self.outbox.dropped + self.queue_dropped

    def stats(self) -> dict[str, int]:
        """The session's counters (``rce_robot.rosbridge.endpoint.SESSION_COUNTERS`` names them)."""
        return {"ops_in": self.ops_in, "errors": self.errors, "msgs_out": self.outbox.sent, "dropped": self.dropped,
                "shed": self.lag.shed,
                "fragments_out": self.outbox.fragments, "fragments_in": self.defrag.fragments,
                "fragments_dropped": self.defrag.dropped}

    # -- to the client ---------------------------------------------------------------------------------
    def send(self, msg: dict, fragment_size: int | None = None, key: Any = None, lane: Lane = Lane.STATE) -> bool:
        """Queue ``msg`` for the client (in fragments of ``fragment_size`` characters when longer);
        ``key``: the subscription whose topic data it is (its newest are kept) in ``lane``, None for an op
        never dropped (control). A client that lets too many ops wait does not read: it is closed (1008).
        Returns True."""
        return self._queued(self.outbox.op(msg, fragment_size, key, lane))

    def _queued(self, ok: bool) -> bool:
        if self.outbox.overrun is not None and self.closing is None:
            log.warning("closing a rosbridge client that does not read", user=self.user, robot=self.robot,
                        reason=self.outbox.overrun)
            self.closing = self.tasks.spawn(self.close(self.outbox.overrun), name="close")
        return ok

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
        """Robot-side interface ``iface`` now exists (the master's ``add_interface``). A ROS 2 one speaks ROS 2
        rosbridge's JSON (:class:`Ros2Link`); an action's ``get_result`` that the client serves waits as long as
        the goal runs (:func:`rce.interfaces.actions.call_timeout`)."""
        self.interfaces[iface.itag] = iface
        if is_ros2_name(iface.cls):
            iface.link = Ros2Link(self)
            iface.robot_call_timeout = max(iface.robot_call_timeout, call_timeout(iface.cls))

    def remove_interface(self, iface: RobotInterface) -> None:
        if self.interfaces.get(iface.itag) is iface:
            del self.interfaces[iface.itag]

    def owns(self, iface: RobotInterface) -> bool:
        """Is ``iface`` one of this session's converters?"""
        return iface.link is self or getattr(iface.link, "session", None) is self

    def battery_seen(self, percent: float) -> None:
        """A rosbridge client's ``BatteryState`` says nothing of a robot's link: not reported to the placer."""

    def send_dm(self, itag: str, cls: str, msg_id: Any, msg: Any, data: bool = False) -> bool:
        """A message from the container on a subscribed topic: to each subscription of it; or a
        call from the container to a service the client provides: a ``call_service`` to the client."""
        bridge = self.by_itag.get(itag)
        if bridge is not None and bridge.role == "v":
            if bridge.on_call is not None:
                bridge.on_call(msg_id, msg)
                return True
            return self.send({"op": "call_service", "id": msg_id, "service": bridge.name, "args": msg})
        if bridge is None or bridge.role != "s":
            self.queue_dropped += 1
            return False
        if bridge.on_message is not None:
            bridge.on_message(msg)
            return True
        for sub in list(self.subs.get(bridge.name, {}).values()):
            self._deliver(bridge, sub, msg)
        return True

    def send_status(self, data: dict) -> None:
        bridge = self.by_itag.get(data.get("iTag", ""))
        if data.get("topic") == "iu" and bridge is not None:
            (bridge.up.set if data.get("status") else bridge.up.clear)()

    def send_error(self, reason: str) -> None:
        self.status("error", reason)

    # -- subscriptions -----------------------------------------------------------------------------------
    def _deliver(self, bridge: Bridge, sub: RosbridgeSubscription, msg: Any) -> None:
        now = time.monotonic()
        if not sub.pending and now - sub.last >= sub.throttle:
            sub.last = now
            self._publish_to(bridge, sub, msg)
            return
        if len(sub.pending) == sub.pending.maxlen:
            sub.dropped += 1
            self.queue_dropped += 1
        sub.pending.append(msg)
        if sub.timer is None:
            sub.timer = asyncio.get_running_loop().call_later(max(0.0, sub.last + sub.throttle - now),
                                                              self._flush, bridge, sub)

    def _flush(self, bridge: Bridge, sub: RosbridgeSubscription) -> None:
        sub.timer = None
        if sub.pending and self.subs.get(bridge.name, {}).get(sub.sid) is sub:     # not unsubscribed or replaced
            sub.last = time.monotonic()
            self._publish_to(bridge, sub, sub.pending.popleft())
            if sub.pending:
                sub.timer = asyncio.get_running_loop().call_later(sub.throttle, self._flush, bridge, sub)

    def _publish_to(self, bridge: Bridge, sub: RosbridgeSubscription, msg: Any) -> None:
        """One ``publish`` op for ``sub``, compressed and fragmented as it asked."""
        op = {"op": "publish", "topic": bridge.name, "msg": msg}
        key = (bridge.name, sub.sid)                # topic data: each subscription keeps its newest
        if sub.compression in ("cbor", "cbor-raw"):
            iface = self.interfaces.get(bridge.itag)
            if iface is None:
                self.queue_dropped += 1
                return
            if sub.compression == "cbor":
                self.outbox.put([cbor_publish(iface.registry, iface.msg_t, bridge.name, msg)], key, bridge.lane)
            else:
                self.outbox.put([cbor_raw_publish(iface.registry, iface.msg_t, bridge.name, msg, time.time())], key,
                                bridge.lane)
            return
        self.send(png_op(jsontext.dumps(op)) if sub.compression == "png" else op, sub.fragment_size, key,
                  bridge.lane)

    # -- from the client ---------------------------------------------------------------------------------
    def backlog(self, waiting: int, now: float) -> None:
        """Before each message the server takes: ``waiting`` more of the client's (frames, else
        bytes) are behind it, at ``now`` (monotonic s)."""
        self._now = now
        shed = self.lag.backlog(waiting, now)
        if shed:
            log.debug("the endpoint caught up with the rosbridge client", user=self.user, robot=self.robot, shed=shed)
            self.status("info", f"the endpoint caught up with this client; {shed} publish ops were shed meanwhile")

    async def handle(self, text: str | bytes) -> None:
        """Take one websocket message from the client; bad input gets a ``status`` error."""
        op: Any = None
        try:
            for mid in self.defrag.expire():
                self.status("warning", f"fragmented message {mid!r} expired before its last fragment came")
            op = self._parse(text)
            if op.get("op") == "fragment":
                whole = self.defrag.add(op)
                if whole is None:
                    return
                op = self._parse(whole)
                if op.get("op") == "fragment":
                    raise ProtocolError("a reassembled message must not be a fragment itself")
            self.ops_in += 1
            handler = self.ops.get(op.get("op"))
            if handler is None:
                raise ProtocolError(f"unknown op {op.get('op')!r}; this endpoint takes {', '.join(self.ops)}, "
                                    "fragment")
            await handler(op)
        except RCEError as e:
            self.status("error", e.message, op.get("id") if isinstance(op, dict) else None)

    @staticmethod
    def _parse(text: str | bytes) -> dict:
        if isinstance(text, bytes):
            raise ProtocolError("binary messages are not taken (rosbridge takes JSON text from clients; cbor "
                                "is only sent); send JSON text")
        try:
            op = jsontext.loads(text)
        except (ValueError, RecursionError) as e:
            raise ProtocolError(f"message is not JSON: {e}") from None
        if not isinstance(op, dict):
            raise ProtocolError(f"message must be a JSON object, got {type(op).__name__}")
        return op

    async def _advertise(self, op: dict) -> None:
        await self._bridge("p", _field(op, "topic"), _field(op, "type"), _lane(op))

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
        iface = self._iface(self._advertised("p", "topic", op))
        msg = _field(op, "msg", dict)
        if not self.lag.admit(op["topic"], self._now):
            if self.lag.episode == 1:
                behind = round(self.lag.behind(self._now), 3)
                self.status("warning", f"the endpoint has been {behind:g} s behind this client (more than max_lag, "
                                       f"{self.lag.max_lag:g} s): its publish ops are shed until it catches up")
                if LAG_LOG.take(self._now):
                    log.warning("the endpoint lags behind the rosbridge client: its publish ops are shed until it "
                                "catches up", user=self.user, robot=self.robot, behind_s=behind)
            return
        iface.from_robot({"msg": msg})

    async def _subscribe(self, op: dict) -> None:
        topic = _field(op, "topic")
        compression = op.get("compression") or "none"
        if compression not in COMPRESSIONS:
            raise ProtocolError(f"subscribe {topic!r}: compression must be one of {', '.join(COMPRESSIONS)}, "
                                f"got {compression!r}")
        throttle, queue = op.get("throttle_rate") or 0, op.get("queue_length") or 0
        if not isinstance(throttle, (int, float)) or not isinstance(queue, int) or throttle < 0 or queue < 0:
            raise ProtocolError(f"subscribe {topic!r}: throttle_rate (ms) and queue_length must be numbers >= 0, "
                                f"got {throttle!r}, {queue!r}")
        size = fragment_size_of(op)
        cls = op.get("type") or await self._type_of("topics", topic)
        await self._bridge("s", topic, str(cls), _lane(op))
        sid = str(op.get("id") or f"subscribe:{topic}")
        self.subs.setdefault(topic, {})[sid] = RosbridgeSubscription(sid, float(throttle), queue, size, compression)

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
        size = fragment_size_of(op)
        if service in ROSAPI:
            self.tasks.spawn(self._reply(service, op.get("id"), rosapi_answer(service, args, self), size),
                             name=service)
            return
        bridge = await self._bridge("c", service, op.get("type") or await self._type_of("services", service), _lane(op))
        self.tasks.spawn(self._reply(service, op.get("id"), self._call(bridge, args), size), name=f"call {service}")

    async def _advertise_service(self, op: dict) -> None:
        await self._bridge("v", _field(op, "service"), _field(op, "type"), _lane(op))

    async def _unadvertise_service(self, op: dict) -> None:
        await self._drop(self._advertised("v", "service", op))

    async def _service_response(self, op: dict) -> None:
        """The client's answer to a call from the container (``id`` as it was sent). ``result:
        false`` fails the call: the caller gets ``values`` (text, or its JSON) as the reason."""
        iface = self._iface(self._advertised("v", "service", op))
        if op.get("result", True) is not False:
            iface.from_robot({"msgID": op.get("id"), "msg": op.get("values")})
            return
        values = op.get("values")
        iface.fail_robot_call(op.get("id"), values if isinstance(values, str) else json.dumps(values))

    async def _call(self, bridge: Bridge, args: Any) -> Any:
        return await self._iface(bridge).call_from_robot({"msg": args})

    async def _reply(self, service: str, op_id: Any, values: Awaitable[Any], fragment_size: int | None) -> None:
        """A ``service_response``: ``values`` awaited (``result: true``), or its error's text (false)."""
        reply: dict = {"op": "service_response", "service": service}
        if op_id is not None:
            reply["id"] = op_id
        try:
            reply.update(values=await values, result=True)
        except RCEError as e:
            reply.update(values=e.message, result=False)
        self.send(reply, fragment_size)

    # -- the graph through the master --------------------------------------------------------------------
    async def describe(self) -> dict:
        """The container's bus (:meth:`rce.bus.core.Bus.describe`), through the master."""
        return await self.master.ask(to_master.ContainerBus(user=self.user, ctag=self.ctag), DESCRIBE_TIMEOUT)

    async def get_param(self, name: str) -> Any:
        """Parameter ``name`` (global) of the container's bus, through the master; NotFound if not set."""
        answer = await self.master.ask(to_master.ContainerParam(user=self.user, ctag=self.ctag, name=name),
                                       DESCRIBE_TIMEOUT)
        return answer.get("value")

    async def set_param(self, name: str, value: Any) -> None:
        """Set parameter ``name`` (global) to ``value`` (JSON), as the robot's CN ``setParam``."""
        await self._request("CN", {"setParam": [{"containerTag": self.ctag, "name": name, "value": value}]})

    async def delete_param(self, name: str) -> None:
        """Delete parameter ``name``, as the robot's CN ``deleteParam`` (NotFound unless the master has it)."""
        await self._request("CN", {"deleteParam": [{"containerTag": self.ctag, "name": name}]})

    async def _type_of(self, kind: str, name: str) -> str:
        """The type of topic or service ``name`` on the container's bus (``kind``: topics, services)."""
        for entry in (await self.describe()).get(kind, []):
            if entry.get("name") == name and entry.get("type"):
                return str(entry["type"])
        raise ProtocolError(f"{kind[:-1]} {name!r} is not on container {self.ctag!r}'s graph; give its type")

    async def _graph_class(self, role: str, name: str, cls: str) -> str:
        """The class the container's end of ``name`` (a topic, or a service for roles c and v) takes: the one
        the container's graph has for it where that is ``cls``'s type in the other ROS's form (the engine
        converts between the two ends); else ``cls``."""
        kind = "services" if role in ("c", "v") else "topics"
        for entry in (await self.describe()).get(kind, []):
            graph_cls = entry.get("type")
            if entry.get("name") == name and isinstance(graph_cls, str) and graph_cls.strip("/") != cls \
                    and same_type(graph_cls, cls):
                return graph_cls.strip("/")
        return cls

    async def _request(self, type_: str, data: dict) -> None:
        """Send a CN/CX built from the client's ops to the master, through the same schema check a
        robot's own requests meet (:func:`rce.protocol.schema.validate`: names, types, tags)."""
        _, request = validate({"type": type_, "data": data})
        await self.master.ask(to_master.RobotRequest(user=self.user, robot=self.robot, type=type_,
                                                     data=request.wire()), REQUEST_TIMEOUT)

    async def _bridge(self, role: str, name: str, cls: str, lane: Lane | None = None, *,
                      on_message: OnMessage | None = None, on_call: OnCall | None = None) -> Bridge:
        """The interfaces of ``name`` in ``role`` (:data:`ROLES`), created and connected through the
        master on first use (``lane``: the robot-side interface's, :mod:`rce.interfaces.lanes`; None: from
        ``cls``; the first op on a name sets it; ``on_message``, ``on_call``: :class:`Bridge`'s); waits up to
        :data:`INTERFACE_UP_WAIT` s for them to connect."""
        bridge = self.bridges.get((role, name))
        if bridge is not None:
            if bridge.cls != cls.strip("/"):
                raise ProtocolError(f"{name!r} is already used with type {bridge.cls!r}, not {cls!r}")
            return bridge
        self._n += 1
        itag = f"{role}{self._n}"
        bridge = Bridge(role, name, cls.strip("/"), itag, f"rosbridge.{self.robot}.{itag}",
                        interface_lane(cls, role in ("c", "v"), lane), on_message=on_message, on_call=on_call)
        container_type, robot_type = ROLES[role]
        self.by_itag[itag] = bridge
        try:
            bridge.container_cls = await self._graph_class(role, name, bridge.cls)
            await self._request("CN", {"addInterfaces": [
                {"endpointTag": self.ctag, "interfaceTag": bridge.ctag_itag, "interfaceType": container_type,
                 "className": bridge.container_cls, "addr": name},
                {"endpointTag": self.robot, "interfaceTag": itag, "interfaceType": robot_type,
                 "className": bridge.cls, **({"lane": lane.value} if lane else {})}]})
        except RCEError:
            del self.by_itag[itag]
            raise
        self.bridges[(role, name)] = bridge
        try:
            await self._request("CX", {"connect": [{"tagA": f"{self.ctag}/{bridge.ctag_itag}",
                                                    "tagB": f"{self.robot}/{itag}"}]})
            try:
                async with asyncio.timeout(INTERFACE_UP_WAIT):
                    await bridge.up.wait()
            except TimeoutError:
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

    async def close(self, reason: str | None = None) -> None:
        """End the session: its calls stop, its interfaces are removed through the master (quietly:
        the master may be away; the robot's disconnect forgets the robot-side ones anyway). With
        ``reason`` (the master closes the robot) the websocket closes with it (1008), and the
        server's end of the session does the rest."""
        if reason is not None and self.ws is not None:
            await self.ws.close(CLOSE_POLICY, reason.encode()[:MAX_CLOSE_REASON].decode(errors="ignore"))
            return
        await self.tasks.cancel_all()
        self.actions.close()
        for subs in self.subs.values():
            for sub in subs.values():
                if sub.timer is not None:
                    sub.timer.cancel()
        bridges = list(self.bridges.values())
        for i, bridge in enumerate(bridges):
            if not self.master.available or not await self._drop_quietly(bridge):
                log.info("the master is away: the session's other interfaces are left to its disconnect",
                         robot=self.robot, left=len(bridges) - i - 1)
                break

    async def _drop_quietly(self, bridge: Bridge) -> bool:
        """:meth:`_drop`, its error logged; False when the master is away or silent (later ones would wait too)."""
        try:
            await self._drop(bridge)
        except (Unavailable, Timeout) as e:
            log.info("could not remove a rosbridge interface", name=bridge.name, reason=e.message)
            return False
        except RCEError as e:
            log.info("could not remove a rosbridge interface", name=bridge.name, reason=e.message)
        return True
