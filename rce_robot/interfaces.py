"""Robot-side interfaces: converters (JSON <-> ROS message) and forwarders (serialized
ROS message as a binary part ``msg*``), docs/design.md, section 3.5.

Each lives in one robot's session and is connected over the data plane to container
interfaces. What the robot sends arrives here (:meth:`RobotInterface.from_robot`,
:meth:`RobotInterface.call_from_robot`) once the session has routed the DM; what peers send
leaves through the session's :class:`RobotLink`. Whether a DM suits its interface's class,
direction and encoding is the session's rule (:mod:`rce.protocol.session`); whether the
message fits its class is decided here, with the message registry.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

from rce.plumbing.errors import MessageError, ProtocolError, RequestError, Unavailable
from rce.interfaces.kind import InterfaceType, Kind, Side
from rce.transport.interface import Interface
from rce.interfaces.lanes import Lane
from rce.interfaces.classes import Conversion
from rce.messages.convert import conversion
from rce.messages.forms import JsonForms
from rce.messages import MessageRegistry
from rce.plumbing.pending import PendingCalls
from rce.protocol.frames import new_id

if TYPE_CHECKING:
    from rce.transport.dataplane import DataPlane

# s a container's call to the robot's service waits for the robot's reply
ROBOT_CALL_TIMEOUT = 30.0
BATTERY = "sensor_msgs/msg/BatteryState"    # a robot's charge, read on its way for the placer


class RobotLink(Protocol):
    """What an interface needs of its robot's session (:class:`rce_robot.namespace.RobotNamespace`)."""

    robot: str
    forms: JsonForms        # the JSON forms this robot gets back (rce.messages.forms), learned from what it sends

    def send_dm(self, itag: str, cls: str, msg_id: Any, msg: Any, data: bool = False) -> bool:
        """Queue a DM for the robot; ``data=True``: droppable topic data (the oldest waiting go first;
        False when this one was dropped)."""

    def send_status(self, data: dict) -> None:
        """Queue an ST for the robot."""

    def send_error(self, reason: str) -> None:
        """Queue an ER for the robot."""

    def battery_seen(self, percent: float) -> None:
        """The robot's charge (0 - 100 %), read from a ``sensor_msgs/BatteryState`` it sent."""


class RobotInterface(Interface):
    """A converter or forwarder (``itype``, a robot-side :class:`InterfaceType`: its kind is
    Publisher, Subscriber, ServiceClient or ServiceProvider), for class ``cls``, in the
    session ``link`` of its robot. ``robot_call_timeout``: s a call from the cloud waits
    for the robot's reply (ServiceClient kinds). ``lane``: the lane the robot set for it
    (:mod:`rce.interfaces.lanes`; None: from ``cls``).

    Raises :class:`MessageError` at creation if ``cls`` is not a known message (or, for the
    service kinds, service) class."""

    def __init__(self, link: RobotLink, plane: "DataPlane", registry: MessageRegistry,
                 iid: int, itag: str, itype: InterfaceType, cls: str, *,
                 robot_call_timeout: float = ROBOT_CALL_TIMEOUT, lane: Lane | None = None):
        super().__init__(plane, iid, f"{link.robot}/{itag}", itype.kind, cls)
        self.link, self.registry, self.itag, self.itype, self.lane = link, registry, itag, itype, lane
        self.side = itype.side
        self.robot_call_timeout = robot_call_timeout
        if itype.kind.service:
            self.req_t, self.resp_t = registry.srv_types(cls)
            self.msg_t = ""
        else:
            self.msg_t = registry.msg_type(cls)
            self.req_t = self.resp_t = ""
        self._up = False
        self._robot_calls = PendingCalls(f"robot {link.robot!r}")     # msgID -> a call from the cloud

    # -- encoding (the only place converters and forwarders differ) ------------------------------
    def _encode(self, typename: str, msg: Any) -> bytes:
        """Robot message -> serialized bytes. Raises :class:`MessageError` naming the interface."""
        try:
            if self.side is Side.CONVERTER:
                return self.registry.json_to_bytes(typename, msg, self.link.forms)
            self.registry.check_structure(typename, msg)     # strings are not decoded: bytes pass untouched
            return msg                                       # the robot's bytes as they came: no copy
        except MessageError as e:
            raise MessageError(f"interface {self.itag!r}: {e.message}") from None

    def _decode(self, typename: str, payload: bytes | memoryview) -> Any:
        """Serialized bytes -> the robot's form: JSON (converters), or the bytes themselves as a
        binary part (forwarders; a view of the received frame, which nobody writes again: no copy)."""
        if self.side is Side.CONVERTER:
            return self.registry.bytes_to_json(typename, bytes(payload), self.link.forms)
        return payload

    # -- ROS 1 <-> ROS 2 ------------------------------------------------------------------------
    def conversion(self, peer_cls: str) -> Conversion:
        try:
            return conversion(self.registry, self.kind, self.cls, peer_cls)
        except MessageError as e:
            raise MessageError(f"interface {self.itag!r} ({self.cls}) cannot be connected to {peer_cls}: "
                               f"{e.message}") from None

    def on_convert_error(self, error: MessageError) -> None:
        self.link.send_error(f"interface {self.itag!r}: a message to the cloud was not converted: {error.message}")

    # -- status ----------------------------------------------------------------------------------
    def on_peers_changed(self) -> None:
        up = bool(self.peers)
        if up != self._up:
            self._up = up
            self.link.send_status({"topic": "iu", "iTag": self.itag, "status": up})

    # -- robot -> cloud ----------------------------------------------------------------------------
    def from_robot(self, data: dict) -> None:
        """Take a DM the robot sent to a Subscriber* (a topic message) or a ServiceClient* (the
        robot's reply to a call from the cloud), inline: nothing here waits. Service calls the
        robot makes go through :meth:`call_from_robot`. Raises :class:`RCEError` to answer ER."""
        msg = data.get("msg")
        if self.kind is Kind.SUBSCRIBER:
            payload = self._encode(self.msg_t, msg)
            self.msgs_in += 1
            if self.msg_t == BATTERY:
                self._battery(msg, payload)
            if not self.peers:
                self.dropped += 1
                return
            self.send_message(payload)
            return
        msg_id = str(data.get("msgID") or "")
        if msg_id not in self._robot_calls:
            raise ProtocolError(f"interface {self.itag!r}: response with unknown msgID {data.get('msgID')!r}")
        try:
            self._robot_calls.settle(msg_id, self._encode(self.resp_t, msg))
        except MessageError as e:
            self._robot_calls.fail(msg_id, e)
            raise

    def _battery(self, msg: Any, payload: bytes | memoryview) -> None:
        """Tell the session the charge a BatteryState carries (``percentage``, 0 - 1, REP 145 /
        sensor_msgs; NaN: not measured, ignored)."""
        try:
            pct = msg.get("percentage") if isinstance(msg, dict) else \
                self.registry.deserialize(self.msg_t, bytes(payload)).percentage
            pct = float(pct)
        except (MessageError, TypeError, ValueError, AttributeError):
            return
        if 0.0 <= pct <= 1.0:
            self.link.battery_seen(100.0 * pct)

    def fail_robot_call(self, msg_id: Any, reason: str) -> None:
        """(ServiceClient*) The robot refuses the call from the cloud ``msg_id`` (a rosbridge
        ``service_response`` with ``result: false``): the caller's call fails with
        :class:`RequestError` ``reason``. Raises :class:`ProtocolError` for an unknown msgID."""
        if not self._robot_calls.fail(str(msg_id or ""), RequestError(f"the robot refused the call: {reason}")):
            raise ProtocolError(f"interface {self.itag!r}: refusal with unknown msgID {msg_id!r}")

    async def call_from_robot(self, data: dict) -> Any:
        """(ServiceProvider*) The robot calls the connected service: forward the request; returns
        the response in the robot's form. Raises :class:`RCEError` (the session's ER)."""
        self.msgs_in += 1
        resp = await self.call_peer(self._encode(self.req_t, data.get("msg")))
        return self._decode(self.resp_t, resp)

    # -- cloud -> robot ----------------------------------------------------------------------------
    def on_message(self, payload: memoryview) -> None:
        if self.kind is not Kind.PUBLISHER:
            self.dropped += 1
            return
        self.msgs_in += 1
        try:
            self.link.send_dm(self.itag, self.cls, "", self._decode(self.msg_t, payload), data=True)
        except MessageError as e:
            self.dropped += 1
            self.link.send_error(f"interface {self.itag!r}: dropped a message from the cloud: {e.message}")

    async def serve(self, payload: bytes) -> bytes:
        """A container calls the robot's service: DM request to the robot, wait for its reply.
        Raises :class:`rce.plumbing.errors.Timeout` after ``robot_call_timeout`` s."""
        if self.kind is not Kind.SERVICE_CLIENT:
            return await super().serve(payload)
        request = self._decode(self.req_t, payload)
        return await self._robot_calls.call(
            lambda msg_id: self.link.send_dm(self.itag, self.cls, msg_id, request), self.robot_call_timeout,
            what=f"the call on {self.itag!r}", key=new_id())

    async def stop(self) -> None:
        self._robot_calls.fail_all(Unavailable(f"interface {self.itag!r} was removed"))
        await super().stop()
