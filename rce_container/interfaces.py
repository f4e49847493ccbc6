"""Container-side interfaces: the ends of connections that live on a container's bus.

Each is a :class:`rce.transport.interface.Interface` (data-plane half) whose local side is the
environment's :class:`~rce.bus.core.Bus`, named on the side where it acts:

- :class:`PublisherInterface` publishes into the container what its peers send;
- :class:`SubscriberInterface` subscribes in the container and sends to its peers;
- :class:`ServiceClientInterface` executes its peers' calls against a container service;
- :class:`ServiceProviderInterface` provides a service in the container and forwards each
  call to its connected peer.

``addr`` (the topic or service) is a global name; absent, it is ``/`` + the interface tag.
Payloads stay ROS 1 serialized bytes end to end. Bus owners are ``interface:<tag>``.
"""
from __future__ import annotations

import asyncio

from rce.bus.core import SERVICE_TIMEOUT, Bus, Subscription, Topic
from rce.transport.dataplane import DataPlane
from rce.plumbing.errors import MessageError, RequestError
from rce.interfaces.kind import InterfaceType, Kind
from rce.transport.interface import Interface
from rce.interfaces.classes import Conversion
from rce.messages import MessageRegistry, default_registry, store_name, wire_name
from rce.messages.convert import conversion
from rce.plumbing.log import get_logger
from rce.interfaces.naming import resolve
from rce.node.package_path import load_package_types

log = get_logger("rce.container.interfaces")

DEFAULT_QUEUE = 100   # messages, bound of a SubscriberInterface's bus subscription
SERVICE_WAIT = 10.0   # s a call from a peer waits for its service to be provided (its node may be starting),
                      # and a call to a ServiceProviderInterface for its connection


class BusInterface(Interface):
    """Base of the container-side interfaces: an :class:`Interface` bound to a bus name.

    ``bus``: the group's bus; ``cid``: the owning container; ``tag``: the interface tag as
    the master names it; ``cls``: wire class name (``std_msgs/String``, ``Test/StringEcho``);
    ``addr``: resolved global topic/service name.

    Counters: ``msgs_in``/``bytes_in`` count what came from the data plane into the container
    (messages, service requests or responses), ``msgs_out``/``bytes_out`` what went out onto
    it; ``dropped`` counts messages a saturated peer link refused."""

    kind = ""

    def __init__(self, plane: DataPlane, bus: Bus, cid: int, iid: int, tag: str, cls: str, addr: str):
        super().__init__(plane, iid, tag, self.kind, cls)
        self.bus, self.cid, self.addr = bus, cid, addr
        self.owner = f"interface:{tag}"
        self.bytes_in = self.bytes_out = 0

    def conversion(self, peer_cls: str) -> Conversion:
        try:
            return conversion(default_registry(), self.kind, self.cls, peer_cls)
        except MessageError as e:
            raise MessageError(f"interface {self.tag} ({self.cls}) cannot be connected to {peer_cls}: "
                               f"{e.message}") from None

    def on_convert_error(self, error: MessageError) -> None:
        log.warning("message not converted", interface=self.tag, cls=self.cls, reason=error.message)

    def send_message(self, payload: bytes | memoryview) -> int:
        n = super().send_message(payload)
        self.bytes_out += len(payload) * n
        return n

    def stats(self) -> dict:
        """``{iid, tag, kind, cls, addr, peers, msgs_in, msgs_out, bytes_in, bytes_out, dropped}``."""
        return {"iid": self.iid, "tag": self.tag, "kind": self.kind, "cls": self.cls, "addr": self.addr,
                "peers": len(self.peers), "msgs_in": self.msgs_in, "msgs_out": self.msgs_out,
                "bytes_in": self.bytes_in, "bytes_out": self.bytes_out, "dropped": self.dropped}


class PublisherInterface(BusInterface):
    """Publishes on topic ``addr`` every message a connected peer sends."""

    kind = Kind.PUBLISHER
    topic: Topic | None = None

    async def start(self) -> None:
        self.topic = self.bus.advertise(self.addr, self.cls, self.owner)
        await super().start()

    async def stop(self) -> None:
        await super().stop()
        self.bus.unadvertise(self.addr, self.owner)

    def on_message(self, payload: memoryview) -> None:
        self.msgs_in += 1
        self.bytes_in += len(payload)
        self.bus.publish(self.topic, payload)     # a view nobody writes again (rce.transport.framing): no copy


class SubscriberInterface(BusInterface):
    """Subscribes to topic ``addr`` (bounded by ``queue_size``) and sends each message to
    every connected peer; a message a saturated peer link refuses is dropped and counted."""

    kind = Kind.SUBSCRIBER
    sub: Subscription | None = None
    queue_size = DEFAULT_QUEUE

    async def start(self) -> None:
        self.sub = self.bus.subscribe(self.addr, self.cls, self._deliver, self.owner, self.queue_size)
        await super().start()

    async def stop(self) -> None:
        await super().stop()
        if self.sub is not None:
            self.bus.unsubscribe(self.sub)

    def _deliver(self, payload: bytes) -> bool:
        if not self.peers:
            return True            # nobody connected: nothing to lose
        return self.send_message(payload) == len(self.peers)


class ServiceClientInterface(BusInterface):
    """Executes calls from its peer against service ``addr`` on the bus."""

    kind = Kind.SERVICE_CLIENT
    call_timeout = SERVICE_TIMEOUT
    service_wait = SERVICE_WAIT

    async def serve(self, payload: bytes) -> bytes:
        self.msgs_in += 1
        self.bytes_in += len(payload)
        resp = await self.bus.call_service(self.addr, payload, self.cls, self.call_timeout, wait=self.service_wait)
        self.msgs_out += 1
        self.bytes_out += len(resp)
        return resp


class ServiceProviderInterface(BusInterface):
    """Provides service ``addr`` on the bus; every call goes to the connected peer. A call made
    before the interface is connected waits up to ``connect_wait`` s for it (a node may call as soon
    as it starts, before the robot's CX: a ROS 2 action client sends its goal once the action's
    services are there)."""

    kind = Kind.SERVICE_PROVIDER
    connect_wait = SERVICE_WAIT

    async def start(self) -> None:
        self._connected = asyncio.Event()
        self.bus.advertise_service(self.addr, self.cls, self._call, self.owner)
        await super().start()

    async def stop(self) -> None:
        await super().stop()
        self.bus.unadvertise_service(self.addr, self.owner)

    def on_peers_changed(self) -> None:
        if self.peers:
            self._connected.set()
        else:
            self._connected.clear()

    async def _call(self, payload: bytes) -> bytes:
        if not self.peers:
            try:
                async with asyncio.timeout(self.connect_wait):
                    await self._connected.wait()
            except TimeoutError:
                pass                     # call_peer says it is not connected
        self.bytes_out += len(payload)
        resp = await self.call_peer(payload)
        self.msgs_in += 1
        self.bytes_in += len(resp)
        return resp


KINDS: dict[Kind, type[BusInterface]] = {c.kind: c for c in (PublisherInterface, SubscriberInterface,
                                                             ServiceClientInterface, ServiceProviderInterface)}


def interface_kind(itype: str | InterfaceType) -> Kind:
    """``"PublisherInterface"`` (or a legacy name like ``"ServiceInterface"``) -> ``Kind.PUBLISHER``.

    Raises :class:`RequestError` for a robot-side type (Converter/Forwarder) and
    :class:`~rce.plumbing.errors.ProtocolError` for an unknown one."""
    return InterfaceType.parse(itype, robot_side=False).kind


def check_class(kind: Kind, cls: str, registry: MessageRegistry | None = None) -> str:
    """Validate the class of a ``kind`` interface and return its wire name.

    Message kinds need a message class, service kinds a service class; package types are
    (re)loaded once before refusing. Raises :class:`MessageError` naming the class."""
    reg = registry or default_registry()
    service = Kind(kind).service

    def lookup() -> str:
        if service:
            reg.srv_types(cls)
            return wire_name(store_name(cls))
        return wire_name(reg.msg_type(cls))
    try:
        return lookup()
    except MessageError:
        try:
            load_package_types(reg)   # a package installed since start may bring the class
        except MessageError:
            pass                      # a broken package elsewhere; the lookup below decides
    try:
        return lookup()
    except MessageError:
        what = "service" if service else "message"
        raise MessageError(f"unknown {what} class {cls!r} for a {kind}Interface") from None


def make_interface(plane: DataPlane, bus: Bus, cid: int, iid: int, tag: str, itype: str | InterfaceType, cls: str,
                   addr: str | None = None, registry: MessageRegistry | None = None) -> BusInterface:
    """Build (not start) the container-side interface for an ``add_interface`` op.

    ``addr`` defaults to ``/`` + the last part of ``tag`` (the interface tag). Raises
    :class:`MessageError` for an unknown class, :class:`RequestError` for a bad name or a
    robot-side type, :class:`~rce.plumbing.errors.ProtocolError` for an unknown type."""
    kind = interface_kind(itype)
    wire = check_class(kind, cls, registry)
    if not isinstance(tag, str) or not tag:
        raise RequestError("add_interface needs a non-empty 'tag'")
    name = resolve(addr, "/") if addr else resolve(tag.rsplit("/", 1)[-1], "/")
    return KINDS[kind](plane, bus, cid, iid, tag, wire, name)
