"""The ROS 2 relay of one container: ``python -m rce_container.ros2_relay --cid N``.

Started by :class:`rce_container.ros2_graph.Ros2Graph` in the container's sandbox, like a node,
in the container's ROS 2 graph (its domain id and discovery range in the environment). It is one
rclpy node and one bus node, both named :func:`~rce_container.ros2_plan.relay_name`, and bridges
the two with :func:`rce_container.ros2_plan.plan`:

- topics as raw CDR both ways (a ``raw=True`` subscription; ``Publisher.publish(bytes)``): between
  two ROS 2 ends the bytes are never re-encoded. What goes into ROS 2 is checked first (rclpy
  deserializes it): a message that is not the topic's type would stop the node reading it, so it
  is refused and counted instead;
- services both ways, each request and response deserialized and serialized at this edge (rclpy
  has no raw services). A service the relay provides in ROS 2 answers later, from the event loop
  (its response goes out with ``send_response`` when the bus answers), so a call that lasts (an
  action's ``get_result`` waits for its goal's end) holds no thread;
- with hidden names bridged like the others, an action is carried as its five parts; a goal goes
  through only once the relay's bridges of its feedback and status are matched in DDS, as an
  rclpy action client waits for its server (else its first feedback could be lost);
- QoS: its subscriptions take what the publishers offer, its publishers offer what the
  subscriptions need (:func:`~rce_container.ros2_plan.request_for`,
  :func:`~rce_container.ros2_plan.offer_for`), a bridge made again when that changes;
  subscriptions it cannot match are in ``incompatible`` (:meth:`Ros2Relay.stats`), and so is every
  incompatible-QoS event DDS reports on its endpoints;
- parameters: a change of the bus's parameters is set on the running ROS 2 nodes that declared
  them (their ``set_parameters`` service); at a node's start they come in its parameter file.

rclpy's executor spins in a thread of its own; the bus and the bridges' bookkeeping live on the
asyncio loop. Bounds: bus -> ROS 2 at most :data:`QUEUE_SIZE` messages wait for the publishing
thread; ROS 2 -> bus at most :data:`QUEUE_SIZE` wait for the loop; at most :data:`CALLS_IN_FLIGHT`
calls into the bus wait for their answer. Beyond, dropped (a call answered with an empty
response) and counted.
"""
from __future__ import annotations

import asyncio
import os
import queue
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

from rce.interfaces.actions import call_timeout, goal_topics
from rce.interfaces.qos import QoS
from rce.node import Publisher
from rce.plumbing.errors import RCEError
from rce.plumbing.log import get_logger
from rce_container import relay_base
from rce_container.relay_base import QUEUE_SIZE, RawNode
from rce_container.ros1_plan import bus_graph, flatten_params, param_changes
from rce_container.ros2_plan import plan, relay_name, ros2_parameters

log = get_logger("rce.container.ros2_relay")

CALLS_IN_FLIGHT = 1000   # calls from ROS 2 into the bus waiting for their answers; beyond, refused
SERVICE_WAIT = 5.0       # s a call waits for the relay's client to match the ROS 2 server
PARAM_WAIT = 5.0         # s each parameter call to a node may take
EXIT_WAIT = 0.5          # s the executor has to finish its callbacks at the relay's end
ECHO_MEMORY = 100        # own messages remembered per topic bridged both ways (to not send them back)


@dataclass
class TopicBridge:
    """One topic bridged: ``bus`` (the bus subscription's handle, or the bus publisher), ``ros``
    (the rclpy publisher or subscription), its ROS 2 ``type`` and ``qos``."""
    bus: Any
    ros: Any
    type: str
    qos: QoS


class Ros2Relay:
    """The bridges of one container between its bus (``bus``) and its ROS 2 graph (``node``, an
    rclpy node spun by an executor in another thread); see the module doc."""

    def __init__(self, bus: RawNode, node: Any, me: str):
        self.bus, self.node, self.me = bus, node, me
        self.loop = asyncio.get_running_loop()
        self.to_ros: dict[str, TopicBridge] = {}
        self.to_bus: dict[str, TopicBridge] = {}
        self.srv_to_bus: dict[str, tuple[int, Any]] = {}     # service -> (bus handle, rclpy client)
        self.srv_to_ros: dict[str, Any] = {}                 # service -> rclpy service
        self.bus_echo: dict[str, deque] = {}                 # what the relay put on the bus, per topic
        self.ros_echo: dict[str, deque] = {}                 # what it published into ROS 2, per topic
        self.pushed: dict[str, Any] | None = None            # ROS 2 parameters as last set on the nodes
        self.outbox: queue.Queue = queue.Queue(maxsize=QUEUE_SIZE)
        self.in_flight = threading.BoundedSemaphore(QUEUE_SIZE)   # ROS 2 -> bus messages not yet on the loop
        self.calls = threading.BoundedSemaphore(CALLS_IN_FLIGHT)
        self.counts = dict.fromkeys(("to_ros", "to_bus", "dropped_to_ros", "dropped_to_bus", "refused_to_ros",
                                     "calls", "call_errors", "syncs", "param_sets"), 0)
        self.problems: dict[str, str] = {}        # name -> why it is not bridged (the last sync)
        self.incompatible: dict[str, str] = {}    # topic -> which QoS the relay cannot match (the last sync)
        self.events: dict[str, str] = {}          # topic -> an incompatible-QoS event DDS reported
        self.params: dict[str, str] = {}          # parameter -> why it is not in ROS 2, or a node refused it
        self._known: dict[str, str] = {}
        self.lock = asyncio.Lock()
        self.stopping = asyncio.Event()
        threading.Thread(target=self._publish_thread, name="ros2 publisher", daemon=True).start()

    # -- bus -> ROS 2 --------------------------------------------------------------------------
    def _publish_thread(self) -> None:
        from rclpy.serialization import deserialize_message
        while True:
            pub, payload = self.outbox.get()
            try:
                deserialize_message(payload, pub.msg_type)     # a node must never take what it cannot read
            except Exception as e:
                self.counts["refused_to_ros"] += 1
                log.debug("refused into ROS 2", topic=pub.topic_name, reason=str(e))
                continue
            try:
                pub.publish(payload)
                self.counts["to_ros"] += 1
            except Exception as e:     # a publisher destroyed meanwhile
                self.counts["dropped_to_ros"] += 1
                log.debug("cannot publish into ROS 2", reason=str(e))

    async def _bridge_to_ros(self, topic: str, wire: str, qos: QoS) -> None:
        from rclpy.event_handler import PublisherEventCallbacks
        from rce.ros2.classes import qos_profile, rclpy_class
        events = PublisherEventCallbacks(incompatible_qos=lambda e: self._qos_event(topic, e, "publisher"))
        pub = self.node.create_publisher(rclpy_class(wire), topic, qos_profile(qos), event_callbacks=events)
        bus_echo, ros_echo = (d.setdefault(topic, deque(maxlen=ECHO_MEMORY)) for d in (self.bus_echo, self.ros_echo))

        def push(payload: bytes) -> None:
            if payload in bus_echo:          # what this relay put on the bus itself
                bus_echo.remove(payload)
                return
            if topic in self.to_bus:
                ros_echo.append(payload)
            try:
                self.outbox.put_nowait((pub, payload))
            except queue.Full:
                self.counts["dropped_to_ros"] += 1
        try:
            handle = await self.bus.raw_subscriber(topic, wire, push)
        except BaseException:
            self.node.destroy_publisher(pub)
            raise
        self.to_ros[topic] = TopicBridge(handle, pub, wire, qos)

    # -- ROS 2 -> bus --------------------------------------------------------------------------
    async def _bridge_to_bus(self, topic: str, wire: str, qos: QoS) -> None:
        from rclpy.event_handler import SubscriptionEventCallbacks
        from rce.ros2.classes import qos_profile, rclpy_class
        cls = rclpy_class(wire)
        bus_pub: Publisher = await self.bus.raw_publisher(topic, wire)
        bus_echo, ros_echo = (d.setdefault(topic, deque(maxlen=ECHO_MEMORY)) for d in (self.bus_echo, self.ros_echo))

        def forward(payload: bytes) -> None:
            self.in_flight.release()
            if payload in ros_echo:          # what this relay published into ROS 2 itself
                ros_echo.remove(payload)
                return
            if topic in self.to_ros:
                bus_echo.append(payload)
            if bus_pub.publish_nowait(payload):
                self.counts["to_bus"] += 1
            else:
                self.counts["dropped_to_bus"] += 1

        def on_message(payload: bytes) -> None:      # the executor's thread
            if not self.in_flight.acquire(blocking=False):
                self.counts["dropped_to_bus"] += 1
                return
            self.loop.call_soon_threadsafe(forward, payload)
        events = SubscriptionEventCallbacks(incompatible_qos=lambda e: self._qos_event(topic, e, "subscription"))
        try:
            sub = self.node.create_subscription(cls, topic, on_message, qos_profile(qos), raw=True,
                                                event_callbacks=events)
        except BaseException:
            await bus_pub.unregister()
            raise
        self.to_bus[topic] = TopicBridge(bus_pub, sub, wire, qos)

    def _qos_event(self, topic: str, event: Any, what: str) -> None:
        """DDS found a ROS 2 endpoint whose QoS does not match the relay's ``what`` on ``topic``."""
        from rclpy.qos import qos_policy_name_from_kind
        self.events[topic] = (f"DDS reports an incompatible {qos_policy_name_from_kind(event.last_policy_kind)} "
                              f"policy between the relay's {what} and a node's ({event.total_count} so far)")

    # -- services ------------------------------------------------------------------------------
    async def _service_to_bus(self, name: str, wire: str) -> None:
        """Provide ROS 2 service ``name`` (type ``wire``) on the bus."""
        from rclpy.serialization import deserialize_message, serialize_message
        from rce.ros2.classes import rclpy_class
        from rce_container.ros2_rclpy import call
        cls = rclpy_class(wire)
        client = self.node.create_client(cls, name)
        timeout = call_timeout(wire)

        async def handler(payload: bytes) -> bytes:
            self.counts["calls"] += 1
            try:
                request = deserialize_message(payload, cls.Request)
                await self._goal_topics_matched(name, self.to_bus, lambda sub: sub.get_publisher_count())
                async with asyncio.timeout(timeout):
                    return serialize_message(await call(client, request, SERVICE_WAIT))
            except Exception as e:
                self.counts["call_errors"] += 1
                why = "no answer in time" if isinstance(e, TimeoutError) else f"{type(e).__name__}: {e}"
                raise RCEError(f"ROS 2 service {name} failed: {why}") from None
        try:
            self.srv_to_bus[name] = (await self.bus.raw_service(name, wire, handler), client)
        except BaseException:
            self.node.destroy_client(client)
            raise

    async def _service_to_ros(self, name: str, wire: str) -> None:
        """Provide bus service ``name`` (type ``wire``) in ROS 2; each call is answered when the
        bus answers it (module doc)."""
        from rclpy.serialization import serialize_message
        from rce.ros2.classes import rclpy_class
        cls = rclpy_class(wire)
        srv = self.node.create_service(cls, name, lambda request, _response: _LaterAnswer(serialize_message(request)))
        send = srv.send_response

        def send_response(response: Any, header: Any) -> None:      # the executor's thread
            if not isinstance(response, _LaterAnswer):
                send(response, header)
            elif not self.calls.acquire(blocking=False):
                self.counts["call_errors"] += 1
                send(cls.Response(), header)
            else:
                asyncio.run_coroutine_threadsafe(self._answer(name, wire, cls, response.payload,
                                                              lambda r: send(r, header)), self.loop)
        srv.send_response = send_response
        self.srv_to_ros[name] = srv

    async def _answer(self, name: str, wire: str, cls: Any, payload: bytes, send) -> None:
        """Call bus service ``name`` with a ROS 2 request and send its answer back into ROS 2; a call
        that fails is logged and answered with an empty response (a ROS 2 service has no errors)."""
        from rclpy.serialization import deserialize_message
        self.counts["calls"] += 1
        try:
            await self._goal_topics_matched(name, self.to_ros, lambda pub: pub.get_subscription_count())
            response = deserialize_message(await self.bus.raw_call(name, payload, call_timeout(wire)), cls.Response)
        except Exception as e:
            self.counts["call_errors"] += 1
            log.warning("bridged call failed", service=name, reason=e.message if isinstance(e, RCEError) else str(e))
            response = cls.Response()
        finally:
            self.calls.release()
        try:
            send(response)
        except Exception as e:        # the service destroyed meanwhile
            log.debug("answer not sent", service=name, reason=str(e))

    async def _goal_topics_matched(self, service: str, bridges: dict[str, TopicBridge],
                                   matched: Callable[[Any], int]) -> None:
        """Before a goal goes through an action's ``send_goal`` (``service``): wait up to
        :data:`SERVICE_WAIT` s until each of the relay's bridges (``bridges``, ``to_bus`` on the
        server's side, ``to_ros`` on the client's) of the action's feedback and status topics is
        matched in DDS (``matched`` of its rclpy endpoint above 0), as an rclpy action client
        waits for its server (:func:`~rce.interfaces.actions.goal_topics`). A bridge just made when
        the goal comes would otherwise miss the goal's first feedback. Past the wait, the goal goes
        on (a server that publishes none must still be reachable); any other service: no wait."""
        from rce_container.ros2_rclpy import holds_within
        ends = [bridges[t].ros for t in goal_topics(service) if t in bridges]
        if not await holds_within(lambda: all(matched(e) > 0 for e in ends), SERVICE_WAIT):
            log.warning("a goal goes on before its action's feedback and status are matched", service=service)

    # -- the sync ------------------------------------------------------------------------------
    async def sync(self) -> dict:
        """Look at both graphs, make and drop bridges, set changed parameters; returns :meth:`stats`."""
        from rce_container.ros2_rclpy import read_graph
        async with self.lock:
            ros = await asyncio.to_thread(read_graph, self.node, self.me)
            want = plan(bus_graph(await self.bus.describe()), ros, self.me)
            self._known, self.problems = self.problems, dict(want.conflicts)
            self.incompatible = dict(want.incompatible)
            await self._apply(want)
            nodes = {n for s, n in ros.services.items() if s == f"{n}/set_parameters"} - {self.me}
            await self._sync_params(sorted(nodes))
            self.counts["syncs"] += 1
            return self.stats()

    async def _apply(self, want) -> None:
        for table, wanted, drop in ((self.to_ros, want.to_ros, self._drop_to_ros),
                                    (self.to_bus, want.to_bus, self._drop_to_bus)):
            for topic in list(table):
                b = table[topic]
                if (b.type, b.qos) != wanted.get(topic, (None, None)):    # gone, or its QoS must change
                    await drop(topic)
        for name in set(self.srv_to_bus) - set(want.services_to_bus):
            handle, client = self.srv_to_bus.pop(name)
            await self.bus.unadvertise_service(handle)
            self.node.destroy_client(client)
        for name in set(self.srv_to_ros) - set(want.services_to_ros):
            self.node.destroy_service(self.srv_to_ros.pop(name))
        for wanted, table, make in ((want.to_ros, self.to_ros, self._bridge_to_ros),
                                    (want.to_bus, self.to_bus, self._bridge_to_bus)):
            for topic, (wire, qos) in wanted.items():
                if topic not in table:
                    await self._try(topic, make(topic, wire, qos))
        for name, wire in want.services_to_bus.items():
            if name not in self.srv_to_bus:
                await self._try(name, self._service_to_bus(name, wire))
        for name, wire in want.services_to_ros.items():
            if name not in self.srv_to_ros:
                await self._try(name, self._service_to_ros(name, wire))

    async def _drop_to_ros(self, topic: str) -> None:
        b = self.to_ros.pop(topic)
        await self.bus.unsubscribe(b.bus)
        self.node.destroy_publisher(b.ros)
        self.events.pop(topic, None)

    async def _drop_to_bus(self, topic: str) -> None:
        b = self.to_bus.pop(topic)
        self.node.destroy_subscription(b.ros)
        await b.bus.unregister()
        self.events.pop(topic, None)

    async def _try(self, name: str, make) -> None:
        """Make one bridge; a failure (a type without Python support, a service gone meanwhile) is
        recorded in ``problems`` and tried again on the next sync; the other bridges go on."""
        try:
            await make
        except Exception as e:
            why = e.message if isinstance(e, RCEError) else f"{type(e).__name__}: {e}"
            if self._known.get(name) != why:
                log.warning("cannot bridge", name=name, reason=why)
            self.problems[name] = why

    async def _sync_params(self, nodes: list[str]) -> None:
        """Set the parameters that changed on the bus since the last sync on ``nodes`` (those that
        declared them); the first sync only takes note (a node gets the parameters of its start)."""
        from rce_container.ros2_rclpy import set_parameters
        params, skipped = ros2_parameters(flatten_params(await self.bus.get_param("/", {})))
        if self.pushed is None:
            self.pushed = params
        to_set, _ = param_changes(params, self.pushed)
        refused: dict[str, str] = {}
        if to_set:
            results = await asyncio.gather(*(set_parameters(self.node, n, to_set, PARAM_WAIT) for n in nodes),
                                           return_exceptions=True)
            for n, r in zip(nodes, results, strict=True):
                if isinstance(r, BaseException):
                    log.warning("cannot set parameters", node=n, reason=f"{type(r).__name__}: {r}")
                    continue
                refused.update({name: f"{n} refused it: {why}" for name, why in r.items()})
            self.counts["param_sets"] += 1
        self.pushed.update(to_set)
        self.params = {**skipped, **refused}

    def stats(self) -> dict:
        """``{to_ros, to_bus, dropped_to_ros, dropped_to_bus, refused_to_ros, calls, call_errors, syncs,
        param_sets}`` (messages, calls, syncs since start), ``topics_to_ros``/``topics_to_bus``/
        ``services_to_bus``/``services_to_ros`` (the bridges now), ``problems`` ({name: why it is not
        bridged}), ``incompatible`` ({topic: which QoS the relay cannot match}), ``params`` ({name:
        why it is not a ROS 2 parameter, or which node refused it})."""
        return {**self.counts, "topics_to_ros": sorted(self.to_ros), "topics_to_bus": sorted(self.to_bus),
                "services_to_bus": sorted(self.srv_to_bus), "services_to_ros": sorted(self.srv_to_ros),
                "problems": dict(self.problems), "incompatible": {**self.events, **self.incompatible},
                "params": dict(self.params)}


class _LaterAnswer:
    """What a service callback of the relay returns: the request, answered later (module doc)."""

    def __init__(self, payload: bytes):
        self.payload = payload


async def serve(cid: int) -> None:
    """Join both graphs and relay until SIGTERM/SIGINT or the bus closes (:func:`relay_base.serve`)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    me = relay_name(cid)
    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)     # SIGTERM is the loop's
    node = rclpy.create_node(me.lstrip("/"), enable_rosout=False, start_parameter_services=False)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinning = threading.Thread(target=executor.spin, name="ros2 executor", daemon=True)
    spinning.start()

    async def make(bus: RawNode) -> Ros2Relay:
        return Ros2Relay(bus, node, me)

    def cleanup() -> None:        # Fast DDS removes its shared-memory segments with its participant,
        executor.shutdown(timeout_sec=EXIT_WAIT)      # once the executor no longer waits on the node
        spinning.join(EXIT_WAIT)
        node.destroy_node()
        rclpy.shutdown()
    await relay_base.serve(me, make, cleanup, graph="ROS 2", domain=os.environ.get("ROS_DOMAIN_ID"))


def main(argv: list[str] | None = None) -> None:
    relay_base.main("rce_container.ros2_relay", "ROS 2", serve, argv)


if __name__ == "__main__":
    main()
