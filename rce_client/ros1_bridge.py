"""``rce-ros CONFIG --ros``: the robot-side interfaces bridged to a real ROS 1 graph.

:class:`RospyGraph` is the robot-side graph of :class:`rce_client.rce_ros.RobotBridge` when
``--ros`` is given (instead of the local bus): one rospy node (``rospy.init_node("rce_ros",
anonymous=True, disable_signals=True)``) on the ROS 1 master named by ``ROS_MASTER_URI``
(Debian's ros-comm, found by :func:`rce.messages.debian_ros1.import_rospy`). Each robot-side interface is bridged
at its ``addr`` (default ``/<iTag>``), which is a ROS 1 graph name:

- ``SubscriberConverter/Forwarder``: a ``rospy.Subscriber`` on topic ``addr``;
- ``PublisherConverter/Forwarder``: a ``rospy.Publisher`` on topic ``addr``;
- ``ServiceProviderConverter/Forwarder``: a ``rospy.Service`` ``addr`` whose calls go to the cloud;
- ``ServiceClientConverter/Forwarder``: the cloud's calls go to the ROS 1 service ``addr``
  (``rospy.ServiceProxy``).

The rospy classes are :mod:`rce.messages.ros1_types` raw classes (``rospy.AnyMsg`` with the real
type name, MD5 sum and definition): rospy moves the serialized bytes untouched. A Forwarder hands
them to the cloud as they are; a Converter converts them with rce's message registry (the same
codec and JSON forms as everywhere in rce). rospy calls back in its own threads: messages go to the
asyncio loop with ``loop.call_soon_threadsafe``, at most ``HANDOFF_LIMIT`` per interface in flight
(the rest are dropped and counted); service calls wait on the loop with ``SERVICE_CALL_TIMEOUT``.
A message that fails conversion is logged and counted (``bad``); the bridge goes on.
On close the node's topics and services are unregistered and rospy is shut down; the counts per
interface are printed.
"""
from __future__ import annotations

import asyncio
import logging
import os
import threading
from dataclasses import dataclass
from typing import Any, Awaitable, Callable

from rce.plumbing.errors import ConfigError, RCEError, RequestError, Unavailable
from rce.plumbing.log import get_logger
from rce.messages.debian_ros1 import import_rospy
from rce.messages.ros1_types import (message_identity, raw_message_class, raw_service_class, service_identity)

log = get_logger("rce.ros.ros1")

NODE_NAME = "rce_ros"          # base name of the rospy node (anonymous: rospy adds pid and time)
QUEUE_SIZE = 100               # messages, rospy's per-subscriber and per-publisher queue_size
HANDOFF_LIMIT = 100            # messages per interface on their way from rospy's threads to the loop
SERVICE_CALL_TIMEOUT = 30.0    # s a ROS 1 caller waits for the cloud, and the cloud for a ROS 1 service
CALLS_IN_FLIGHT = 8            # the cloud's calls to ROS 1 services running at once, per interface
MASTER_TIMEOUT = 10.0          # s to wait for the ROS 1 master to answer at start


@dataclass
class Counts:
    """What went through one bridged interface: ``to_ros`` / ``from_ros`` messages or calls,
    ``dropped`` (handoff full, a publish that failed, calls over ``CALLS_IN_FLIGHT``), ``bad``
    (calls that failed: conversion, the cloud's or the ROS 1 service's error, timeout), ``lost``
    (ROS 2 only: messages the robot's middleware reports lost before the bridge took them, e.g. a
    ``keep_last`` writer that replaced samples a starved bridge had not acknowledged: the graph's
    QoS at work, not a drop of the bridge's).
    :meth:`add` is safe from rospy's threads."""
    from_ros: int = 0
    to_ros: int = 0
    dropped: int = 0
    bad: int = 0
    lost: int = 0

    def __post_init__(self) -> None:
        self._lock = threading.Lock()

    def add(self, **deltas: int) -> None:
        """Add to counters by name, e.g. ``add(from_ros=1, dropped=1)``."""
        with self._lock:
            for name, n in deltas.items():
                setattr(self, name, getattr(self, name) + n)


class Handoff:
    """rospy thread -> asyncio loop for one topic: ``offer(payload)`` from any thread schedules
    ``deliver(payload)`` in the loop with ``loop.call_soon_threadsafe``; at most ``limit`` payloads
    are in flight, the rest are dropped and counted in ``counts.dropped``."""

    def __init__(self, loop: asyncio.AbstractEventLoop, deliver: Callable[[bytes], Any], counts: Counts,
                 limit: int = HANDOFF_LIMIT):
        self.loop, self.deliver, self.counts, self.limit = loop, deliver, counts, limit
        self._lock = threading.Lock()
        self.in_flight = 0

    def offer(self, payload: bytes) -> bool:
        """Schedule ``payload`` for the loop; False (counted) when ``limit`` are in flight or the loop is closed."""
        with self._lock:
            full = self.in_flight >= self.limit
            if not full:
                self.in_flight += 1
        self.counts.add(from_ros=1, dropped=int(full))
        if full:
            return False
        try:
            self.loop.call_soon_threadsafe(self._run, payload)
            return True
        except RuntimeError:          # the loop is closed: rce-ros is exiting
            with self._lock:
                self.in_flight -= 1
            self.counts.add(dropped=1)
            return False

    def _run(self, payload: bytes) -> None:
        with self._lock:
            self.in_flight -= 1
        self.deliver(payload)


class RospyGraph:
    """The robot-side graph of ``rce-ros --ros`` (same calls as :class:`rce_client.rce_ros.LocalBusGraph`).

    :meth:`start` raises :class:`ConfigError` (rospy missing, ``ROS_MASTER_URI`` unset, a class with
    no ROS 1 identity) before anything is sent to the cloud, and :class:`Unavailable` when the
    master does not answer within ``MASTER_TIMEOUT`` s."""

    def __init__(self, bridge: Any):
        self.bridge = bridge
        self.rospy = import_rospy()
        self.loop: asyncio.AbstractEventLoop | None = None
        self.counts: dict[str, Counts] = {}
        self.classes: dict[str, type] = {}     # iTag -> raw message class or raw service class
        self._handles: list[Callable[[], None]] = []   # unregister a rospy Subscriber, Publisher, Service
        self._calls: dict[str, int] = {}       # iTag -> the cloud's calls to its ROS 1 service running now
        self._started = False

    async def start(self) -> None:
        """Resolve every robot-side class, check the master answers, and start the rospy node."""
        uri = os.environ.get("ROS_MASTER_URI")
        if not uri:
            raise ConfigError("--ros: ROS_MASTER_URI is not set (e.g. export ROS_MASTER_URI=http://localhost:11311)")
        for k in self.bridge.kinds:
            self.classes[k.spec.iTag] = self._resolve(k)
            self.counts[k.spec.iTag] = Counts()
        self.loop = asyncio.get_running_loop()
        await self._in_thread(self._check_master, uri, timeout=MASTER_TIMEOUT)
        await self._in_thread(self._init_node, timeout=MASTER_TIMEOUT)
        self._started = True
        self.bridge.out(f"rce-ros: ROS 1 node {self.rospy.get_name()} on the master at {uri}")

    def _resolve(self, kind: Any) -> type:
        reg, where = self.bridge.registry, f"{self.bridge.source}: interface {kind.spec.iTag} ({kind.spec.iCls})"
        try:
            if kind.prefix in ("ServiceClient", "ServiceProvider"):
                return raw_service_class(service_identity(kind.spec.iCls, reg))
            return raw_message_class(message_identity(kind.spec.iCls, reg))
        except ConfigError as e:
            raise ConfigError(f"{where}: {e.message}") from None

    def _check_master(self, uri: str) -> None:
        import rosgraph
        try:
            rosgraph.Master(f"/{NODE_NAME}", master_uri=uri).getPid()
        except Exception as e:        # socket errors, xmlrpc faults, rosgraph.MasterError
            raise Unavailable(f"--ros: the ROS 1 master at {uri} does not answer: {e}") from None

    def _init_node(self) -> None:
        """``rospy.init_node``, keeping rce's logging: rospy's ``configure_logging`` replaces the root
        logger's handlers with its log file (``fileConfig`` of ``python_logging.conf``); they are
        restored, and rospy's own loggers say only warnings and errors (to rce's stderr)."""
        root = logging.getLogger()
        handlers, level = root.handlers[:], root.level
        logging.getLogger("rospy").setLevel(logging.WARNING)
        try:
            self.rospy.init_node(NODE_NAME, argv=[], anonymous=True, disable_signals=True)
        finally:
            root.handlers[:] = handlers
            root.setLevel(level)

    async def _in_thread(self, fn: Callable, *args: Any, timeout: float, **kw: Any) -> Any:
        try:
            async with asyncio.timeout(timeout):
                return await asyncio.to_thread(fn, *args, **kw)
        except TimeoutError:
            raise Unavailable(f"--ros: the ROS 1 master did not answer within {timeout} s") from None

    async def close(self) -> None:
        """Unregister every topic and service, shut rospy down, print the counts."""
        if not self._started:
            return
        self._started = False
        for undo in self._handles:
            undo()
        await self._in_thread(self.rospy.signal_shutdown, "rce-ros stopping", timeout=MASTER_TIMEOUT)
        for itag, c in self.counts.items():
            self.bridge.out(f"rce-ros: ROS 1 {itag}: {c.from_ros} from ROS 1, {c.to_ros} to ROS 1, "
                            f"{c.dropped} dropped, {c.bad} failed")

    # -- topics ------------------------------------------------------------------------------
    def subscribe(self, kind: Any, deliver: Callable[[bytes], bool]) -> None:
        """ROS 1 topic ``k.addr`` -> ``deliver`` (in the loop), the serialized bytes untouched. What this
        node itself publishes on ``k.addr`` (a Publisher interface at the same ``addr``) is not sent
        back to the cloud (rospy delivers a node's own messages to its subscribers)."""
        handoff, me = Handoff(self.loop, deliver, self.counts[kind.spec.iTag]), self.rospy.get_name()

        def on_ros(msg: Any) -> None:
            header = getattr(msg, "_connection_header", None) or {}
            if header.get("callerid") != me:
                handoff.offer(msg._buff)
        sub = self.rospy.Subscriber(kind.addr, self.classes[kind.spec.iTag], on_ros, queue_size=QUEUE_SIZE)
        self._handles.append(sub.unregister)

    def advertise(self, kind: Any) -> Callable[[bytes], None]:
        """Advertise ROS 1 topic ``k.addr``; returns its publish function (serialized bytes)."""
        cls, counts = self.classes[kind.spec.iTag], self.counts[kind.spec.iTag]
        pub = self.rospy.Publisher(kind.addr, cls, queue_size=QUEUE_SIZE)
        self._handles.append(pub.unregister)

        def publish(payload: bytes) -> None:
            try:
                pub.publish(cls.wrap(payload))
                counts.add(to_ros=1)
            except self.rospy.ROSException as e:       # shut down, or unregistered
                counts.add(dropped=1)
                log.warning("message not published to ROS 1", itag=kind.spec.iTag, topic=kind.addr, reason=str(e))
        return publish

    # -- services ----------------------------------------------------------------------------
    def advertise_service(self, kind: Any, handler: Callable[[bytes], Awaitable[bytes]]) -> None:
        """Serve ROS 1 service ``k.addr``: each call (in a rospy thread) runs ``handler`` in the loop
        and waits up to ``SERVICE_CALL_TIMEOUT`` s; a failure is the caller's ServiceException."""
        cls, counts, rospy = self.classes[kind.spec.iTag], self.counts[kind.spec.iTag], self.rospy

        def serve(req: Any) -> Any:
            counts.add(from_ros=1)
            fut = asyncio.run_coroutine_threadsafe(handler(req._buff), self.loop)
            try:
                return cls._response_class.wrap(fut.result(SERVICE_CALL_TIMEOUT))
            except RCEError as e:
                reason = e.message
            except TimeoutError:
                fut.cancel()
                reason = f"no answer from the cloud within {SERVICE_CALL_TIMEOUT} s"
            except Exception as e:        # the loop is closing, or a fault in a conversion: the call fails alone
                reason = f"{type(e).__name__}: {e}"
            counts.add(bad=1)
            log.warning("ROS 1 service call failed", itag=kind.spec.iTag, service=kind.addr, reason=reason)
            raise rospy.ServiceException(f"rce: {reason}")
        self._handles.append(rospy.Service(kind.addr, cls, serve).shutdown)

    async def call_service(self, kind: Any, payload: bytes) -> bytes:
        """Call ROS 1 service ``k.addr`` with the serialized request; returns the serialized response.
        Raises :class:`RequestError` (the service's failure, or it is not there), :class:`Unavailable`
        (``CALLS_IN_FLIGHT`` calls already running, or no answer within ``SERVICE_CALL_TIMEOUT`` s)."""
        itag = kind.spec.iTag
        cls, counts = self.classes[itag], self.counts[itag]
        if self._calls.get(itag, 0) >= CALLS_IN_FLIGHT:
            counts.add(dropped=1)
            raise Unavailable(f"ROS 1 service {kind.addr}: {CALLS_IN_FLIGHT} calls already in flight")
        self._calls[itag] = self._calls.get(itag, 0) + 1
        counts.add(to_ros=1)
        proxy = self.rospy.ServiceProxy(kind.addr, cls)
        try:
            async with asyncio.timeout(SERVICE_CALL_TIMEOUT):
                resp = await asyncio.to_thread(proxy.call, cls._request_class.wrap(payload))
        except TimeoutError:
            counts.add(bad=1)
            raise Unavailable(f"ROS 1 service {kind.addr}: no answer within {SERVICE_CALL_TIMEOUT} s") from None
        except (self.rospy.ServiceException, self.rospy.ROSException) as e:
            counts.add(bad=1)
            raise RequestError(f"ROS 1 service {kind.addr}: {e}") from None
        finally:
            self._calls[itag] -= 1
        counts.add(from_ros=1)
        return resp._buff
