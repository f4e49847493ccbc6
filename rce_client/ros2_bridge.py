"""``rce-ros CONFIG --ros2``: the robot-side interfaces bridged to the robot's ROS 2 graph.

:class:`RclpyGraph` is the robot-side graph of :class:`rce_client.rce_ros.RobotBridge` when ``--ros2``
is given (instead of the local bus): one rclpy node named after the robot
(:func:`rce_client.ros2_types.node_name`) on the ROS 2 graph that ``ROS_DOMAIN_ID`` and
``ROS_AUTOMATIC_DISCOVERY_RANGE`` say, spun in a thread of its own (:mod:`rce_client.ros2_spin`).
Each robot-side interface is bridged at its ``addr`` (default ``/<iTag>``), a ROS 2 name, with the
QoS its config gives (:func:`rce_client.ros2_types.qos_profile`; none: rclpy's default):

- ``SubscriberConverter/Forwarder``: a subscription to topic ``addr`` whose messages go to the cloud;
- ``PublisherConverter/Forwarder``: a publisher on topic ``addr`` of what the cloud sends;
- ``ServiceProviderConverter/Forwarder``: a service server ``addr`` whose calls go to the cloud;
- ``ServiceClientConverter/Forwarder``: the cloud's calls go to the ROS 2 service ``addr`` (a client);
- an action (``ActionProvider*``/``ActionClient*``) is its five parts (:mod:`rce.interfaces.actions`):
  an unchanged rclpy ``ActionClient`` or ``ActionServer`` on the robot sees an action at ``addr``.

Topics carry the CDR bytes untouched (a ``raw=True`` subscription, ``Publisher.publish(bytes)``);
services are (de)serialized at this edge with ``rclpy.serialization`` (rclpy has no raw services).
A Forwarder hands the bytes to the cloud as they are; a Converter converts them with rce's message
registry (JSON <-> CDR), as on the local bus.

Messages go from rclpy's thread to the loop through a bounded handoff per interface
(:class:`rce_client.ros1_bridge.Handoff`, drops counted). A call from the robot's graph is a
coroutine callback that yields to the executor while the cloud answers (an action's get_result may
wait as long as its goal runs: :func:`rce.interfaces.actions.call_timeout`); a call that fails gets
no response (ROS 2 services have no error reply: the caller's timeout applies) and is logged and
counted, naming the interface. A QoS that does not match a peer on the robot's graph (rclpy's
``incompatible_qos`` events) is printed and logged, naming the interface, the topic and the policy;
messages the middleware reports lost (``message_lost``) are counted apart from the bridge's own drops,
as lost on the robot's graph: a ``keep_last`` depth (the topic's QoS) bounds what waits in DDS for
the bridge, and there, as in every ROS 2 subscription, a newer message replaces the oldest (Fast DDS
reports it when a reliable writer replaced samples a starved bridge had not acknowledged).
On close the node is destroyed, rclpy shut down, and the counts per interface printed.
"""
from __future__ import annotations

import asyncio
import os
from typing import Any, Awaitable, Callable

from rce.interfaces.actions import call_timeout
from rce.plumbing.errors import ConfigError, MessageError, RCEError, Unavailable
from rce.plumbing.log import get_logger
from rce_client.ros1_bridge import Counts, Handoff
from rce_client.ros2_spin import NoAnswer, Spinner, asyncio_future
from rce.ros2.classes import qos_profile
from rce_client.ros2_types import describe_qos, is_service_class, node_name, rclpy_class

log = get_logger("rce.ros.ros2")

CALLS_IN_FLIGHT = 64       # calls per service interface waiting at once (each goal of an action has a get_result)
SERVICE_WAIT = 10.0        # s the cloud's call waits for the robot's ROS 2 service to appear on the graph
SERVICE_POLL = 0.05        # s between looks at the graph while it waits
CLOSE_TIMEOUT = 5.0        # s to stop the executor and shut rclpy down


class RclpyGraph:
    """The robot-side graph of ``rce-ros --ros2`` (same calls as :class:`rce_client.rce_ros.LocalBusGraph`).

    :meth:`start` raises :class:`ConfigError` (rclpy not installed, a class in ROS 1's form, a class
    rclpy does not have, a message class where a service is meant) before anything is sent to the
    cloud. ``counts``: iTag -> :class:`Counts`; ``qos_incompatible``: iTag -> incompatible-QoS events."""

    def __init__(self, bridge: Any):
        self.bridge = bridge
        self.loop: asyncio.AbstractEventLoop | None = None
        self.spinner: Spinner | None = None
        self.counts: dict[str, Counts] = {}
        self.classes: dict[str, Any] = {}        # iTag -> rclpy message or service class
        self.qos_incompatible: dict[str, int] = {}
        self._clients: dict[str, Any] = {}       # iTag -> rclpy Client (ServiceClient*)
        self._calls: dict[str, int] = {}         # iTag -> calls in flight

    async def start(self) -> None:
        """Resolve every robot-side class, then start the node (and the clients of ServiceClient*)."""
        heard: dict[str, str] = {}           # topic -> the Subscriber* interface that takes it from the graph
        for k in self.bridge.kinds:
            self.classes[k.spec.iTag] = self._resolve(k)
            self.counts[k.spec.iTag] = Counts()
            if k.prefix == "Subscriber":
                heard[k.addr] = k.spec.iTag
        for k in self.bridge.kinds:
            if k.prefix == "Publisher" and k.addr in heard:
                raise ConfigError(f"{self.bridge.source}: interfaces {heard[k.addr]} and {k.spec.iTag} are both at "
                                  f"{k.addr}: on a ROS 2 graph the bridge would take what it publishes there and send "
                                  f"it to the cloud again (rclpy does not tell its own messages apart)")
        try:
            import rclpy  # noqa: F401
        except ImportError as e:
            raise ConfigError(f"--ros2: rclpy is not installed ({e}): install rce with its ros2 extra "
                              f"(pip install '.[ros2]', as make setup does)") from None
        self.loop = asyncio.get_running_loop()
        self.spinner = Spinner(node_name(self.bridge.cfg.robotID))
        try:
            self.spinner.start()
            node = self.spinner.node
            for k in self.bridge.kinds:
                if k.prefix == "ServiceClient":
                    self._clients[k.spec.iTag] = node.create_client(
                        self.classes[k.spec.iTag], k.addr, qos_profile=qos_profile(k.spec.qos),
                        callback_group=self.spinner.group)
        except Exception as e:        # rclpy's own (a name it refuses, rmw failing to start): nothing sent yet
            spinner, self.spinner = self.spinner, None
            await asyncio.to_thread(spinner.close, CLOSE_TIMEOUT)
            raise ConfigError(f"--ros2: rclpy could not start node {spinner.name}: {type(e).__name__}: {e}") from None
        domain = os.environ.get("ROS_DOMAIN_ID", "0")
        self.bridge.out(f"rce-ros: ROS 2 node {node.get_fully_qualified_name()} on domain {domain}")

    def _resolve(self, kind: Any) -> Any:
        itag, cls = kind.spec.iTag, kind.spec.iCls
        try:
            rcls = rclpy_class(itag, cls)
        except ConfigError as e:
            raise ConfigError(f"{self.bridge.source}: {e.message}") from None
        service = kind.prefix in ("ServiceClient", "ServiceProvider")
        if service != is_service_class(rcls):
            raise ConfigError(f"{self.bridge.source}: interface {itag} ({cls}): a {kind.spec.iType} needs a "
                              f"{'service' if service else 'message'} class")
        return rcls

    async def close(self) -> None:
        """Stop the executor, destroy the node, shut rclpy down, print the counts."""
        if self.spinner is None:
            return
        spinner, self.spinner = self.spinner, None
        await asyncio.to_thread(spinner.close, CLOSE_TIMEOUT)
        for itag, c in self.counts.items():
            qos = self.qos_incompatible.get(itag)
            self.bridge.out(f"rce-ros: ROS 2 {itag}: {c.from_ros} from ROS 2, {c.to_ros} to ROS 2, "
                            f"{c.dropped} dropped, {c.bad} failed" + (f", {c.lost} lost on the robot's graph"
                                                                      if c.lost else "")
                            + (f", {qos} QoS incompatible" if qos else ""))
        if spinner.callback_errors:
            self.bridge.out(f"rce-ros: ROS 2: {spinner.callback_errors} rclpy callback(s) failed (see the log)")

    # -- QoS ---------------------------------------------------------------------------------
    def _events(self, kind: Any, publisher: bool) -> Any:
        """rclpy's event callbacks of ``kind``'s publisher or subscription, handed to the loop: an
        incompatible QoS to :meth:`_report_qos`; messages the middleware reports lost (a subscription)
        to :meth:`_report_lost`."""
        from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks

        def in_loop(fn: Callable[..., None], *args: Any) -> None:
            try:
                self.loop.call_soon_threadsafe(fn, *args)
            except RuntimeError:          # the loop is closed: rce-ros is exiting
                pass

        def on_qos(event: Any) -> None:
            in_loop(self._report_qos, kind, publisher, event.total_count, event.total_count_change,
                    event.last_policy_kind)
        if publisher:
            return PublisherEventCallbacks(incompatible_qos=on_qos)
        return SubscriptionEventCallbacks(incompatible_qos=on_qos, message_lost=lambda event: in_loop(
            self._report_lost, kind, event.total_count_change))

    def _report_lost(self, kind: Any, lost: int) -> None:
        self.counts[kind.spec.iTag].add(lost=lost)
        log.warning("messages lost on the robot's graph before the bridge took them", itag=kind.spec.iTag,
                    topic=kind.addr, lost=lost)

    def _report_qos(self, kind: Any, publisher: bool, total: int, change: int, policy: Any) -> None:
        itag = kind.spec.iTag
        self.qos_incompatible[itag] = self.qos_incompatible.get(itag, 0) + change
        name = getattr(policy, "name", str(policy)).removeprefix("RMW_QOS_POLICY_")   # rmw's RMW_QOS_POLICY_...
        peer = "a subscription" if publisher else "a publisher"
        mine = "publisher" if publisher else "subscription"
        self.bridge.out(f"rce-ros: ROS 2 {itag}: QoS incompatible with {peer} on {kind.addr} ({name}; "
                        f"{total} in all): the bridge's {mine} is {describe_qos(kind.spec.qos)}; nothing flows "
                        f"between them (set the interface's qos in the config)")
        log.warning("incompatible QoS on the robot's graph", itag=itag, topic=kind.addr, policy=name,
                    side=mine, qos=describe_qos(kind.spec.qos), total=total)

    # -- topics ------------------------------------------------------------------------------
    def subscribe(self, kind: Any, deliver: Callable[[bytes], bool]) -> None:
        """ROS 2 topic ``k.addr`` -> ``deliver`` (in the loop), the CDR bytes untouched."""
        handoff = Handoff(self.loop, deliver, self.counts[kind.spec.iTag])
        self.spinner.node.create_subscription(
            self.classes[kind.spec.iTag], kind.addr, handoff.offer, qos_profile(kind.spec.qos),
            callback_group=self.spinner.group, event_callbacks=self._events(kind, False), raw=True)

    def advertise(self, kind: Any) -> Callable[[bytes], None]:
        """A publisher on ROS 2 topic ``k.addr``; returns its publish function (CDR bytes)."""
        counts = self.counts[kind.spec.iTag]
        pub = self.spinner.node.create_publisher(
            self.classes[kind.spec.iTag], kind.addr, qos_profile(kind.spec.qos),
            callback_group=self.spinner.group, event_callbacks=self._events(kind, True))

        def publish(payload: bytes) -> None:
            try:
                pub.publish(payload if type(payload) is bytes else bytes(payload))
                counts.add(to_ros=1)
            except Exception as e:         # rclpy shut down, or the publisher destroyed
                counts.add(dropped=1)
                log.warning("message not published to ROS 2", itag=kind.spec.iTag, topic=kind.addr,
                            reason=f"{type(e).__name__}: {e}")
        return publish

    # -- services ----------------------------------------------------------------------------
    def advertise_service(self, kind: Any, handler: Callable[[bytes], Awaitable[bytes]]) -> None:
        """Serve ROS 2 service ``k.addr``: each call's request (CDR) goes to ``handler`` in the loop, whose
        response (CDR) answers it. The rclpy callback waits without blocking the executor."""
        from rclpy.serialization import serialize_message
        spinner, loop = self.spinner, self.loop

        async def serve(request: Any, _response: Any) -> Any:
            fut = asyncio.run_coroutine_threadsafe(self._from_ros_call(kind, handler, serialize_message(request)), loop)
            answer = (await spinner.rclpy_future(fut)).result()
            if answer is None:
                raise NoAnswer(kind.addr)
            return answer
        spinner.node.create_service(self.classes[kind.spec.iTag], kind.addr, serve,
                                    qos_profile=qos_profile(kind.spec.qos), callback_group=spinner.group)

    async def _from_ros_call(self, kind: Any, handler: Callable[[bytes], Awaitable[bytes]], payload: bytes) -> Any:
        """One call from the robot's graph, in the loop: the response object, or None (logged, counted)."""
        from rclpy.serialization import deserialize_message
        itag, cls = kind.spec.iTag, kind.spec.iCls
        counts = self.counts[itag]
        counts.add(from_ros=1)
        if self._calls.get(itag, 0) >= CALLS_IN_FLIGHT:
            counts.add(dropped=1)
            log.warning("ROS 2 service call not answered", itag=itag, service=kind.addr,
                        reason=f"{CALLS_IN_FLIGHT} calls already in flight")
            return None
        self._calls[itag] = self._calls.get(itag, 0) + 1
        timeout = call_timeout(cls)
        try:
            async with asyncio.timeout(timeout):
                resp = await handler(payload)
            return deserialize_message(resp, self.classes[itag].Response)
        except RCEError as e:
            reason = e.message
        except TimeoutError:
            reason = f"no answer from the cloud within {timeout:g} s"
        except Exception as e:          # rclpy's deserialization (RuntimeError), or the loop closing
            reason = f"the cloud's response does not decode as {cls}: {e}" if isinstance(e, RuntimeError) \
                else f"{type(e).__name__}: {e}"
        finally:
            self._calls[itag] -= 1
        counts.add(bad=1)
        log.warning("ROS 2 service call not answered", itag=itag, service=kind.addr, cls=cls, reason=reason)
        return None

    async def call_service(self, kind: Any, payload: bytes) -> bytes:
        """Call ROS 2 service ``k.addr`` with a CDR request; returns the CDR response. Raises
        :class:`MessageError` (the request does not decode as the interface's class),
        :class:`Unavailable` (``CALLS_IN_FLIGHT`` calls running, the service not on the graph within
        ``SERVICE_WAIT`` s, no answer within the class's call timeout)."""
        from rclpy.serialization import deserialize_message, serialize_message
        itag, cls = kind.spec.iTag, kind.spec.iCls
        counts, client = self.counts[itag], self._clients[itag]
        if self._calls.get(itag, 0) >= CALLS_IN_FLIGHT:
            counts.add(dropped=1)
            raise Unavailable(f"ROS 2 service {kind.addr} (interface {itag}): {CALLS_IN_FLIGHT} calls already in "
                              f"flight")
        try:
            request = deserialize_message(bytes(payload), self.classes[itag].Request)
        except RuntimeError as e:
            counts.add(bad=1)
            raise MessageError(f"interface {itag}: a request from the cloud does not decode as {cls}: {e}") from None
        self._calls[itag] = self._calls.get(itag, 0) + 1
        counts.add(to_ros=1)
        rfut = None
        try:
            await self._until_service(kind, client)
            rfut = client.call_async(request)
            timeout = call_timeout(cls)
            try:
                async with asyncio.timeout(timeout):
                    resp = await asyncio_future(rfut, self.loop)
            except TimeoutError:
                raise Unavailable(f"ROS 2 service {kind.addr} (interface {itag}): no answer within {timeout:g} s") \
                    from None
        except RCEError:
            counts.add(bad=1)
            raise
        finally:
            self._calls[itag] -= 1
            if rfut is not None and not rfut.done():
                client.remove_pending_request(rfut)      # a late response finds no one waiting
        counts.add(from_ros=1)
        return serialize_message(resp)

    async def _until_service(self, kind: Any, client: Any) -> None:
        """Wait up to ``SERVICE_WAIT`` s for service ``k.addr`` on the robot's graph; :class:`Unavailable` if not."""
        deadline = self.loop.time() + SERVICE_WAIT
        while not client.service_is_ready():
            if self.loop.time() >= deadline:
                raise Unavailable(f"ROS 2 service {kind.addr} (interface {kind.spec.iTag}) is not on the robot's "
                                  f"graph (waited {SERVICE_WAIT:g} s)")
            await asyncio.sleep(SERVICE_POLL)

