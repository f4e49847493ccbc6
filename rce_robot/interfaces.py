"""Robot-side interfaces: converters (JSON <-> ROS message) and forwarders (serialized
ROS message as a binary part ``msg*``), DESIGN section 3.5.

Each lives in one robot namespace and is connected over the data plane to
container interfaces. What the robot sends arrives here as a DM; what peers
send leaves as a DM.
"""
from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

from rce.errors import MessageError, ProtocolError, RequestError, Unavailable
from rce.interfaces import Interface
from rce.messages import MessageRegistry
from rce.protocol import new_id

if TYPE_CHECKING:
    from rce.dataplane import DataPlane
    from rce_robot.namespace import RobotNamespace


class RobotInterface(Interface):
    """A converter (``side == "Converter"``) or forwarder (``"Forwarder"``) of kind
    Publisher, Subscriber, ServiceClient or ServiceProvider, for class ``cls``.

    Raises :class:`MessageError` at creation if ``cls`` is not a known message (or, for the
    service kinds, service) class."""

    robot_call_timeout = 30.0   # s, a cloud -> robot service call waiting for the robot's reply

    def __init__(self, ns: "RobotNamespace", plane: "DataPlane", registry: MessageRegistry,
                 iid: int, itag: str, kind: str, side: str, cls: str):
        super().__init__(plane, iid, f"{ns.robot}/{itag}", kind, cls)
        self.ns, self.registry, self.itag, self.side = ns, registry, itag, side
        if kind in ("ServiceClient", "ServiceProvider"):
            self.req_t, self.resp_t = registry.srv_types(cls)
            self.msg_t = ""
        else:
            self.msg_t = registry.msg_type(cls)
            self.req_t = self.resp_t = ""
        self._up = False
        self._robot_calls: dict[str, asyncio.Future] = {}

    @property
    def itype(self) -> str:
        return self.kind + self.side

    # -- encoding (the only place converters and forwarders differ) ------------------------------
    def _encode(self, typename: str, msg: Any) -> bytes:
        """Robot message -> serialized bytes. Raises :class:`MessageError` naming the interface."""
        if self.side == "Converter":
            if isinstance(msg, (bytes, bytearray)):
                raise MessageError(f"{self.itype} {self.itag!r} takes JSON messages; use a "
                                   f"{self.kind}Forwarder for serialized binary messages")
            try:
                return self.registry.json_to_bytes(typename, msg)
            except MessageError as e:
                raise MessageError(f"interface {self.itag!r}: {e.message}") from None
        if not isinstance(msg, (bytes, bytearray)):
            raise MessageError(f"{self.itype} {self.itag!r} takes the serialized message as binary part 'msg*'")
        try:
            self.registry.deserialize(typename, bytes(msg))
        except MessageError as e:
            raise MessageError(f"interface {self.itag!r}: {e.message}") from None
        return bytes(msg)

    def _decode(self, typename: str, payload: bytes | memoryview) -> Any:
        if self.side == "Converter":
            return self.registry.bytes_to_json(typename, bytes(payload))
        return bytes(payload)

    # -- status ----------------------------------------------------------------------------------
    def on_peers_changed(self) -> None:
        up = bool(self.peers)
        if up != self._up:
            self._up = up
            self.ns.send_status({"topic": "iu", "iTag": self.itag, "status": up})

    # -- robot -> cloud ----------------------------------------------------------------------------
    def from_robot(self, data: dict) -> None:
        """Handle a DM the robot sent to a Subscriber* (a topic message) or ServiceClient* (the
        robot's reply to a call from the cloud), inline: nothing here waits. Service calls the
        robot makes go through :meth:`call_from_robot`. Raises :class:`RCEError` to answer ER."""
        msg = data.get("msg")
        if self.kind == "Subscriber":
            payload = self._encode(self.msg_t, msg)
            self.msgs_in += 1
            if not self.peers:
                self.dropped += 1
                return
            self.send_message(payload)
        elif self.kind == "ServiceClient":
            fut = self._robot_calls.get(str(data.get("msgID") or ""))
            if fut is None:
                raise ProtocolError(f"interface {self.itag!r}: response with unknown msgID {data.get('msgID')!r}")
            if not fut.done():
                try:
                    fut.set_result(self._encode(self.resp_t, msg))
                except Exception as e:
                    fut.set_exception(e)
                    raise
        else:
            raise RequestError(f"{self.itype} {self.itag!r} sends messages to the robot; it does not take "
                               f"messages from it (use a SubscriberConverter)")

    async def call_from_robot(self, data: dict) -> None:
        """(ServiceProvider*) The robot calls the connected service: forward the request, answer
        with a DM carrying the same msgID. Raises :class:`RCEError` to answer ER."""
        self.msgs_in += 1
        msg_id = data.get("msgID") or ""
        payload = self._encode(self.req_t, data.get("msg"))
        resp = await self.call_peer(payload)
        self.ns.send_dm(self.itag, self.cls, msg_id, self._decode(self.resp_t, resp))

    # -- cloud -> robot ----------------------------------------------------------------------------
    def on_message(self, payload: memoryview) -> None:
        if self.kind != "Publisher":
            self.dropped += 1
            return
        self.msgs_in += 1
        try:
            self.ns.send_dm(self.itag, self.cls, "", self._decode(self.msg_t, payload), data=True)
        except MessageError as e:
            self.dropped += 1
            self.ns.send_error(f"interface {self.itag!r}: dropped a message from the cloud: {e.message}")

    async def serve(self, payload: bytes) -> bytes:
        """A container calls the robot's service: DM request to the robot, wait for its reply."""
        if self.kind != "ServiceClient":
            raise RequestError(f"{self.itype} {self.itag!r} does not serve calls")
        msg_id = new_id()
        fut = asyncio.get_running_loop().create_future()
        self._robot_calls[msg_id] = fut
        try:
            self.ns.send_dm(self.itag, self.cls, msg_id, self._decode(self.req_t, payload))
            return await asyncio.wait_for(fut, self.robot_call_timeout)
        except asyncio.TimeoutError:
            raise Unavailable(f"robot {self.ns.robot!r} did not answer the call on {self.itag!r} within "
                              f"{self.robot_call_timeout:g} s") from None
        finally:
            self._robot_calls.pop(msg_id, None)

    async def stop(self) -> None:
        for fut in self._robot_calls.values():
            if not fut.done():
                fut.set_exception(Unavailable(f"interface {self.itag!r} was removed"))
        await super().stop()
