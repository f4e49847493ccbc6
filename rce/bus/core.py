"""The bus core: topics, services, parameters and nodes of one ROS-like graph.

One implementation, two uses: the environment of a container (its nodes and
container-side interfaces) and the robot's local bus under ``rce-ros`` (local
programs and the robot-side interfaces). In-process users call it directly;
node processes reach it through :mod:`rce.bus.server` over a Unix socket.

Payloads are ROS 1 serialized bytes; the bus never decodes them. Every
subscription has a bound (``queue_size`` messages in flight to a remote node,
or the subscriber's own queue) and counts what it drops.
"""
from __future__ import annotations

import asyncio
import itertools
from collections.abc import Collection
from dataclasses import dataclass, field
from operator import attrgetter
from typing import Any, Awaitable, Callable

from rce.plumbing.errors import MessageError, NotFound, RequestError, Timeout
from rce.interfaces.naming import validate_name

Deliver = Callable[[bytes | memoryview], bool]    # returns False when the message was dropped; a view stays valid
ServiceHandler = Callable[[bytes], Awaitable[bytes]]
SERVICE_TIMEOUT = 30.0   # s a service call waits for its provider unless the caller says otherwise


@dataclass(eq=False)
class Subscription:
    """One subscriber of a topic: ``deliver(payload)`` is called for every message."""
    topic: "Topic"
    deliver: Deliver
    owner: str
    queue_size: int
    received: int = 0
    dropped: int = 0


@dataclass(eq=False)
class Topic:
    """A topic: its type (wire name), publishers (owner -> count), subscriptions and counters."""
    name: str
    type: str
    publishers: dict[str, int] = field(default_factory=dict)
    subscriptions: list[Subscription] = field(default_factory=list)
    messages: int = 0
    bytes: int = 0

    @property
    def dropped(self) -> int:
        return sum(s.dropped for s in self.subscriptions)


@dataclass(eq=False)
class Service:
    """A service: its type (wire name), provider owner and handler."""
    name: str
    type: str
    owner: str
    handler: ServiceHandler
    calls: int = 0
    errors: int = 0


class Bus:
    """Topics, services, parameters and nodes of one graph (all names global, resolved by callers)."""

    def __init__(self, name: str = "bus"):
        self.name = name
        self.topics: dict[str, Topic] = {}
        self.services: dict[str, Service] = {}
        self.params: dict[str, Any] = {}
        self.nodes: dict[str, dict] = {}          # node name -> info (pid, ...)
        self.on_change: list[Callable[[], None]] = []
        self.on_graph: list[Callable[[], None]] = []   # a topic's publishers or subscriptions changed
        self._ids = itertools.count(1)
        self._service_added: asyncio.Event | None = None

    # -- topics --------------------------------------------------------------------------------
    def _topic(self, name: str, type_: str) -> Topic:
        validate_name(name, "topic name")
        t = self.topics.get(name)
        if t is None:
            t = self.topics[name] = Topic(name, type_)
        elif t.type != type_:
            raise MessageError(f"topic {name!r} has type {t.type!r}, not {type_!r}")
        return t

    def advertise(self, name: str, type_: str, owner: str) -> Topic:
        """Register ``owner`` as a publisher of ``name`` with type ``type_`` (wire name).

        Raises :class:`MessageError` if the topic exists with another type."""
        t = self._topic(name, type_)
        t.publishers[owner] = t.publishers.get(owner, 0) + 1
        self._graph_changed()
        return t

    def unadvertise(self, name: str, owner: str) -> None:
        """Drop one publisher registration of ``owner`` on ``name`` (no error if absent)."""
        t = self.topics.get(name)
        if t and owner in t.publishers:
            t.publishers[owner] -= 1
            if t.publishers[owner] <= 0:
                del t.publishers[owner]
            self._gc(t)
            self._graph_changed()

    def subscribe(self, name: str, type_: str, deliver: Deliver, owner: str, queue_size: int = 100) -> Subscription:
        """Subscribe ``deliver`` to ``name``. Raises :class:`MessageError` on a type mismatch."""
        t = self._topic(name, type_)
        sub = Subscription(t, deliver, owner, max(1, int(queue_size)))
        t.subscriptions.append(sub)
        self._graph_changed()
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        """Remove a subscription (no error if already removed)."""
        if sub in sub.topic.subscriptions:
            sub.topic.subscriptions.remove(sub)
            self._gc(sub.topic)
            self._graph_changed()

    def _graph_changed(self) -> None:
        for cb in self.on_graph:
            cb()

    def _gc(self, topic: Topic) -> None:
        if not topic.publishers and not topic.subscriptions and self.topics.get(topic.name) is topic:
            del self.topics[topic.name]

    def publish(self, topic: Topic, payload: bytes | memoryview, skip: Collection[Subscription] = ()) -> int:
        """Deliver ``payload`` (a serialized message; a view must stay valid: subscribers may keep
        it) to every subscriber of ``topic`` but those in ``skip`` (its publisher reached them
        directly); returns how many took it."""
        topic.messages += 1
        topic.bytes += len(payload)
        n = 0
        for sub in topic.subscriptions:
            if skip and sub in skip:
                continue
            if sub.deliver(payload):
                sub.received += 1
                n += 1
            else:
                sub.dropped += 1
        return n

    # -- services ------------------------------------------------------------------------------
    def advertise_service(self, name: str, type_: str, handler: ServiceHandler, owner: str) -> Service:
        """Provide service ``name``. Raises :class:`RequestError` if another owner provides it."""
        validate_name(name, "service name")
        s = self.services.get(name)
        if s is not None and s.owner != owner:
            raise RequestError(f"service {name!r} is already provided by {s.owner!r}")
        s = self.services[name] = Service(name, type_, owner, handler)
        if self._service_added is not None:
            self._service_added.set()
            self._service_added = None
        return s

    def unadvertise_service(self, name: str, owner: str) -> None:
        """Withdraw service ``name`` if ``owner`` provides it."""
        s = self.services.get(name)
        if s and s.owner == owner:
            del self.services[name]

    async def wait_for_service(self, name: str, timeout: float) -> Service | None:
        """The service ``name`` once provided (like ``rospy.wait_for_service``), or None after
        ``timeout`` s."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while (s := self.services.get(name)) is None:
            left = deadline - loop.time()
            if left <= 0:
                return None
            if self._service_added is None:
                self._service_added = asyncio.Event()
            try:
                async with asyncio.timeout(left):
                    await self._service_added.wait()
            except TimeoutError:
                return None
        return s

    async def call_service(self, name: str, payload: bytes, type_: str | None = None,
                           timeout: float | None = SERVICE_TIMEOUT, wait: float = 0.0) -> bytes:
        """Call service ``name`` with a serialized request; returns the serialized response.
        ``wait``: s to wait for the service to be provided (a node may still be starting).

        Raises :class:`NotFound` (no such service), :class:`MessageError` (type mismatch),
        :class:`Timeout` (after ``timeout`` s) or the provider's error."""
        s = self.services.get(name)
        if s is None and wait > 0:
            s = await self.wait_for_service(name, wait)
        if s is None:
            raise NotFound(f"service {name!r} is not provided on {self.name}"
                           + (f" (waited {wait:g} s)" if wait > 0 else ""))
        if type_ is not None and type_ != s.type:
            raise MessageError(f"service {name!r} has type {s.type!r}, not {type_!r}")
        s.calls += 1
        try:
            async with asyncio.timeout(timeout):
                return await s.handler(payload)
        except TimeoutError:
            s.errors += 1
            raise Timeout(f"service {name!r} did not answer within {timeout:g} s") from None
        except Exception:
            s.errors += 1
            raise

    # -- parameters ----------------------------------------------------------------------------
    def set_param(self, name: str, value: Any) -> None:
        """Set parameter ``name`` (global name) to a JSON value; a dict sets a subtree.

        As on the ROS parameter server, the new value replaces whatever was at ``name`` (a
        value or a whole subtree) and a value on the path above it."""
        validate_name(name, "parameter name")
        name = "/" + name.strip("/")
        leaves: dict[str, Any] = {}
        _flatten(name, value, leaves)
        prefix = name.rstrip("/") + "/"
        for k in [k for k in self.params if k == name or k.startswith(prefix) or name.startswith(k + "/")]:
            del self.params[k]
        self.params.update(leaves)

    def get_param(self, name: str) -> Any:
        """Value of ``name``, or a dict of the subtree under it. Raises :class:`NotFound`."""
        name = "/" + name.strip("/")
        if name in self.params:
            return self.params[name]
        prefix = name.rstrip("/") + "/"
        sub = {k[len(prefix):]: v for k, v in self.params.items() if k.startswith(prefix) or prefix == "//"}
        if prefix == "//":
            sub = {k[1:]: v for k, v in self.params.items()}
        if not sub:
            raise NotFound(f"parameter {name!r} is not set")
        tree: dict = {}
        for k, v in sub.items():
            node = tree
            *path, leaf = k.split("/")
            for p in path:
                node = node.setdefault(p, {})
            node[leaf] = v
        return tree

    def delete_param(self, name: str) -> None:
        """Delete ``name`` (and its subtree). Raises :class:`NotFound` if nothing was set."""
        name = "/" + name.strip("/")
        keys = [k for k in self.params if k == name or k.startswith(name + "/")]
        if not keys:
            raise NotFound(f"parameter {name!r} is not set")
        for k in keys:
            del self.params[k]

    # -- introspection -------------------------------------------------------------------------
    def describe(self) -> dict:
        """Topics, services, parameters and nodes with their counters (for status and tools)."""
        return {
            "topics": [{"name": t.name, "type": t.type, "publishers": sorted(t.publishers),
                        "subscribers": sorted({s.owner for s in t.subscriptions}),
                        "messages": t.messages, "bytes": t.bytes, "dropped": t.dropped}
                       for t in sorted(self.topics.values(), key=attrgetter("name"))],
            "services": [{"name": s.name, "type": s.type, "provider": s.owner, "calls": s.calls,
                          "errors": s.errors} for s in sorted(self.services.values(), key=attrgetter("name"))],
            "params": sorted(self.params),
            "nodes": [{"name": n, **info} for n, info in sorted(self.nodes.items())],
        }


def _flatten(name: str, value: Any, out: dict[str, Any]) -> None:
    """Leaves of ``value`` under ``name`` (a dict is a subtree); checks every key is a legal name."""
    if isinstance(value, dict):
        for k, v in value.items():
            child = f"{name.rstrip('/')}/{k}"
            validate_name(child, "parameter name")
            _flatten(child, v, out)
    else:
        out[name] = value
