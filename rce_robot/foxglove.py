"""The Foxglove WebSocket endpoint of a robot task set (``rce-robot --foxglove-port``; off by default): a
container's graph in Foxglove and Lichtblick, over the Foxglove WebSocket protocol (:mod:`rce.foxglove`).

A client opens ``ws://HOST:PORT/?userID=U&password=SHA256HEX&container=CTAG`` (``&robotID=R`` optional; default
``foxgloveN``). Before the websocket opens the master checks the password, that ``U`` has container ``CTAG`` and
takes ``R`` as a connected robot, as for a rosbridge client (refusals: HTTP 401, 404, 403). The client is then a
rosbridge session of the endpoint (:class:`~rce_robot.rosbridge.session.RosbridgeSession`, a robot namespace whose
interfaces the master makes on its behalf), driven with rosbridge ops:

- the container's topics are advertised as channels, its services as services (``services``), as they are when the
  client connects: a ROS 1 type's with encoding ``ros1``, schema encoding ``ros1msg`` and the full ROS 1 definition;
  a ROS 2 type's (``pkg/msg/T``, ``pkg/srv/T``) with ``cdr``, ``ros2msg`` and the ROS 2 ``.msg`` texts
  (:func:`rce.foxglove.protocol.ros2_schema`), as Foxglove's ROS 2 bridge advertises them;
- a Foxglove ``subscribe`` is a rosbridge ``subscribe`` with ``cbor-raw`` compression: the serialized message
  (ROS 1, or CDR) comes back and goes out as ``MESSAGE_DATA``, with the time it was received;
- a client channel (``clientPublish`` in ``ros1``, ``cdr`` or ``json``: ``supportedEncodings``) is a rosbridge
  ``advertise`` of its schema name and its messages ``publish`` ops, each decoded as the class its encoding names
  (``cdr``: the ROS 2 form of the schema name, ``ros1``: the ROS 1 form); a service call (in any of the three) is a
  ``call_service`` whose answer goes back, in the call's encoding, as ``SERVICE_CALL_RESPONSE`` (or
  ``serviceCallFailure``);
- the session's ``status`` errors reach the client as Foxglove ``status`` errors.
"""
from __future__ import annotations

import asyncio
import itertools
from typing import Any

import cbor2
import orjson

from rce.foxglove.protocol import (ALL_CLIENT_ENCODINGS, CDR, JSON, ROS2MSG, ClientChannel, FoxgloveService,
                                   ros1_schema, ros2_schema)
from rce.foxglove.server import FoxgloveClient, FoxgloveServer
from rce.interfaces.classes import is_ros2_name, plain_name
from rce.messages import default_registry
from rce.messages.registry import ROS2_PREFIX
from rce.contract import master as to_master
from rce.plumbing.errors import AuthError, MessageError, NotFound, RCEError, RequestError
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_robot.rosbridge.endpoint import RosbridgeServer
from rce_robot.rosbridge.session import RosbridgeSession

log = get_logger("rce.foxglove")

CALL_TIMEOUT = 30.0         # s a service call waits for the container's answer
ROBOT_PREFIX = "foxglove"   # robotID of a client that names none: foxglove1, foxglove2, ...


class RobotFoxglove:
    """The endpoint's Foxglove server (module docstring), beside its rosbridge server ``rosbridge`` (whose master
    link, interface table and session table it shares)."""

    def __init__(self, rosbridge: RosbridgeServer):
        self.rb = rosbridge
        self.reg = default_registry()
        self.server = FoxgloveServer("rce-robot", authenticate=self._auth, on_publish=self._publish,
                                     on_service_call=self._call, per_client=True, on_connect=self._connect,
                                     on_disconnect=self._disconnect, on_subscribe=self._subscribe,
                                     on_unsubscribe=self._unsubscribe, metric_prefix="rce_robot_foxglove",
                                     client_encodings=ALL_CLIENT_ENCODINGS)
        self._robots = itertools.count(1)
        self._calls = itertools.count(1)

    @property
    def port(self) -> int:
        """The port it listens on."""
        return self.server.port

    async def start(self, bind: str, port: int, ssl_context=None) -> None:
        """Listen on ``bind``:``port`` (0: ephemeral); wss:// with ``ssl_context`` (the task set's TLS)."""
        await self.server.start(bind, port, ssl_context)

    async def stop(self) -> None:
        """Close the server and its clients' sessions."""
        await self.server.stop()

    async def _auth(self, query: dict[str, str]) -> tuple[str, str, str]:
        user, password, ctag = query.get("userID", ""), query.get("password", "").lower(), query.get("container", "")
        if not user or not password or not ctag:
            raise AuthError("give userID, password (the hex SHA-256 of the password) and container in the URL's query")
        if len(password) != 64 or any(c not in "0123456789abcdef" for c in password):
            raise AuthError("password must be the hex SHA-256 digest (64 hex digits) of the password")
        robot = query.get("robotID") or f"{ROBOT_PREFIX}{next(self._robots)}"
        await self.rb.master.ask(to_master.Auth(user=user, robot=robot, password=password, addr="foxglove"))
        try:
            await self.rb.master.ask(to_master.ContainerBus(user=user, ctag=ctag))
        except NotFound:
            raise
        except RCEError as e:
            raise NotFound(e.message) from None
        await self.rb.master.ask(to_master.RobotConnected(user=user, robot=robot))
        return user, robot, ctag

    async def _connect(self, client: FoxgloveClient) -> None:
        user, robot, ctag = client.principal
        session = client.session = RosbridgeSession(user, robot, ctag, self.rb.master, self.rb.max_lag)
        session.ws = client.ws
        session.fox_calls = {}                              # rosbridge call id -> (future)
        self.rb.sessions[(user, robot)] = session
        self.rb.sessions_total += 1
        session.fox_pump = Tasks(f"foxglove {user}/{robot}")
        session.fox_pump.spawn(self._pump(client, session), name="pump")
        graph = await session.describe()
        for t in graph.get("topics", []):
            try:
                typename = self.reg.msg_type(t["type"])
            except MessageError:
                continue                                    # a class this endpoint does not know: not offered
            if typename.startswith(ROS2_PREFIX):
                client.add_channel(t["name"], t["type"], self._schema(typename), encoding=CDR, schema_encoding=ROS2MSG)
            else:
                client.add_channel(t["name"], t["type"], self._schema(typename))
        for s in graph.get("services", []):
            try:
                req, resp = self.reg.srv_types(s["type"])
            except MessageError:
                continue
            client.add_service(s["name"], s["type"], self._schema(req), self._schema(resp))

    def _schema(self, typename: str) -> str:
        """The schema of registry type ``typename``: ``ros2msg`` for a ROS 2 one, else ``ros1msg``."""
        if typename.startswith(ROS2_PREFIX):
            return ros2_schema(self.reg.ros2, typename[len(ROS2_PREFIX):])
        return ros1_schema(self.reg.store, typename)

    async def _disconnect(self, client: FoxgloveClient) -> None:
        session = client.session
        if session is None:
            try:
                await self.rb.master.ask(to_master.RobotDisconnected(user=client.principal[0],
                                                                     robot=client.principal[1]))
            except RCEError:
                pass
            return
        await session.fox_pump.cancel_all()
        await self.rb._end(session)

    async def _op(self, client: FoxgloveClient, op: dict) -> None:
        await client.session.handle(orjson.dumps(op).decode())

    async def _subscribe(self, client: FoxgloveClient, ch) -> None:
        await self._op(client, {"op": "subscribe", "topic": ch.topic, "type": ch.schema_name, "compression": "cbor-raw",
                                "id": f"fox{ch.id}"})

    async def _unsubscribe(self, client: FoxgloveClient, ch) -> None:
        await self._op(client, {"op": "unsubscribe", "topic": ch.topic, "id": f"fox{ch.id}"})

    async def _publish(self, client: FoxgloveClient, ch: ClientChannel, payload: bytes) -> None:
        session = client.session
        msg = _json(payload) if ch.encoding == JSON else \
            self.reg.bytes_to_json(self.reg.msg_type(_twin(ch.schema_name, ch.encoding, "msg")), payload)
        advertised = getattr(session, "fox_advertised", set())
        session.fox_advertised = advertised
        if ch.topic not in advertised:
            await self._op(client, {"op": "advertise", "topic": ch.topic, "type": ch.schema_name})
            advertised.add(ch.topic)
        await self._op(client, {"op": "publish", "topic": ch.topic, "msg": msg})

    async def _call(self, client: FoxgloveClient, service: FoxgloveService, encoding: str,
                    payload: bytes) -> tuple[str, bytes]:
        session = client.session
        req, resp = ("", "") if encoding == JSON else self.reg.srv_types(_twin(service.type, encoding, "srv"))
        args = _json(payload) if encoding == JSON else self.reg.bytes_to_json(req, payload)
        call_id = f"foxcall{next(self._calls)}"
        done = session.fox_calls[call_id] = asyncio.get_running_loop().create_future()
        try:
            await self._op(client, {"op": "call_service", "service": service.name, "type": service.type,
                                    "args": args, "id": call_id})
            async with asyncio.timeout(CALL_TIMEOUT):
                answer = await done
        except TimeoutError:
            raise RequestError(f"{service.name}: no answer within {CALL_TIMEOUT:g} s") from None
        finally:
            session.fox_calls.pop(call_id, None)
        if not answer.get("result", False):
            raise RequestError(f"{service.name}: {answer.get('values')}")
        values = answer.get("values") or {}
        if encoding == JSON:
            return JSON, orjson.dumps(values)
        return encoding, self.reg.json_to_bytes(resp, values)

    async def _pump(self, client: FoxgloveClient, session: RosbridgeSession) -> None:
        """What the rosbridge session sends its client, as Foxglove messages."""
        while True:
            for frame in await session.outbox.get():
                if isinstance(frame, bytes):
                    self._message(client, cbor2.loads(frame))
                else:
                    self._text(client, session, orjson.loads(frame))

    @staticmethod
    def _message(client: FoxgloveClient, op: dict) -> None:
        ch = client.by_topic.get(op.get("topic", "")) if op.get("op") == "publish" else None
        if ch is not None:
            m = op["msg"]
            client.publish(ch.id, m["bytes"], m["secs"] * 1_000_000_000 + m["nsecs"])

    @staticmethod
    def _text(client: FoxgloveClient, session: Any, op: dict) -> None:
        if op.get("op") == "service_response":
            done = session.fox_calls.get(op.get("id"))
            if done is not None and not done.done():
                done.set_result(op)
        elif op.get("op") == "status" and op.get("level") == "error":
            client.status(2, str(op.get("msg", "")))


def _twin(cls: str, encoding: str, sub: str) -> str:
    """``cls`` (a message class for ``sub`` ``msg``, a service's for ``srv``) in the form of ``encoding``'s ROS:
    ROS 2's ``pkg/SUB/Name`` for ``cdr``, ROS 1's ``pkg/Name`` for ``ros1``."""
    if encoding != CDR:
        return plain_name(cls)
    if is_ros2_name(cls):
        return cls.strip("/")
    pkg, _, name = plain_name(cls).partition("/")
    return f"{pkg}/{sub}/{name}"


def _json(payload: bytes) -> Any:
    try:
        return orjson.loads(payload)
    except orjson.JSONDecodeError as e:
        raise MessageError(f"not JSON: {e}") from None
