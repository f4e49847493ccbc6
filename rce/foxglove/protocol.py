"""The Foxglove WebSocket protocol (subprotocol ``foxglove.websocket.v1``), server side, sans I/O.

The protocol is Foxglove's (github.com/foxglove/ws-protocol, ``docs/spec.md``; the message shapes
are those of ``@foxglove/ws-protocol``'s ``types.ts``): JSON text messages with an ``op``, and
binary messages whose first byte is an opcode, little-endian integers after it.

Server -> client: ``serverInfo``, ``status`` (level 0 info, 1 warning, 2 error), ``advertise`` and
``unadvertise`` (channels), ``advertiseServices``, binary ``MESSAGE_DATA`` (opcode 1: subscription id
u32, receive time u64 ns, payload) and ``SERVICE_CALL_RESPONSE`` (3: service id u32, call id u32,
encoding length u32, encoding, payload), ``serviceCallFailure``.

Client -> server: ``subscribe``, ``unsubscribe``, ``advertise`` and ``unadvertise`` (client channels,
for ``clientPublish``), binary ``MESSAGE_DATA`` (opcode 1: client channel id u32, payload) and
``SERVICE_CALL_REQUEST`` (2: as the response).

:class:`ClientState` is one client's state: its subscriptions and its channels. It takes the client's
messages (:meth:`~ClientState.receive_text`, :meth:`~ClientState.receive_binary`) and returns typed
events; what breaks the protocol or a bound is a :class:`Problem` event, which the shell answers with a
``status`` error, and nothing else of the client's or any other client's state changes. The builders
(:func:`server_info`, :func:`status`, :func:`message_data`, ...) make the server's messages.

rce's channels carry a ROS 1 type's messages as ``ros1`` with a ``ros1msg`` schema, the full message definition as
a ROS 1 bag stores it (the class's text, then each type it uses after a line of ``=``), as rosbags'
``generate_msgdef`` writes it (:func:`ros1_schema`); a ROS 2 type's (``pkg/msg/T``) as ``cdr`` with a ``ros2msg``
schema, the same layout of ROS 2 ``.msg`` texts (:func:`ros2_schema`): the well-known encodings of MCAP's registry
(https://mcap.dev/spec/registry), which Foxglove's ROS 2 bridge uses too. A service of a ROS 2 type is advertised
with ``cdr`` and ``ros2msg`` (:class:`FoxgloveService`). Which encodings a client may publish and call services in
is the server's choice (``ClientState.encodings``; :data:`CLIENT_ENCODINGS` by default).
"""
from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import orjson

from rce.interfaces.classes import is_ros2_name

SUBPROTOCOL = "foxglove.websocket.v1"
INFO, WARNING, ERROR = 0, 1, 2                      # status levels
MESSAGE_DATA, TIME, SERVICE_CALL_RESPONSE = 1, 2, 3  # server binary opcodes
CLIENT_MESSAGE_DATA, SERVICE_CALL_REQUEST = 1, 2     # client binary opcodes
ROS1, ROS1MSG, JSON = "ros1", "ros1msg", "json"
CDR, ROS2MSG = "cdr", "ros2msg"                      # ROS 2's message and schema encodings (MCAP's registry)
CLIENT_ENCODINGS = (ROS1, JSON)                     # what clients may publish and call services in (default)
ALL_CLIENT_ENCODINGS = (ROS1, CDR, JSON)            # ... on a server that takes ROS 2's CDR too
SCHEMA_SEPARATOR = "=" * 80                         # between the definitions of a ros1msg / ros2msg schema

MAX_SUBSCRIPTIONS = 1024        # subscriptions one client may hold
MAX_CLIENT_CHANNELS = 256       # channels one client may advertise
MAX_CLIENT_PAYLOAD = 4 << 20    # bytes of one message a client publishes or one service request (4 MiB)
MAX_TEXT = 1 << 20              # bytes of one JSON message from a client (1 MiB)
MAX_IDS = 4096                  # entries of one subscribe/unsubscribe/advertise list
MAX_TOPIC = 256                 # characters of a topic or schema name
U32 = 0xFFFFFFFF

_DATA_HEADER = struct.Struct("<BIQ")
_CALL_HEADER = struct.Struct("<BIII")


@dataclass(frozen=True)
class Channel:
    """A server channel: ``id`` (u32), ``topic``, message ``encoding``, ``schema_name`` (``pkg/Name``),
    ``schema`` (its definition text) and ``schema_encoding``."""
    id: int
    topic: str
    schema_name: str
    schema: str
    encoding: str = ROS1
    schema_encoding: str = ROS1MSG

    def to_json(self) -> dict:
        """The channel as ``advertise`` lists it."""
        return {"id": self.id, "topic": self.topic, "encoding": self.encoding, "schemaName": self.schema_name,
                "schema": self.schema, "schemaEncoding": self.schema_encoding}


@dataclass(frozen=True)
class FoxgloveService:
    """A server service: ``id`` (u32), ``name``, ``type`` (``pkg/Name``; a ROS 2 type ``pkg/srv/Name``), the
    request's and response's definitions (``ros1msg`` text; ``ros2msg`` for a ROS 2 type)."""
    id: int
    name: str
    type: str
    request_schema: str
    response_schema: str

    @property
    def encodings(self) -> tuple[str, str]:
        """(message encoding, schema encoding): ``cdr``, ``ros2msg`` for a ROS 2 type, else ``ros1``, ``ros1msg``."""
        return (CDR, ROS2MSG) if is_ros2_name(self.type) else (ROS1, ROS1MSG)

    def to_json(self) -> dict:
        """The service as ``advertiseServices`` lists it (with the deprecated ``requestSchema`` and
        ``responseSchema`` too, for older clients)."""
        encoding, schema_encoding = self.encodings
        req = {"encoding": encoding, "schemaName": f"{self.type}_Request", "schemaEncoding": schema_encoding,
               "schema": self.request_schema}
        resp = {**req, "schemaName": f"{self.type}_Response", "schema": self.response_schema}
        return {"id": self.id, "name": self.name, "type": self.type, "request": req, "response": resp,
                "requestSchema": self.request_schema, "responseSchema": self.response_schema}


@dataclass(frozen=True)
class ClientChannel:
    """A channel a client advertised for publishing: ``id`` (the client's u32), ``topic``, ``encoding``
    (one of its server's client encodings, :attr:`ClientState.encodings`), ``schema_name``."""
    id: int
    topic: str
    encoding: str
    schema_name: str


# -- events ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Subscribed:
    """The client subscribed to ``channel_id`` as ``subscription_id`` (the shell may send it a latched message)."""
    subscription_id: int
    channel_id: int


@dataclass(frozen=True)
class Unsubscribed:
    """The client ended ``subscription_id`` (on ``channel_id``)."""
    subscription_id: int
    channel_id: int


@dataclass(frozen=True)
class Advertised:
    """The client advertised ``channel`` to publish on."""
    channel: ClientChannel


@dataclass(frozen=True)
class Unadvertised:
    """The client withdrew ``channel``."""
    channel: ClientChannel


@dataclass(frozen=True)
class Published:
    """The client published ``payload`` (in ``channel.encoding``) on ``channel``."""
    channel: ClientChannel
    payload: bytes


@dataclass(frozen=True)
class ServiceCalled:
    """The client called ``service_id`` (call ``call_id``) with ``payload`` in ``encoding``."""
    service_id: int
    call_id: int
    encoding: str
    payload: bytes


@dataclass(frozen=True)
class Problem:
    """What the client sent breaks the protocol or a bound: answer with a ``status`` error of ``message``."""
    message: str
    level: int = ERROR


Event = Subscribed | Unsubscribed | Advertised | Unadvertised | Published | ServiceCalled | Problem


# -- one client's state ------------------------------------------------------------------------------------
@dataclass
class ClientState:
    """One client's subscriptions and advertised channels, against the server's ``channels`` and
    ``services`` (id -> :class:`Channel` / :class:`FoxgloveService`, read at each message, never changed here).

    Each subscribe, unsubscribe, advertise or unadvertise entry is taken or refused on its own: the
    good entries of a message with a bad one still count. ``encodings``: what the client may publish and call
    services in (the server's ``supportedEncodings``)."""
    channels: Mapping[int, Channel]
    services: Mapping[int, FoxgloveService] = field(default_factory=dict)
    client_publish: bool = True
    encodings: tuple[str, ...] = CLIENT_ENCODINGS
    subscriptions: dict[int, int] = field(default_factory=dict)      # subscription id -> channel id
    by_channel: dict[int, int] = field(default_factory=dict)         # channel id -> subscription id
    client_channels: dict[int, ClientChannel] = field(default_factory=dict)

    def receive_text(self, text: str) -> list[Event]:
        """Events of one JSON message (``subscribe``, ``unsubscribe``, ``advertise``, ``unadvertise``)."""
        if len(text) > MAX_TEXT:
            return [Problem(f"JSON message of {len(text)} characters is over the {MAX_TEXT} limit")]
        try:
            msg = orjson.loads(text)
        except orjson.JSONDecodeError as e:
            return [Problem(f"not JSON: {e}")]
        if not isinstance(msg, dict) or not isinstance(msg.get("op"), str):
            return [Problem("a message must be a JSON object with a string 'op'")]
        op = msg["op"]
        handler = _TEXT_OPS.get(op)
        if handler is None:
            return [Problem(f"unsupported op {op!r} (this server takes: {', '.join(_TEXT_OPS)})")]
        return handler(self, msg)

    def receive_binary(self, data: bytes) -> list[Event]:
        """Events of one binary message (client ``MESSAGE_DATA`` or ``SERVICE_CALL_REQUEST``)."""
        if not data:
            return [Problem("empty binary message")]
        op = data[0]
        if op == CLIENT_MESSAGE_DATA:
            return self._message_data(data)
        if op == SERVICE_CALL_REQUEST:
            return self._service_call(data)
        return [Problem(f"unknown binary opcode {op} (1: message data, 2: service call request)")]

    def subscription_of(self, channel_id: int) -> int | None:
        """The client's subscription id on ``channel_id``, or None."""
        return self.by_channel.get(channel_id)

    def forget_channel(self, channel_id: int) -> int | None:
        """The server withdrew ``channel_id``: drop the client's subscription to it (returned, or None)."""
        sid = self.by_channel.pop(channel_id, None)
        if sid is not None:
            self.subscriptions.pop(sid, None)
        return sid

    # -- text ops ----------------------------------------------------------------------------------------
    def _subscribe(self, msg: dict) -> list[Event]:
        subs = _list(msg, "subscriptions")
        if isinstance(subs, Problem):
            return [subs]
        out: list[Event] = []
        for s in subs:
            sid = _u32(s, "id") if isinstance(s, dict) else None
            cid = _u32(s, "channelId") if isinstance(s, dict) else None
            if sid is None or cid is None:
                out.append(Problem(f"subscribe: each subscription needs integer 'id' and 'channelId', got {s!r:.80}"))
            elif cid not in self.channels:
                out.append(Problem(f"subscribe: unknown channel {cid}"))
            elif sid in self.subscriptions:
                out.append(Problem(f"subscribe: subscription id {sid} is in use (channel "
                                   f"{self.subscriptions[sid]})"))
            elif cid in self.by_channel:
                out.append(Problem(f"subscribe: already subscribed to channel {cid} as {self.by_channel[cid]}"))
            elif len(self.subscriptions) >= MAX_SUBSCRIPTIONS:
                out.append(Problem(f"subscribe: over {MAX_SUBSCRIPTIONS} subscriptions; unsubscribe first"))
            else:
                self.subscriptions[sid] = cid
                self.by_channel[cid] = sid
                out.append(Subscribed(sid, cid))
        return out

    def _unsubscribe(self, msg: dict) -> list[Event]:
        ids = _list(msg, "subscriptionIds")
        if isinstance(ids, Problem):
            return [ids]
        out: list[Event] = []
        for sid in ids:
            cid = self.subscriptions.pop(sid, None) if isinstance(sid, int) else None
            if cid is None:
                out.append(Problem(f"unsubscribe: unknown subscription {sid!r:.40}"))
            else:
                self.by_channel.pop(cid, None)
                out.append(Unsubscribed(sid, cid))
        return out

    def _advertise(self, msg: dict) -> list[Event]:
        if not self.client_publish:
            return [Problem("advertise: this server does not take client publishing")]
        chans = _list(msg, "channels")
        if isinstance(chans, Problem):
            return [chans]
        out: list[Event] = []
        for c in chans:
            got = _client_channel(c, self.encodings)
            if isinstance(got, Problem):
                out.append(got)
            elif got.id in self.client_channels:
                out.append(Problem(f"advertise: client channel {got.id} is already advertised"))
            elif len(self.client_channels) >= MAX_CLIENT_CHANNELS:
                out.append(Problem(f"advertise: over {MAX_CLIENT_CHANNELS} client channels"))
            else:
                self.client_channels[got.id] = got
                out.append(Advertised(got))
        return out

    def _unadvertise(self, msg: dict) -> list[Event]:
        ids = _list(msg, "channelIds")
        if isinstance(ids, Problem):
            return [ids]
        out: list[Event] = []
        for cid in ids:
            ch = self.client_channels.pop(cid, None) if isinstance(cid, int) else None
            out.append(Unadvertised(ch) if ch is not None else
                       Problem(f"unadvertise: unknown client channel {cid!r:.40}"))
        return out

    # -- binary ops --------------------------------------------------------------------------------------
    def _message_data(self, data: bytes) -> list[Event]:
        if len(data) < 5:
            return [Problem(f"client message data of {len(data)} bytes: needs opcode and a u32 channel id")]
        cid = int.from_bytes(data[1:5], "little")
        ch = self.client_channels.get(cid)
        if ch is None:
            return [Problem(f"message data on unknown client channel {cid}: advertise it first")]
        if len(data) - 5 > MAX_CLIENT_PAYLOAD:
            return [Problem(f"message of {len(data) - 5} bytes on {ch.topic} is over the {MAX_CLIENT_PAYLOAD}-byte "
                            f"limit; dropped")]
        return [Published(ch, bytes(data[5:]))]

    def _service_call(self, data: bytes) -> list[Event]:
        if len(data) < _CALL_HEADER.size:
            return [Problem(f"service call request of {len(data)} bytes: needs opcode, service id, call id and "
                            f"encoding length")]
        _, service_id, call_id, n = _CALL_HEADER.unpack_from(data)
        if len(data) < _CALL_HEADER.size + n:
            return [Problem(f"service call request {call_id}: encoding of {n} bytes runs past the message")]
        encoding = bytes(data[_CALL_HEADER.size:_CALL_HEADER.size + n]).decode("utf-8", "replace")
        payload = bytes(data[_CALL_HEADER.size + n:])
        if service_id not in self.services:
            return [Problem(f"service call {call_id}: unknown service {service_id}")]
        if encoding not in self.encodings:
            return [Problem(f"service call {call_id}: encoding {encoding!r} is not one of "
                            f"{', '.join(self.encodings)}")]
        if len(payload) > MAX_CLIENT_PAYLOAD:
            return [Problem(f"service call {call_id}: request of {len(payload)} bytes is over the "
                            f"{MAX_CLIENT_PAYLOAD}-byte limit")]
        return [ServiceCalled(service_id, call_id, encoding, payload)]


_TEXT_OPS = {"subscribe": ClientState._subscribe, "unsubscribe": ClientState._unsubscribe,
             "advertise": ClientState._advertise, "unadvertise": ClientState._unadvertise}


def _list(msg: dict, key: str) -> list | Problem:
    v = msg.get(key)
    if not isinstance(v, list):
        return Problem(f"{msg['op']}: '{key}' must be a list")
    if len(v) > MAX_IDS:
        return Problem(f"{msg['op']}: '{key}' has {len(v)} entries, over the {MAX_IDS} limit")
    return v


def _u32(d: dict, key: str) -> int | None:
    v = d.get(key)
    return v if isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= U32 else None


def _client_channel(c, encodings: tuple[str, ...]) -> ClientChannel | Problem:
    if not isinstance(c, dict):
        return Problem(f"advertise: a channel must be an object, got {c!r:.80}")
    cid = _u32(c, "id")
    topic, enc, schema = c.get("topic"), c.get("encoding"), c.get("schemaName")
    if cid is None:
        return Problem("advertise: a channel needs an integer 'id' (u32)")
    if not isinstance(topic, str) or not topic or len(topic) > MAX_TOPIC:
        return Problem(f"advertise: channel {cid}: 'topic' must be a string of 1 - {MAX_TOPIC} characters")
    if not isinstance(schema, str) or not schema or len(schema) > MAX_TOPIC:
        return Problem(f"advertise: channel {cid} ({topic}): 'schemaName' must be a string of 1 - {MAX_TOPIC} "
                       f"characters")
    if enc not in encodings:
        return Problem(f"advertise: channel {cid} ({topic}): encoding {enc!r} is not one of "
                       f"{', '.join(encodings)}")
    return ClientChannel(cid, topic, enc, schema)


# -- the server's messages -------------------------------------------------------------------------------
def _text(obj: dict) -> str:
    return orjson.dumps(obj).decode()


def server_info(name: str, capabilities: list[str], *, supported_encodings: list[str] | None = None,
                metadata: dict[str, str] | None = None, session_id: str | None = None) -> str:
    """The ``serverInfo`` message the server sends first."""
    obj: dict = {"op": "serverInfo", "name": name, "capabilities": capabilities}
    if supported_encodings is not None:
        obj["supportedEncodings"] = supported_encodings
    if metadata:
        obj["metadata"] = metadata
    if session_id:
        obj["sessionId"] = session_id
    return _text(obj)


def status(level: int, message: str, status_id: str | None = None) -> str:
    """A ``status`` message (``level``: :data:`INFO`, :data:`WARNING` or :data:`ERROR`)."""
    obj: dict = {"op": "status", "level": level, "message": message}
    if status_id is not None:
        obj["id"] = status_id
    return _text(obj)


def advertise(channels: list[Channel]) -> str:
    """An ``advertise`` message of ``channels``."""
    return _text({"op": "advertise", "channels": [c.to_json() for c in channels]})


def unadvertise(channel_ids: list[int]) -> str:
    """An ``unadvertise`` message."""
    return _text({"op": "unadvertise", "channelIds": channel_ids})


def advertise_services(services: list[FoxgloveService]) -> str:
    """An ``advertiseServices`` message."""
    return _text({"op": "advertiseServices", "services": [s.to_json() for s in services]})


def service_call_failure(service_id: int, call_id: int, message: str) -> str:
    """A ``serviceCallFailure`` message: call ``call_id`` of ``service_id`` failed, ``message`` says why."""
    return _text({"op": "serviceCallFailure", "serviceId": service_id, "callId": call_id, "message": message})


def message_data(subscription_id: int, stamp_ns: int, payload: bytes | memoryview) -> bytes:
    """A binary ``MESSAGE_DATA``: ``payload`` for ``subscription_id``, received at ``stamp_ns`` (ns since the epoch)."""
    return _DATA_HEADER.pack(MESSAGE_DATA, subscription_id, stamp_ns) + payload


def service_call_response(service_id: int, call_id: int, encoding: str, payload: bytes) -> bytes:
    """A binary ``SERVICE_CALL_RESPONSE``."""
    enc = encoding.encode()
    return _CALL_HEADER.pack(SERVICE_CALL_RESPONSE, service_id, call_id, len(enc)) + enc + payload


def ros1_schema(store, typename: str) -> str:
    """The full ROS 1 definition of store type ``typename`` (``pkg/msg/Name``) from a rosbags typestore
    ``store``: its text and, after a line of 80 ``=``, each type it uses (``MSG: pkg/Name``), as in a bag."""
    text, _md5 = store.generate_msgdef(typename)
    return text


def ros2_schema(registry: Any, typename: str) -> str:
    """The ``ros2msg`` schema of ROS 2 type ``typename`` (a typestore name, ``pkg/msg/Name``, a service's
    ``pkg/srv/Name_Request``, an action part's ``pkg/action/Name_SendGoal_Request``...) of ``registry`` (the ROS 2
    half of the message registry, :class:`rce.messages.ros2.Ros2Registry`: its ``store`` and ament ``prefixes``):
    the type's ``.msg`` text, then each type it uses, depth first, once, after a line of 80 ``=`` and
    ``MSG: pkg/msg/Name`` (MCAP's ``ros2msg``, the layout of ``ros1msg``). A message's text is its installed
    ``share/<pkg>/msg/<Name>.msg`` (comments, defaults and constants as written), as rosbag2 and Foxglove's ROS 2
    bridge read them; a type without one (a service's or an action's part, a node package's type) is written
    from its definition by rosbags."""
    from rosbags.interfaces import Nodetype
    store = registry.store
    out: list[str] = []
    seen: set[str] = set()

    def visit(name: str) -> None:
        seen.add(name)
        if out:
            out.append(f"{SCHEMA_SEPARATOR}\nMSG: {name}\n")
        out.append(_ros2_text(registry, name))
        for _, (nt, arg) in store.fielddefs[name][1]:
            sub = arg[0] if nt in (Nodetype.ARRAY, Nodetype.SEQUENCE) else (nt, arg)
            if sub[0] == Nodetype.NAME and sub[1] not in seen:
                visit(sub[1])
    visit(typename)
    return "".join(out)


def _ros2_text(registry: Any, name: str) -> str:
    """One ROS 2 type's own ``.msg`` text, ending with a newline (see :func:`ros2_schema`)."""
    pkg, sub, base = name.split("/")
    if sub == "msg":
        for prefix in registry.prefixes:
            f = Path(prefix) / "share" / pkg / "msg" / f"{base}.msg"
            if f.is_file():
                text = f.read_text()
                return text if text.endswith("\n") else text + "\n"
    consts, fields = registry.store.fielddefs[name]
    lines = [f"{t} {c}={_const(v)}" for c, t, v in consts]
    lines += [f"{_field_type(*ftype)} {fname}" for fname, ftype in fields
              if fname != "structure_needs_at_least_one_member"]      # rosidl's member of an empty message
    return "".join(line + "\n" for line in lines)


def _field_type(nt: Any, arg: Any) -> str:
    """A field's type in ``.msg`` syntax from a rosbags field definition (``string<=22``, ``int32[3]``,
    ``float64[<=5]``, ``pkg/msg/Name[]``)."""
    from rosbags.interfaces import Nodetype
    if nt == Nodetype.BASE:
        t, bound = arg
        return f"{t}<={bound}" if bound else t
    if nt == Nodetype.NAME:
        return arg
    item, n = _field_type(*arg[0]), arg[1]
    return f"{item}[{n}]" if nt == Nodetype.ARRAY else f"{item}[<={n}]" if n else f"{item}[]"


def _const(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return orjson.dumps(value).decode() if isinstance(value, str) else str(value)
