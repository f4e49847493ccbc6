"""Interfaces: the ends of connections (docs/design.md, section 3.5), sans transport details.

An interface has a kind (prefix) and a side (suffix). Each is named on the side
where it acts:

- ``Subscriber*`` takes messages from its local side (the robot, or the
  container's bus) and sends them to every connected ``Publisher*``;
- ``Publisher*`` hands what it receives to its local side;
- ``ServiceProvider*`` provides a service to its local side and forwards each
  call to its connected ``ServiceClient*``;
- ``ServiceClient*`` executes calls it receives against its local side.

This module holds the data-plane half every endpoint shares (an interface is a
:class:`rce.transport.dataplane.Receiver` of its endpoint's data plane); robot endpoints
(converters, forwarders) and environments (bus interfaces) subclass it for
their local side.
"""
from __future__ import annotations

from rce.interfaces.actions import call_timeout
from rce.interfaces.classes import Conversion, Convert, is_ros2_name
from rce.plumbing.errors import MessageError, RequestError, Unavailable
from rce.transport import framing
from rce.transport.dataplane import DataPlane



class Interface:
    """Data-plane half of an interface.

    ``iid``: the master-assigned id; ``tag``: ``endpointTag/interfaceTag``; ``kind``: prefix
    (Publisher, Subscriber, ServiceClient, ServiceProvider); ``cls``: message or service class
    (wire name); ``peers``: connected interface id -> data address; ``conversions``: the peers
    whose end is of the other ROS (ROS 1 and ROS 2), and how this end converts what it sends them
    (the sending end converts: a Subscriber* its messages, a ServiceProvider* its requests and
    the responses that come back). ``call_timeout``: s a call forwarded to the peer waits
    (:func:`rce.interfaces.actions.call_timeout`: an action's get_result waits for its goal)."""

    def __init__(self, plane: DataPlane, iid: int, tag: str, kind: str, cls: str):
        self.plane, self.iid, self.tag, self.kind, self.cls = plane, iid, tag, kind, cls
        self.peers: dict[int, str] = {}
        self.conversions: dict[int, Conversion] = {}
        self.call_timeout = call_timeout(cls)
        self.msgs_in = self.msgs_out = self.dropped = 0
        self.convert_errors = 0

    # -- lifecycle -----------------------------------------------------------------------------
    async def start(self) -> None:
        """Attach to the local side (subclasses) and to the data plane."""
        self.plane.interfaces[self.iid] = self

    async def stop(self) -> None:
        """Detach from the data plane and the local side."""
        self.plane.interfaces.pop(self.iid, None)
        self.plane.forbid(self.iid)
        self.peers.clear()

    def connect(self, peer_iid: int, addr: str, token: bytes, fence: int | None = None,
                peer_cls: str | None = None) -> int:
        """Add a connection to interface ``peer_iid`` reachable at data address ``addr``;
        ``token``: the master's credential for sending to it (:mod:`rce.transport.cluster_auth`).
        A connection that exists already is pointed at ``addr`` in one step (its container moved,
        :mod:`rce_master.placement.mover`): from here on it goes there, and the old copy's claims end; with
        ``fence`` (the move's fence id) the old copy first gets a fence behind the last message sent
        to it on each path (:meth:`rce.transport.dataplane.DataPlane.fence`). Messages to it that
        had not left this process yet go to the new address instead, first
        (:meth:`~rce.transport.dataplane.DataPlane.take_unsent`). Returns how many fences went out
        (0: none, or nothing can still be on its way to the old copy). ``peer_cls``: the peer's
        class; one of the other ROS makes this end convert what it sends (:meth:`conversion`, which
        raises :class:`MessageError` when it cannot: nothing is connected then)."""
        if peer_cls and is_ros2_name(peer_cls) != is_ros2_name(self.cls) and self.kind in ("Subscriber",
                                                                                          "ServiceProvider"):
            self.conversions[peer_iid] = self.conversion(peer_cls)
        else:
            self.conversions.pop(peer_iid, None)
        old = self.peers.get(peer_iid)
        fenced = 0
        unsent: list = []
        if old is not None and old != addr:
            unsent = self.plane.take_unsent(self.iid, peer_iid, old)
            if fence is not None:
                fenced = self.plane.fence(self.iid, peer_iid, old, fence)
            self.plane.drop_claims(peer_iid)
        self.peers[peer_iid] = addr
        self.plane.allow(self.iid, peer_iid, token)
        if old != addr:
            self.plane.send_unsent(self.iid, peer_iid, addr, unsent)
            self.plane.readdressed(peer_iid)
        self.on_peers_changed()
        return fenced

    def disconnect(self, peer_iid: int) -> None:
        """Drop the connection to interface ``peer_iid`` (no error if absent)."""
        self.peers.pop(peer_iid, None)
        self.conversions.pop(peer_iid, None)
        self.plane.forbid(self.iid, peer_iid)
        self.on_peers_changed()

    def on_peers_changed(self) -> None:
        """Hook: the set of connections changed (robot endpoints send an ST)."""

    def conversion(self, peer_cls: str) -> Conversion:
        """How this end converts for a peer of class ``peer_cls`` in the other ROS. Endpoints that hold a
        message registry give it (:func:`rce.messages.convert.conversion`); here, none can be made:
        raises :class:`MessageError`."""
        raise MessageError(f"interface {self.tag} ({self.cls}) cannot convert to {peer_cls} here")

    def on_convert_error(self, error: MessageError) -> None:
        """Hook: a message could not be converted for a peer (dropped and counted in ``convert_errors``).
        Endpoints tell the robot (ER) or log it."""

    # -- data ----------------------------------------------------------------------------------
    def send_message(self, payload: bytes | memoryview) -> int:
        """(Subscriber*) Send a serialized message to every connected peer; returns how many took it."""
        n = 0
        converted: dict[Convert, bytes] = {}
        for peer, addr in self.peers.items():
            data = payload
            conv = self.conversions.get(peer)
            if conv is not None:
                data = converted.get(conv.out)
                if data is None:
                    try:
                        data = converted[conv.out] = conv.out(payload)
                    except MessageError as e:
                        self.dropped += 1
                        self.convert_errors += 1
                        self.on_convert_error(e)
                        continue
            if self.plane.send(addr, framing.MSG, peer, self.iid, 0, data):
                n += 1
            else:
                self.dropped += 1
        self.msgs_out += 1
        return n

    async def call_peer(self, payload: bytes) -> bytes:
        """(ServiceProvider*) Forward a serialized request to the connected ServiceClient.

        Raises :class:`Unavailable` with no connection (or a saturated link),
        :class:`~rce.plumbing.errors.Timeout` after ``call_timeout`` s, :class:`RequestError` with the
        remote reason when the call fails there."""
        if not self.peers:
            raise Unavailable(f"service interface {self.tag} is not connected")
        peer, addr = next(iter(self.peers.items()))
        self.msgs_out += 1
        conv = self.conversions.get(peer)
        if conv is None:
            return await self.plane.call(addr, peer, self.iid, payload, self.call_timeout)
        resp = await self.plane.call(addr, peer, self.iid, conv.out(payload), self.call_timeout)
        return conv.back(resp)

    def on_message(self, payload: memoryview) -> None:
        """(Publisher*) A message arrived from a peer. Subclasses deliver it locally."""
        raise RequestError(f"{self.kind} interface {self.tag} does not receive messages")

    async def serve(self, payload: bytes) -> bytes:
        """(ServiceClient*) Execute a call that arrived from a peer; returns the response bytes."""
        raise RequestError(f"{self.kind} interface {self.tag} does not serve calls")
