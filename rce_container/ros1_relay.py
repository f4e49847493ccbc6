"""The ROS 1 relay of one container: ``python -m rce_container.ros1_relay --cid N``.

Started by :class:`rce_container.ros1_graph.Ros1Graph` in the container's sandbox, like a
node, next to the container's own rosmaster (``ROS_MASTER_URI``). It is a node of both graphs,
named :func:`~rce_container.ros1_plan.relay_name` on each, and moves serialized ROS 1 bytes
between them untouched (``rospy.AnyMsg`` and the raw classes of
:mod:`rce.messages.ros1_types`; the bus never decodes either):

- every :data:`~rce_container.relay_base.POLL_INTERVAL` s, and whenever its ``sync`` service is
  called (:func:`rce_container.relay_base.run`), it reads both
  graphs (rosmaster's ``getSystemState``/``getTopicTypes``, the bus's ``describe``) and makes the
  bridges :func:`rce_container.ros1_plan.plan` asks for: topics bus -> ROS 1 and ROS 1 -> bus,
  services ROS 1 -> bus (type and MD5 sum probed from the service, as ``rosservice`` does) and
  bus -> ROS 1 (type and MD5 sum from :func:`rce.messages.ros1_types.service_identity`);
- it copies the bus's parameters to rosmaster (``rospy.get_param`` in a ROS 1 node sees the
  parameters a robot sets with CN ``setParam``);
- its bus service ``<relay name>/sync`` (request and response are bytes: empty, then the JSON
  of :meth:`Ros1Relay.stats`) syncs at once; the environment calls it before a ROS 1 node starts and
  after a parameter changes.

Bounds: bus -> ROS 1 messages wait in one queue of :data:`~rce_container.relay_base.QUEUE_SIZE`
for the publishing thread; ROS 1 -> bus at most as many wait for the event loop; beyond, they are
dropped and counted (:meth:`Ros1Relay.stats`).
"""
from __future__ import annotations

import asyncio
import os
import queue
import threading
import time
import warnings
from collections import deque
from typing import Any

from rce.plumbing.errors import RCEError, Unavailable
from rce.plumbing.log import get_logger
from rce.messages import default_registry
from rce.node import Publisher
from rce.node.package_path import load_package_types
from rce.messages.debian_ros1 import import_rospy
from rce.messages.ros1_types import (Ros1Message, Ros1Service, message_identity, raw_message_class,
                                   raw_service_class, service_identity)
from rce_container import relay_base
from rce_container.relay_base import QUEUE_SIZE, RawNode
from rce_container.ros1_plan import bus_graph, flatten_params, param_changes, plan, relay_name, ros1_graph

log = get_logger("rce.container.ros1_relay")

MASTER_WAIT = 20.0       # s the relay waits for its rosmaster to answer before giving up
MASTER_POLL = 0.05       # s between two tries to reach it
SERVICE_TIMEOUT = 30.0   # s a bridged service call may take (rospy's client has no timeout of its own)
ECHO_MEMORY = 100        # own messages remembered per topic bridged both ways (to not send them back)


def wait_for_master(master: Any, timeout: float = MASTER_WAIT) -> None:
    """Return once rosmaster answers ``getPid``; raises :class:`Unavailable` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            master.getPid()
            return
        except Exception as e:    # connection refused while it starts, or an XML-RPC fault
            if time.monotonic() > deadline:
                raise Unavailable(f"rosmaster at {os.environ.get('ROS_MASTER_URI')} did not answer within "
                                  f"{timeout:g} s: {e}") from None
        time.sleep(MASTER_POLL)


class Ros1Relay:
    """The bridges of one container between its bus (``node``) and its ROS 1 graph (module doc)."""

    def __init__(self, node: RawNode, me: str):
        self.rospy = import_rospy()
        import rosgraph
        self.node, self.me = node, me
        self.master = rosgraph.Master(me)
        self.registry = default_registry()
        load_package_types(self.registry)
        self.loop = asyncio.get_running_loop()
        self.to_ros: dict[str, tuple[int, Any]] = {}         # topic -> (bus subscription, rospy publisher)
        self.to_bus: dict[str, tuple[Any, Publisher]] = {}   # topic -> (rospy subscriber, bus publisher)
        self.srv_to_bus: dict[str, int] = {}                 # service -> bus handle
        self.srv_to_ros: dict[str, Any] = {}                 # service -> rospy.Service
        self.echo: dict[str, deque] = {}
        self.pushed: dict[str, Any] = {}
        self.outbox: queue.Queue = queue.Queue(maxsize=QUEUE_SIZE)
        self.in_flight = threading.BoundedSemaphore(QUEUE_SIZE)   # ROS 1 -> bus messages not yet on the bus
        self.counts = dict.fromkeys(("to_ros", "to_bus", "dropped_to_ros", "dropped_to_bus", "calls",
                                     "call_errors", "syncs"), 0)
        self.problems: dict[str, str] = {}                  # what could not be bridged in the last sync, and why
        self._known: dict[str, str] = {}                    # the same of the sync before (logged once)
        self.lock = asyncio.Lock()
        self.stopping = asyncio.Event()
        threading.Thread(target=self._publish_thread, name="ros1 publisher", daemon=True).start()

    # -- bus -> ROS 1 --------------------------------------------------------------------------
    def _publish_thread(self) -> None:
        while True:
            pub, msg = self.outbox.get()
            try:
                pub.publish(msg)
                self.counts["to_ros"] += 1
            except Exception as e:     # a publisher unregistered meanwhile, or a closed connection
                self.counts["dropped_to_ros"] += 1
                log.debug("cannot publish into ROS 1", reason=str(e))

    async def _bridge_to_ros(self, topic: str, wire: str) -> None:
        cls = raw_message_class(message_identity(wire, self.registry))
        with warnings.catch_warnings():          # rospy warns of synchronous publishers: ours is on purpose
            warnings.simplefilter("ignore", SyntaxWarning)
            pub = self.rospy.Publisher(topic, cls, queue_size=None)  # synchronous: drops are ours, counted
        echo = self.echo.setdefault(topic, deque(maxlen=ECHO_MEMORY))

        def push(payload: bytes) -> None:
            if payload in echo:          # what this relay published on the bus itself
                echo.remove(payload)
                return
            try:
                self.outbox.put_nowait((pub, cls.wrap(payload)))
            except queue.Full:
                self.counts["dropped_to_ros"] += 1
        self.to_ros[topic] = (await self.node.raw_subscriber(topic, wire, push), pub)

    # -- ROS 1 -> bus --------------------------------------------------------------------------
    async def _bridge_to_bus(self, topic: str, wire: str) -> None:
        bus_pub = await self.node.raw_publisher(topic, wire)
        echo = self.echo.setdefault(topic, deque(maxlen=ECHO_MEMORY))

        def forward(payload: bytes) -> None:
            self.in_flight.release()
            if topic in self.to_ros:
                echo.append(payload)
            if bus_pub.publish_nowait(payload):
                self.counts["to_bus"] += 1
            else:
                self.counts["dropped_to_bus"] += 1

        def on_message(msg: Any) -> None:       # a rospy thread
            if msg._connection_header.get("callerid") == self.me:
                return
            if not self.in_flight.acquire(blocking=False):
                self.counts["dropped_to_bus"] += 1
                return
            self.loop.call_soon_threadsafe(forward, msg._buff)
        sub = self.rospy.Subscriber(topic, self.rospy.AnyMsg, on_message, queue_size=QUEUE_SIZE)
        self.to_bus[topic] = (sub, bus_pub)

    # -- services ------------------------------------------------------------------------------
    async def _service_to_bus(self, name: str) -> None:
        """Provide ROS 1 service ``name`` on the bus, under the type and MD5 sum it declares."""
        import rosservice

        def probe() -> dict:
            return rosservice.get_service_headers(name, self.master.lookupService(name))
        h = await asyncio.to_thread(probe)
        req, resp = (Ros1Message(h["type"] + part, "*", "") for part in ("Request", "Response"))
        cls = raw_service_class(Ros1Service(h["type"], h["md5sum"], req, resp))

        def call(payload: bytes) -> bytes:
            proxy = self.rospy.ServiceProxy(name, cls)
            try:
                return proxy.call(cls._request_class.wrap(payload))._buff
            finally:
                proxy.close()

        async def handler(payload: bytes) -> bytes:
            self.counts["calls"] += 1
            try:
                async with asyncio.timeout(SERVICE_TIMEOUT):
                    return await asyncio.to_thread(call, payload)
            except Exception as e:
                self.counts["call_errors"] += 1
                raise RCEError(f"ROS 1 service {name} failed: {e}") from None
        self.srv_to_bus[name] = await self.node.raw_service(name, h["type"], handler)

    def _service_to_ros(self, name: str, wire: str) -> None:
        """Provide bus service ``name`` in the ROS 1 graph."""
        cls = raw_service_class(service_identity(wire, self.registry))

        def handler(req: Any) -> Any:            # a rospy thread
            self.counts["calls"] += 1
            fut = asyncio.run_coroutine_threadsafe(self.node.raw_call(name, req._buff, SERVICE_TIMEOUT), self.loop)
            try:
                return cls._response_class.wrap(fut.result(SERVICE_TIMEOUT))
            except Exception:
                self.counts["call_errors"] += 1
                raise
        self.srv_to_ros[name] = self.rospy.Service(name, cls, handler)

    # -- the sync ------------------------------------------------------------------------------
    def _ros_state(self) -> tuple[list, list]:
        return self.master.getSystemState(), self.master.getTopicTypes()

    async def sync(self) -> dict:
        """Look at both graphs, make and drop bridges, copy the parameters; returns :meth:`stats`."""
        async with self.lock:
            state, types = await asyncio.to_thread(self._ros_state)
            want = plan(bus_graph(await self.node.describe()), ros1_graph(state, types), self.me)
            self._known, self.problems = self.problems, dict(want.conflicts)
            await self._apply(want.to_ros, want.to_bus, want.services_to_bus, want.services_to_ros)
            await self._sync_params()
            self.counts["syncs"] += 1
            return self.stats()

    async def _apply(self, to_ros: dict, to_bus: dict, srv_bus: set, srv_ros: dict) -> None:
        for topic in set(self.to_ros) - set(to_ros):
            h, pub = self.to_ros.pop(topic)
            await self.node.unsubscribe(h)
            pub.unregister()
        for topic in set(self.to_bus) - set(to_bus):
            sub, bus_pub = self.to_bus.pop(topic)
            sub.unregister()
            await bus_pub.unregister()
        for name in set(self.srv_to_bus) - srv_bus:
            await self.node.unadvertise_service(self.srv_to_bus.pop(name))
        for name in set(self.srv_to_ros) - set(srv_ros):
            self.srv_to_ros.pop(name).shutdown()
        for what, table, make in ((to_ros, self.to_ros, self._bridge_to_ros),
                                  (to_bus, self.to_bus, self._bridge_to_bus)):
            for topic, wire in what.items():
                if topic not in table:
                    await self._try(topic, make(topic, wire))
        for name in srv_bus - set(self.srv_to_bus):
            await self._try(name, self._service_to_bus(name))
        for name, wire in srv_ros.items():
            if name not in self.srv_to_ros:
                await self._try(name, asyncio.to_thread(self._service_to_ros, name, wire))

    async def _try(self, name: str, make) -> None:
        """Make one bridge; a failure (an unknown class, a service gone meanwhile) is recorded in
        ``problems`` and retried on the next sync, and the other bridges go on."""
        try:
            await make
        except Exception as e:
            why = e.message if isinstance(e, RCEError) else f"{type(e).__name__}: {e}"
            if self._known.get(name) != why:
                log.warning("cannot bridge", name=name, reason=why)
            self.problems[name] = why

    async def _sync_params(self) -> None:
        tree = await self.node.get_param("/", {})
        to_set, to_delete = param_changes(flatten_params(tree), self.pushed)

        def push() -> None:
            for k, v in to_set.items():
                self.master.setParam(k, v)
            for k in to_delete:
                self.master.deleteParam(k)
        await asyncio.to_thread(push)
        for k in to_delete:
            self.pushed.pop(k, None)
        self.pushed.update(to_set)

    def stats(self) -> dict:
        """``{to_ros, to_bus, dropped_to_ros, dropped_to_bus, calls, call_errors, syncs}`` (messages,
        calls, syncs since start), ``topics_to_ros``/``topics_to_bus``/``services_to_bus``/
        ``services_to_ros`` (the bridges now) and ``problems`` ({name: why it is not bridged})."""
        return {**self.counts, "topics_to_ros": sorted(self.to_ros), "topics_to_bus": sorted(self.to_bus),
                "services_to_bus": sorted(self.srv_to_bus), "services_to_ros": sorted(self.srv_to_ros),
                "problems": dict(self.problems)}


async def serve(cid: int) -> None:
    """Connect both graphs and relay until SIGTERM/SIGINT or the bus closes (:func:`relay_base.serve`)."""
    rospy = import_rospy()
    import rosgraph
    me = relay_name(cid)
    await asyncio.to_thread(wait_for_master, rosgraph.Master(me))
    rospy.init_node(me.lstrip("/"), disable_signals=True, disable_rosout=True)

    async def make(bus: RawNode) -> Ros1Relay:
        return Ros1Relay(bus, me)
    await relay_base.serve(me, make, graph="ROS 1", master=os.environ.get("ROS_MASTER_URI"))


def main(argv: list[str] | None = None) -> None:
    relay_base.main("rce_container.ros1_relay", "ROS 1", serve, argv)


if __name__ == "__main__":
    main()
