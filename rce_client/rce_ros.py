"""``rce-ros CONFIG``: connect a robot to the cloud and bridge its local bus.

::

    rce-ros configs/debug.config [--bus PATH | --ros | --ros2] [--timeout S] [--keep] [--url MASTER_URL] [--no-resume]
                                 [--relay-port PORT [--relay-max N] [--relay-rate BYTES_S]] [--relays HOST:PORT,...]
                                 [--record FILE.mcap]

1. Loads the robot config (:func:`rce.protocol.config.load_config`, JSON or YAML). A bad config is
   refused before anything is sent: exit code 2 and the ConfigError (file, key path, reason).
2. Runs the robot's LOCAL BUS (:class:`rce.bus.core.Bus` served by
   :class:`rce.bus.server.BusServer`, the same implementation as a container's) on a Unix
   socket (``--bus``, default ``$XDG_RUNTIME_DIR/rce/<robotID>.sock`` or
   ``/tmp/rce-<uid>/<robotID>.sock``) and prints ``export RCE_BUS=...`` for local programs
   (:mod:`rce.node`, ``rce-topic``, ``rce-service``).
3. Logs in and sends, in order: CC for each container (with its containerData), CN setParam,
   CN addNodes, CN addInterfaces, CX connect; then waits until every robot-side interface
   (eTag == robotID) is up (ST ``iu``; ``--timeout`` s, default 30) and prints ``ready``.
4. Bridges each robot-side interface to the local bus at its ``addr`` (default ``/<iTag>``):

   - ``SubscriberConverter/Forwarder``: the local topic's messages go to the cloud as DMs
     (Converter: JSON; Forwarder: the serialized bytes as binary part ``msg*``);
   - ``PublisherConverter/Forwarder``: DMs from the cloud are published on the local topic;
   - ``ServiceProviderConverter/Forwarder``: a local service ``addr`` whose calls go to the cloud;
   - ``ServiceClientConverter/Forwarder``: the cloud's calls run against the local service ``addr``.

   With ``--ros`` there is no local bus: the interfaces are bridged to the ROS 1 master named by
   ``ROS_MASTER_URI``, each at its ``addr`` (:mod:`rce_client.ros1_bridge`); with ``--ros2``, to the
   robot's ROS 2 graph as one rclpy node named after the robot (:mod:`rce_client.ros2_bridge`).

5. Asks for session resume (docs/INTERNALS.md "Session resume"; ``--no-resume``: not): when the link
   to the cloud drops, the local bus stays up and local programs never notice: their messages to
   the cloud are kept and sent after the resume, their calls to the cloud wait, and what the cloud
   sent meanwhile is published once the session is resumed. rce-ros prints the drop and the resume.

6. Relays (docs/relays.md): with ``--relay-port PORT`` this robot relays for nearby robots out of
   coverage (:class:`rce_client.relay.RobotRelay`: at most ``--relay-max`` at once, its own traffic first);
   with ``--relays HOST:PORT,...`` it is a follower: it logs in and dials its endpoint directly when
   it can, else through the first relay that answers, and moves between them by session resume.

7. ``--record FILE.mcap``: every message of the bridged topics, both ways, is written to an MCAP file as
   it crosses the bridge (its bytes, ROS 1 or a ROS 2 class's CDR, on the interface's local topic;
   :mod:`rce_client.mcap_recorder`);
   ``FILE.bag``: a ROS 1 bag. The file is finished at the stop and its counts printed.

Every ER from the cloud is printed with its reason. SIGINT/SIGTERM tear down: the interfaces
and containers this run created are removed (unless ``--keep``), the websocket is closed,
the socket removed; exit code 0. (With ``--keep`` nothing is removed by rce-ros, but today's
master still destroys the containers a robot created when that robot disconnects.) Exit code 1:
login refused, interfaces not up in time, or the connection lost (and not resumed).
"""
from __future__ import annotations

import argparse
import asyncio
import math
import os
import signal
import socket
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Awaitable, Callable

from rce.interfaces.lanes import Lane, interface_lane
from rce.transport import tls
from rce.plumbing.process import exit_command, run_loop
from rce.bus.core import Bus, Subscription
from rce.bus.server import BusServer
from rce.protocol.config import InterfaceSpec, RobotConfig, load_config
from rce.plumbing.errors import ConfigError, MessageError, RCEError, Unavailable
from rce.plumbing.log import get_logger, setup_logging
from rce.messages import MessageRegistry, default_registry, wire_name
from rce.interfaces.naming import validate_name
from rce.node.package_path import load_package_types
from rce.protocol.schema import split_interface_type
from rce.interfaces.pacer import Pacing, rate_arg
from rce_client.connection import Connection, Message
from rce_client.paths import default_bus_path
from rce_client.relay import DEFAULT_MAX_FOLLOWERS, DEFAULT_RATE, RobotRelay
from rce_client.routes import Routes, parse_relays

log = get_logger("rce.ros")
OWNER = "/rce_ros"
QUEUE_SIZE = 100            # messages waiting to go to the cloud, per interface
TEARDOWN_TIMEOUT = 5.0      # s to wait for the cloud to process the teardown requests
CONNECT_WAIT = 5.0          # s a robot-side service call waits for its interface to be wired to the cloud


class _Stopped(Exception):
    """SIGINT/SIGTERM arrived."""


@dataclass
class _Kind:
    """What a robot-side interface is: prefix, forwarder?, local address, bus type name."""
    spec: InterfaceSpec
    prefix: str
    forwarder: bool
    addr: str
    bus_type: str
    types: tuple[str, ...]   # store names: (msg,) or (request, response); () for an unknown forwarder class


def classify(spec: InterfaceSpec, registry: MessageRegistry, where: str) -> _Kind:
    """Resolve a robot-side interface for the bridge. Raises :class:`ConfigError` (``where``
    names it, e.g. ``configs/x.config: interfaces[4].iCls``) when a Converter's class is
    unknown locally: the robot converts between JSON and ROS 1 bytes, so it needs the class."""
    prefix, suffix = split_interface_type(spec.iType)
    forwarder = suffix == "Forwarder"
    is_srv = prefix in ("ServiceClient", "ServiceProvider")
    try:
        if is_srv:
            types = registry.srv_types(spec.iCls)
            bus_type = spec.iCls.strip("/")
        else:
            t = registry.msg_type(spec.iCls)
            types, bus_type = (t,), wire_name(t)
    except MessageError as e:
        if not forwarder:
            raise ConfigError(f"{where}: {e.message} (a {spec.iType} converts on the robot, so the class must "
                              f"be known locally: put its package on RCE_PACKAGE_PATH, or use a Forwarder)") from None
        types, bus_type = (), spec.iCls.strip("/")
    return _Kind(spec, prefix, forwarder, spec.addr or f"/{spec.iTag}", bus_type, types)


class _ToCloud:
    """Robot-side topic -> SubscriberConverter/Forwarder: a bounded queue and a sender task.

    The robot-side graph calls :meth:`deliver` (in the loop) with each serialized message. The queue
    holds :data:`QUEUE_SIZE`; when it is full a state or bulk interface drops its oldest for the new one
    (``superseded``: the newest goes out), a control one the new one (``dropped``).
    ``dropped``: messages not sent (queue full, interface down, or refused); ``bad``: of those,
    the ones that did not convert or were refused (logged with the reason)."""

    def __init__(self, bridge: "RobotBridge", kind: _Kind):
        self.bridge, self.kind = bridge, kind
        self.itag = kind.spec.iTag
        self.pub = bridge.conn.publisher(self.itag, kind.spec.iCls, kind.spec.lane)
        self.queue: asyncio.Queue[bytes] = asyncio.Queue(maxsize=QUEUE_SIZE)
        self.newest = interface_lane(kind.spec.iCls, False, kind.spec.lane) is not Lane.CONTROL
        self.dropped = self.superseded = 0
        self.bad = 0
        self._warned = False
        self.task = asyncio.create_task(self._pump())

    def deliver(self, payload: bytes) -> bool:
        """Queue ``payload`` for the cloud; False (and counted) when it is dropped."""
        if not self.bridge.conn.interfaces.get(self.itag):
            self.dropped += 1
            if not self._warned:
                self._warned = True
                log.warning("interface not connected yet: local messages dropped", itag=self.itag, topic=self.kind.addr)
            return False
        if self.queue.full() and self.newest:
            self.queue.get_nowait()
            self.superseded += 1
        try:
            self.queue.put_nowait(payload)
            return True
        except asyncio.QueueFull:
            self.dropped += 1
            return False

    async def _pump(self) -> None:
        reg = self.bridge.registry
        while True:
            payload = await self.queue.get()
            try:
                msg: Message = payload if self.kind.forwarder else reg.bytes_to_json(self.kind.types[0], payload)
                await self.pub.publish(msg)
            except RCEError as e:
                self.dropped += 1
                self.bad += 1
                log.warning("message not sent to the cloud", itag=self.itag, reason=e.message)

    def close(self) -> None:
        self.task.cancel()


class LocalBusGraph:
    """The robot-side graph of ``rce-ros``: the robot's local bus (:class:`rce.bus.core.Bus`), served
    on the Unix socket ``bridge.bus_path`` (None: in-process, no socket).

    Every robot-side graph (this one, :class:`rce_client.ros1_bridge.RospyGraph`) offers the same
    calls, all made in the loop: :meth:`start`, :meth:`close`, :meth:`subscribe`, :meth:`advertise`,
    :meth:`advertise_service`, :meth:`call_service`. ``kind`` is a :class:`_Kind`."""

    def __init__(self, bridge: "RobotBridge"):
        self.bridge, self.bus, self.path = bridge, bridge.bus, bridge.bus_path
        self.server = BusServer(self.bus)
        self._undo: list[Callable[[], None]] = []

    async def start(self) -> None:
        """Serve the bus socket. Raises :class:`Unavailable` when another rce-ros serves it."""
        self.bus.nodes[OWNER] = {"pid": os.getpid(), "container": None}
        if self.path is None:       # in-process: the owner uses ``bridge.bus`` directly
            return
        path = Path(self.path)
        if path.exists():
            if _socket_alive(str(path)):
                raise Unavailable(f"another rce-ros already serves a bus at {path} (pass --bus for another path)")
        if not path.parent.exists():
            path.parent.mkdir(parents=True, mode=0o700, exist_ok=True)
        await self.server.listen(path)
        out = self.bridge.out
        out(f"rce-ros: local bus of robot {self.bridge.cfg.robotID} at {path}")
        out(f"  export RCE_BUS={path}")

    async def close(self) -> None:
        """Take back what was attached and stop serving the socket (removed)."""
        for f in self._undo:
            f()
        if self.path is None:
            return
        await self.server.close()
        try:
            os.unlink(self.path)
        except OSError:
            pass

    def subscribe(self, kind: _Kind, deliver: Callable[[bytes], bool]) -> None:
        """Hand every message on the local topic ``k.addr`` to ``deliver``."""
        sub: Subscription = self.bus.subscribe(kind.addr, kind.bus_type, deliver, OWNER, QUEUE_SIZE)
        self._undo.append(lambda: self.bus.unsubscribe(sub))

    def advertise(self, kind: _Kind) -> Callable[[bytes], None]:
        """Advertise the local topic ``k.addr``; returns its publish function (serialized bytes)."""
        topic = self.bus.advertise(kind.addr, kind.bus_type, OWNER)
        self._undo.append(lambda: self.bus.unadvertise(kind.addr, OWNER))
        return lambda payload: self.bus.publish(topic, payload)

    def advertise_service(self, kind: _Kind, handler: Callable[[bytes], Awaitable[bytes]]) -> None:
        """Serve the local service ``k.addr`` with ``handler`` (request bytes -> response bytes)."""
        self.bus.advertise_service(kind.addr, kind.bus_type, handler, OWNER)
        self._undo.append(lambda: self.bus.unadvertise_service(kind.addr, OWNER))

    async def call_service(self, kind: _Kind, payload: bytes) -> bytes:
        """Call the local service ``k.addr``; raises the bus's :class:`RCEError` on failure."""
        return await self.bus.call_service(kind.addr, payload, kind.bus_type)


class RobotBridge:
    """One ``rce-ros`` run: local bus, cloud connection, setup, bridges, teardown.

    ``out(line)`` prints status lines (stdout); ``err(line)`` prints errors (stderr).
    ``bus_path`` None serves no socket: an in-process robot (the fleet simulator runs one
    bridge per simulated robot) publishes and subscribes on ``self.bus`` directly; ``run()``
    in a task, ``ready`` tells when the interfaces are up, ``stop.set()`` tears down.
    ``resume``: ask for session resume and ride out lost links (:class:`Connection` ``allow_reconnect``).
    ``lanes``, ``bulk_rate``, ``mptcp``: a bulk link beside the session's (paced as ``bulk_rate`` says),
    Multipath TCP (:class:`Connection`; docs/lanes.md). ``max_lag``: s the cloud endpoint may stay behind
    this robot's frames before it sheds its topic messages (``maxLag``; 0: never; None: the endpoint's).
    ``graph(bridge)`` makes the robot-side graph the interfaces are bridged to (default
    :class:`LocalBusGraph`; ``rce-ros --ros``: :class:`rce_client.ros1_bridge.RospyGraph`).
    ``relays``: [(host, port)] of relays to reach the cloud through when the direct path fails (or
    ``routes``: the follower's :class:`~rce_client.routes.Routes` given whole, e.g. with its own dial);
    ``relay_port``: relay for nearby robots on ``relay_bind``:this port (None: not; 0: any free port), at
    most ``relay_max`` at once, relayed traffic paced to ``relay_rate`` bytes/s (docs/relays.md)."""

    def __init__(self, config: RobotConfig, source: str, bus_path: str | None, *, timeout: float = 30.0,
                 keep: bool = False, url: str | None = None, registry: MessageRegistry | None = None,
                 out: Callable[[str], None] | None = None, err: Callable[[str], None] | None = None,
                 resume: bool = True, graph: Callable[["RobotBridge"], Any] | None = None,
                 relays: list[tuple[str, int]] | None = None, relay_port: int | None = None,
                 relay_max: int = DEFAULT_MAX_FOLLOWERS, relay_rate: float = DEFAULT_RATE, relay_bind: str = "0.0.0.0",
                 routes: Routes | None = None, lanes: bool = False, bulk_rate: Pacing | None = None,
                 mptcp: bool = False, record: str | None = None, max_lag: float | None = None):
        self.cfg, self.source, self.bus_path = config, source, bus_path
        self.record = record                     # --record FILE.mcap|FILE.bag: the bridged topics recorded
        self.recorder = None
        self.not_recorded = 0
        self.timeout, self.keep, self.resume = timeout, keep, resume
        self.lanes, self.bulk_rate, self.mptcp, self.max_lag = lanes, bulk_rate, mptcp, max_lag
        self.url = url or config.url
        self.registry = registry or default_registry()
        self.out = out or (lambda text: print(text, flush=True))
        self.err = err or (lambda text: print(text, file=sys.stderr, flush=True))
        self.bus = Bus(f"robot {config.robotID}")
        self.graph = (graph or LocalBusGraph)(self)
        self.conn: Connection | None = None
        self.routes = routes or (Routes(relays) if relays else None)
        self.relay_port, self.relay_max, self.relay_rate = relay_port, relay_max, relay_rate
        self.relay_bind = relay_bind
        self.relay: RobotRelay | None = None
        self.stop = asyncio.Event()
        self.ready = asyncio.Event()            # set once every robot-side interface is up
        self.created: list[str] = []            # containers this run created
        self._to_cloud: list[_ToCloud] = []
        self.not_published: dict[str, int] = {}   # iTag -> messages from the cloud that did not convert
        robot = config.robotID
        self.robot_side = [i for i in config.interfaces if i.eTag == robot]
        self.kinds: list[_Kind] = []

    # -- helpers -----------------------------------------------------------------------------
    async def _until_stop(self, aw: Awaitable) -> Any:
        """Await ``aw`` unless a stop signal or the connection's end comes first."""
        task = asyncio.ensure_future(aw)
        waits = [task, asyncio.ensure_future(self.stop.wait())]
        if self.conn is not None:
            waits.append(asyncio.ensure_future(self.conn.wait_closed()))
        try:
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waits[1:]:
                w.cancel()
        if task.done():
            return task.result()
        task.cancel()
        if self.stop.is_set():
            raise _Stopped
        raise Unavailable(f"connection to the cloud closed: {self.conn.close_reason}")

    def _check_local_types(self) -> None:
        """Resolve the robot-side interfaces and check their local addresses agree with each other
        (one class per topic, one interface per service). Raises :class:`ConfigError`."""
        topics: dict[str, str] = {}
        services: dict[str, str] = {}
        for i, itf in enumerate(self.cfg.interfaces):
            if itf.eTag != self.cfg.robotID:
                continue
            k = classify(itf, self.registry, f"{self.source}: interfaces[{i}].iCls")
            where = f"{self.source}: interfaces[{i}].addr"
            try:
                validate_name(k.addr, "address")
            except RCEError as e:
                raise ConfigError(f"{where}: {e.message}") from None
            if k.prefix in ("Publisher", "Subscriber"):
                if topics.setdefault(k.addr, k.bus_type) != k.bus_type:
                    raise ConfigError(f"{where}: local topic {k.addr} is used with classes {topics[k.addr]} "
                                      f"and {k.bus_type}")
            elif k.addr in services:
                raise ConfigError(f"{where}: local service {k.addr} is already bridged by {services[k.addr]}")
            else:
                services[k.addr] = itf.iTag
            self.kinds.append(k)

    # -- run ---------------------------------------------------------------------------------
    async def run(self) -> int:
        """Run until stopped; returns the exit code (0 clean stop, 1 failure)."""
        load_package_types(self.registry)
        self._check_local_types()     # ConfigError before anything is sent
        if self.record:
            from rce_client.mcap_recorder import recorder_for
            self.recorder = recorder_for(self.record, self.registry, [
                (k.addr, k.spec.iCls, k.spec.qos) for k in self.kinds
                if k.types and k.prefix in ("Publisher", "Subscriber")])        # the topics it records
            self.recorder.open()
        await self.graph.start()
        try:
            try:
                await self._connect_and_setup()
                await self._until_stop(self.conn.wait_closed())
                # only returns when the cloud closed the connection
                self.err(f"rce-ros: connection to the cloud closed: {self.conn.close_reason}")
                return 1
            except _Stopped:
                self.out("rce-ros: stopping")
                await self._teardown()
                return 0
            except RCEError as e:
                self.err(f"rce-ros: {e.message}")
                if self.conn is not None and not self.conn.closed:
                    await self._teardown()
                return 1
        finally:
            if self.relay is not None:
                await self.relay.close()
                self.out(f"rce-ros: relayed {self.relay.stats.summary()}")
            for c in self._to_cloud:
                c.close()
            self._report_drops()
            await self.graph.close()
            if self.recorder is not None:
                self.recorder.close()
                self.out(f"rce-ros: {self.recorder.summary()}" + (f"; {self.not_recorded} not recorded (a topic "
                                                                   f"recorded with another class)"
                                                                   if self.not_recorded else ""))

    def _report_drops(self) -> None:
        """Print the messages this run dropped, per interface (nothing when none were)."""
        for c in self._to_cloud:
            if c.dropped:
                self.out(f"rce-ros: {c.itag}: {c.dropped} message(s) not sent to the cloud ({c.bad} refused)")
            if c.superseded:
                self.out(f"rce-ros: {c.itag}: {c.superseded} message(s) superseded by a newer one before they left "
                         f"the bridge's queue")
        for itag, n in self.not_published.items():
            self.out(f"rce-ros: {itag}: {n} message(s) from the cloud not published (did not convert)")
        if self.conn is not None and self.conn.session.resume_lost:
            self.out(f"rce-ros: {self.conn.session.resume_lost} message(s) to the cloud lost at resumes (the "
                     f"resume buffer forgot them while no link was up)")
        if self.conn is not None and self.conn.session.superseded:
            self.out(f"rce-ros: {self.conn.session.superseded} state/bulk message(s) to the cloud superseded while "
                     f"no link was up (only each interface's newest was sent)")

    async def _connect_and_setup(self) -> None:
        cfg = self.cfg
        self.out(f"rce-ros: logging in at {self.url} as {cfg.userID}/{cfg.robotID}")
        self.conn = await self._until_stop(Connection.connect(self.url, cfg.userID, cfg.password, cfg.robotID,
                                                              allow_reconnect=self.resume, routes=self.routes,
                                                              lanes=self.lanes, bulk_rate=self.bulk_rate,
                                                              mptcp=self.mptcp, max_lag=self.max_lag))
        conn = self.conn
        conn.on_error(lambda reason: self.err(f"rce-ros: error from the cloud: {reason}"))
        conn.on_status(self._on_status)
        conn.on_disconnected(lambda reason: self.err(f"rce-ros: link to the cloud lost ({reason}); resuming the "
                                                     f"session (the local bus stays up)"))
        conn.on_resumed(lambda st: self.out(f"rce-ros: session resumed ({st.get('dropped', 0)} message(s) from "
                                            f"the cloud lost, {st.get('superseded', 0)} superseded; "
                                            f"{conn.session.resume_lost} to the cloud lost, "
                                            f"{conn.session.superseded} superseded in all){self._via()}"))
        via = self._via()
        self.out(f"rce-ros: connected to {conn.ws_url}{via}")
        if self.relay_port is not None:
            self.relay = await RobotRelay.for_connection(conn, self.relay_port, bind=self.relay_bind,
                                                         max_followers=self.relay_max, rate=self.relay_rate)
            self.out(f"rce-ros: relaying for nearby robots on port {self.relay.port} (at most {self.relay_max})")
        self._bridge()

        for c in cfg.containers:
            n = len(conn.errors)
            data = c.container_data()
            await conn.create_container(c.cTag, **data)
            checked = await self._until_stop(conn.barrier(self.timeout))
            if not checked or len(conn.errors) == n:
                self.created.append(c.cTag)
        if cfg.parameters:
            await conn.configure({"setParam": [{"containerTag": p.cTag, "name": p.name, "value": p.value}
                                               for p in cfg.parameters]})
        if cfg.nodes:
            await conn.configure({"addNodes": [n.component() for n in cfg.nodes]})
        if cfg.interfaces:
            await conn.configure({"addInterfaces": [i.component() for i in cfg.interfaces]})
        if cfg.connections:
            await conn.send("CX", {"connect": [{"tagA": c.tagA, "tagB": c.tagB} for c in cfg.connections]})

        itags = [i.iTag for i in self.robot_side]
        if itags:
            self.out(f"rce-ros: waiting for {len(itags)} interface(s) to come up: {', '.join(itags)}")
        await self._until_stop(conn.wait_interfaces_up(itags, self.timeout))
        self.ready.set()
        self.out(f"rce-ros: ready ({len(itags)} interface(s) up; Ctrl-C to stop)")

    def _via(self) -> str:
        """`` through relay NAME`` while a follower's link goes through a relay, `` on its own path`` while
        it does not, "" for a robot without relays."""
        if self.routes is None:
            return ""
        return f" through relay {self.routes.relay}" if self.routes.relay else " on its own path"

    # -- bridges -----------------------------------------------------------------------------
    def _bridge(self) -> None:
        """Attach every robot-side interface to the robot-side graph (messages flow once it is up)."""
        graph = self.graph
        for k in self.kinds:
            try:
                if k.prefix == "Subscriber":
                    to_cloud = _ToCloud(self, k)
                    self._to_cloud.append(to_cloud)
                    graph.subscribe(k, self._recorded(k, to_cloud.deliver))
                elif k.prefix == "Publisher":
                    self._from_cloud(k, self._recorded(k, graph.advertise(k)))
                elif k.prefix == "ServiceProvider":
                    graph.advertise_service(k, self._cloud_service(k))
                else:
                    self._cloud_calls(k, lambda payload, kind=k: graph.call_service(kind, payload))
            except RCEError as e:
                raise ConfigError(f"{self.source}: interface {k.spec.iTag} at {k.addr}: {e.message}") from None
            log.info("bridged", itag=k.spec.iTag, itype=k.spec.iType, addr=k.addr)

    def _recorded(self, kind: _Kind, fn: Callable[[bytes], Any]) -> Callable[[bytes], Any]:
        """``fn``, and with ``--record`` each message it takes written first to the recording, on the
        interface's local topic (a forwarder's class unknown here: not recorded)."""
        rec = self.recorder
        if rec is None or not kind.types:
            return fn
        topic, cls = kind.addr, kind.spec.iCls

        def recorded(payload: bytes) -> Any:
            try:
                rec.write(topic, cls, payload)
            except MessageError:
                self.not_recorded += 1
            return fn(payload)
        return recorded

    def _from_cloud(self, kind: _Kind, publish: Callable[[bytes], Any]) -> None:
        """PublisherConverter/Forwarder: DMs from the cloud published (serialized) with ``publish``."""
        reg = self.registry

        def on_msg(msg: Message) -> None:
            try:
                payload = bytes(msg) if isinstance(msg, (bytes, bytearray)) else reg.json_to_bytes(kind.types[0], msg)
            except (RCEError, IndexError) as e:
                self.not_published[kind.spec.iTag] = self.not_published.get(kind.spec.iTag, 0) + 1
                log.warning("message from the cloud not published", itag=kind.spec.iTag, topic=kind.addr,
                            reason=getattr(e, "message", repr(e)))
                return
            publish(payload)
        self.conn.subscriber(kind.spec.iTag, kind.spec.iCls, on_msg)

    def _cloud_service(self, kind: _Kind) -> Callable[[bytes], Awaitable[bytes]]:
        """ServiceProviderConverter/Forwarder: the handler of the robot-side service ``k.addr``, whose
        calls (request bytes -> response bytes) go to the cloud. A call while the interface is not
        wired to the cloud (rce-ros just started, or the cloud away) waits up to ``CONNECT_WAIT`` s
        for it. Raises :class:`RCEError` (:class:`Unavailable` when it stays unwired)."""
        client = self.conn.service(kind.spec.iTag, kind.spec.iCls)
        reg, itag = self.registry, kind.spec.iTag

        async def handler(payload: bytes) -> bytes:
            if not self.conn.interfaces.get(itag):          # just set up, or the cloud away: wait a little
                try:
                    await self.conn.wait_interfaces_up([itag], CONNECT_WAIT)
                except Unavailable:
                    raise Unavailable(f"service {kind.addr}: interface {itag} is not connected to the cloud "
                                      f"(waited {CONNECT_WAIT:g} s)") from None
            if kind.forwarder:
                resp = await client.call(payload, timeout=None)
                if isinstance(resp, (bytes, bytearray)):
                    return bytes(resp)
                if not kind.types:
                    raise MessageError(f"service {kind.addr}: the cloud answered JSON for unknown class "
                                       f"{kind.spec.iCls}")
                return reg.json_to_bytes(kind.types[1], resp)
            resp = await client.call(reg.bytes_to_json(kind.types[0], payload), timeout=None)
            if isinstance(resp, (bytes, bytearray)):
                return bytes(resp)
            return reg.json_to_bytes(kind.types[1], resp)
        return handler

    def _cloud_calls(self, kind: _Kind, call_local: Callable[[bytes], Awaitable[bytes]]) -> None:
        """ServiceClientConverter/Forwarder: the cloud's calls run against the robot-side service
        with ``call_local`` (request bytes -> response bytes)."""
        reg = self.registry

        async def handler(req: Message) -> Message:
            if isinstance(req, (bytes, bytearray)):
                payload = bytes(req)
            elif kind.types:
                payload = reg.json_to_bytes(kind.types[0], req)
            else:
                raise MessageError(f"service {kind.addr}: JSON request for unknown class {kind.spec.iCls}")
            resp = await call_local(payload)
            return resp if kind.forwarder else reg.bytes_to_json(kind.types[1], resp)
        self.conn.service_provider(kind.spec.iTag, kind.spec.iCls, handler)

    def _on_status(self, st: dict) -> None:
        if st.get("topic") == "iu":
            if self.ready.is_set():
                self.out(f"rce-ros: interface {st.get('iTag')} {'up' if st.get('status') else 'down'}")
        elif st.get("topic") == "node":
            extra = "".join(f" {k}={st[k]}" for k in ("code", "signal", "reason") if st.get(k) is not None)
            self.out(f"rce-ros: node {st.get('cTag')}/{st.get('nTag')}: {st.get('status')}{extra}")

    # -- teardown ----------------------------------------------------------------------------
    async def _teardown(self) -> None:
        """Remove what this run created (unless ``keep``), then close the websocket."""
        conn = self.conn
        if conn is None:
            return
        try:
            if not self.keep and not conn.closed:
                created = set(self.created)
                remove = [{"endpointTag": i.eTag, "interfaceTag": i.iTag} for i in self.cfg.interfaces
                          if i.eTag not in created]
                nodes = [{"containerTag": n.cTag, "nodeTag": n.nTag} for n in self.cfg.nodes if n.cTag not in created]
                if remove:
                    await conn.configure({"removeInterfaces": remove})
                if nodes:
                    await conn.configure({"removeNodes": nodes})
                for tag in self.created:
                    await conn.destroy_container(tag)
                await conn.barrier(TEARDOWN_TIMEOUT)
                self.out(f"rce-ros: removed {len(remove)} interface(s), destroyed {len(self.created)} container(s)")
        except RCEError as e:
            self.err(f"rce-ros: teardown incomplete: {e.message}")
        finally:
            await conn.close()


def _socket_alive(path: str) -> bool:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.settimeout(1.0)
        s.connect(path)
        return True
    except OSError:
        return False
    finally:
        s.close()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rce-ros", description="Connect this robot to the cloud as its config says "
                                "and bridge its local bus to its interfaces.")
    p.add_argument("config", help="robot config (JSON like the seed's robot1.config, or YAML)")
    p.add_argument("--bus", metavar="PATH", help="local bus socket (default $XDG_RUNTIME_DIR/rce/<robotID>.sock "
                   "or /tmp/rce-<uid>/<robotID>.sock)")
    p.add_argument("--ros", action="store_true", help="bridge the robot-side interfaces to the ROS 1 master named "
                   "by ROS_MASTER_URI (Debian's ros-comm) instead of a local bus")
    p.add_argument("--ros2", action="store_true", help="bridge the robot-side interfaces to the robot's ROS 2 graph "
                   "(rclpy; ROS_DOMAIN_ID) as one node named after the robot, instead of a local bus")
    p.add_argument("--timeout", type=float, default=30.0, metavar="S",
                   help="seconds to wait for the robot-side interfaces to come up (default 30)")
    p.add_argument("--keep", action="store_true", help="do not remove interfaces and containers on exit (note: "
                   "the master still destroys a robot's containers when the robot disconnects)")
    p.add_argument("--record", metavar="FILE.mcap", help="record every topic the robot's interfaces bridge, both "
                   "ways, into an MCAP file (one channel per topic: ros1, or cdr for a ROS 2 class; FILE.bag: a "
                   "ROS 1 bag)")
    p.add_argument("--url", metavar="MASTER_URL", help="master login URL (overrides the config's url)")
    p.add_argument("--no-resume", dest="resume", action="store_false",
                   help="do not ask for session resume: a lost link ends the run (exit code 1)")
    p.add_argument("--relay-port", type=int, metavar="PORT", help="relay for nearby robots out of coverage on "
                   "this TCP port (0: any free port; docs/relays.md)")
    p.add_argument("--relay-max", type=int, default=DEFAULT_MAX_FOLLOWERS, metavar="N",
                   help=f"robots relayed at once; the others are refused with 503 (default {DEFAULT_MAX_FOLLOWERS})")
    p.add_argument("--relay-rate", type=float, default=DEFAULT_RATE, metavar="BYTES_S",
                   help=f"relayed bytes/s in all, past which they are paced (0: no pacing; default {DEFAULT_RATE})")
    p.add_argument("--relays", metavar="HOST:PORT[,HOST:PORT...]",
                   help="relays to reach the cloud through when this robot's own path fails, in order of preference")
    p.add_argument("--lanes", action="store_true",
                   help="open a bulk link beside the session's link: images, clouds, scans and maps go on it, paced, "
                        "and commands never wait behind them (docs/lanes.md; needs resume)")
    p.add_argument("--uplink-rate", type=rate_arg, default="auto", metavar="RATE",
                   help="with --lanes, pace the bulk link to RATE: bytes/s, or with a unit (1.25MB, 10Mbit), a little "
                        "below the robot's uplink; 'auto' (the default): under the rate estimated for the uplink's "
                        "path; 'off': not paced (docs/lanes.md)")
    p.add_argument("--max-lag", type=float, metavar="S",
                   help="seconds the cloud endpoint may stay behind this robot's frames before it sheds its topic "
                        "messages, counted (0: never, for streams that must come whole; default: the endpoint's, 1 s)")
    p.add_argument("--mptcp", action="store_true",
                   help="connect over Multipath TCP where the kernel offers it (net.mptcp.enabled), else TCP")
    tls.add_client_arguments(p)
    return p



def main(argv: list[str] | None = None) -> None:
    """Entry point of ``rce-ros``: exits 0 after a clean stop, 1 on failure, 2 on a bad config
    (:func:`~rce.plumbing.process.exit_command`)."""
    args = build_parser().parse_args(argv)
    setup_logging()
    try:
        cfg = load_config(args.config)
    except ConfigError as e:
        print(f"rce-ros: {e.message}", file=sys.stderr)
        sys.exit(2)
    if args.lanes and not args.resume:
        build_parser().error("--lanes needs resume: the bulk link joins the session with its token (drop --no-resume)")
    if sum(map(bool, (args.ros, args.ros2, args.bus))) > 1:
        build_parser().error("--bus, --ros and --ros2 exclude each other: with --ros the interfaces are on the ROS 1 "
                             "graph, with --ros2 on the ROS 2 graph")
    bus_path = None if args.ros or args.ros2 else args.bus or default_bus_path(cfg.robotID)
    try:
        relays = parse_relays(args.relays) if args.relays else None
    except ValueError as e:
        build_parser().error(str(e))
    if args.relay_max < 1:
        build_parser().error(f"--relay-max must be at least 1, got {args.relay_max}")
    if args.max_lag is not None and not (args.max_lag >= 0 and math.isfinite(args.max_lag)):
        build_parser().error(f"--max-lag must be 0 or more seconds, got {args.max_lag:g}")
    if args.ca_file:           # the https:// login and the wss:// endpoint trust it (rce.transport.tls.client_context)
        os.environ[tls.CA_FILE_ENV] = str(args.ca_file)

    async def amain() -> int:
        graph = None
        if args.ros:
            from rce_client.ros1_bridge import RospyGraph
            graph = RospyGraph
        elif args.ros2:
            from rce_client.ros2_bridge import RclpyGraph
            graph = RclpyGraph
        bridge = RobotBridge(cfg, args.config, bus_path, timeout=args.timeout, keep=args.keep, url=args.url,
                             resume=args.resume, graph=graph, relays=relays, relay_port=args.relay_port,
                             relay_max=args.relay_max, relay_rate=args.relay_rate, lanes=args.lanes,
                             bulk_rate=args.uplink_rate, mptcp=args.mptcp, record=args.record,
                             max_lag=args.max_lag)
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, bridge.stop.set)
        return await bridge.run()

    try:
        code = run_loop(amain())
    except ConfigError as e:
        print(f"rce-ros: {e.message}", file=sys.stderr)
        code = 2
    except RCEError as e:
        print(f"rce-ros: {e.message}", file=sys.stderr)
        code = 1
    exit_command(code, argv)


if __name__ == "__main__":
    main()
