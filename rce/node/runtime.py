"""The node API: what a node program imports, in the spirit of rospy, asyncio-native.

::

    import rce.node

    async def main(node: rce.node.Node):
        pub = await node.publisher("chatter", "std_msgs/String", queue_size=10)
        await node.subscriber("echo", "std_msgs/String", lambda m: print(m.data))
        await node.service("add", "Test/StringEcho", lambda req: {"data": req.data})
        await pub.publish({"data": "hi"})
        await node.spin()

    rce.node.run(main, "talker")          # the blocking convenience

A node connects to its bus (a container's environment, or the robot's local bus
under ``rce-ros``) through the Unix socket named by ``RCE_BUS`` (or ``bus=``).
Its name and namespace come from the arguments, ``RCE_NODE_NAME`` /
``RCE_NAMESPACE``, or ROS-style ``__name:=`` / ``__ns:=`` command-line
remappings. Names resolve as in ROS (:mod:`rce.interfaces.naming`).

Messages handed to callbacks are rosbags typestore instances (attribute access
like rospy messages); ``publish`` and service handlers accept an instance or a
JSON-form dict (:mod:`rce.messages`).
"""
from __future__ import annotations

import asyncio
import base64
import functools
import inspect
import itertools
import os
import signal
import sys
import time
import weakref
from collections import deque
from typing import Any, Awaitable, Callable

from rce.contract import bus as to_bus
from rce.contract import node as ops
from rce.transport import framing

from rce.transport import rpc
from rce.transport.op_table import OpTable
from rce.plumbing.errors import MessageError, NotFound, RCEError, RequestError, Unavailable
from rce.transport.link import Responder, settle_reply
from rce.messages import MessageRegistry, default_registry, wire_name
from rce.interfaces.naming import join, resolve
from rce.node.links import DIRECT_OPS, DirectLinks
from rce.node.package_path import load_package_types, search_path
from rce.node.results import INPUT_ARRIVAL, ResultClock, stamp_of
from rce.plumbing.pending import PendingCalls
from rce.plumbing.process import run_loop
from rce.plumbing.tasks import Tasks

_NO = object()
#: registry -> :func:`definitions_key` of the package types loaded into it (a node forked by a
#: container's zygote inherits the zygote's registry and need not parse the same files again).
_LOADED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
SERVICE_TIMEOUT = 30.0   # s a service call waits for its response unless the caller says otherwise
HOLD_MAX = 20.0          # s a move's new copy holds its inputs for its state at most (Node.handoff)
HANDLED_POLL = 0.005     # s between looks at the subscribers while the state waits for them
SETTLE_FLUSH = 10.0      # s a moved copy's node waits for its direct links' far ends to take its last outputs
MAX_STATE = 8 * 2**20    # bytes of state a node hands over

#: What a node's environment asks it on its bus link, besides its direct links' ops (:data:`DIRECT_OPS`).
NODE_OPS = OpTable("environment -> node")


def definitions_key(env: dict | None = None) -> tuple:
    """What :func:`rce.node.package_path.load_package_types` would read: ``(path, size, mtime_ns)``
    of every ``msg``/``srv`` definition file of the packages on the path (``env``: default
    :data:`os.environ`), in its order. Equal keys mean the same definitions."""
    out = []
    for d in search_path(env):
        for p in [d] + (sorted(x for x in d.iterdir() if x.is_dir()) if d.is_dir() else []):
            for sub in ("msg", "srv"):
                if (p / sub).is_dir():
                    for f in sorted((p / sub).iterdir()):
                        st = f.stat()
                        out.append((str(f), st.st_size, st.st_mtime_ns))
    return tuple(out)


def load_types(registry: MessageRegistry) -> None:
    """Register the packages' ``.msg``/``.srv`` types into ``registry`` unless exactly these
    definitions are in it already. Raises :class:`MessageError` naming a bad file."""
    key = definitions_key()
    if _LOADED.get(registry) != key:
        load_package_types(registry)
        _LOADED[registry] = key


def _argv_remaps(argv: list[str]) -> dict[str, str]:
    return dict(a.split(":=", 1) for a in argv if a.startswith("__") and ":=" in a)


def node_argv(argv: list[str] | None = None) -> list[str]:
    """``sys.argv[1:]`` without ROS-style ``__name:=``/``__ns:=`` remappings (like ``rospy.myargv``)."""
    argv = sys.argv[1:] if argv is None else argv
    return [a for a in argv if not (a.startswith("__") and ":=" in a)]


class Publisher:
    """Publishes messages of one class on one topic."""

    def __init__(self, node: "Node", topic: str, typename: str, handle: int):
        self.node, self.topic, self.typename, self.handle = node, topic, typename, handle
        self.published = 0
        self.dropped = 0

    async def publish(self, msg: Any) -> None:
        """Publish ``msg`` (typestore instance or JSON-form dict), then wait for the socket to
        drain (backpressure: nothing is lost). Raises :class:`MessageError` if it does not fit
        the topic's class."""
        payload = self.node._encode(self.typename, msg)
        src = self._direct(payload)
        if src >= 0:
            self.node._peer.send_raw(self._head(payload, src), payload)
        self.published += 1
        self.node.results.published(msg, time.monotonic())
        await self.node._peer.link.drain()
        if self.node._direct is not None:
            await self.node._direct.drain(self.handle)

    def publish_nowait(self, msg: Any) -> bool:
        """Publish without waiting for the socket to drain (for callbacks). A message that would
        pass the link's bound (the bus is not reading) is dropped, counted in ``dropped``, and
        False returned."""
        payload = self.node._encode(self.typename, msg)
        src = self._direct(payload)
        if src >= 0 and not self.node._peer.link.offer(self._head(payload, src), payload, self):
            self.dropped += 1
            return False
        self.published += 1
        self.node.results.published(msg, time.monotonic())
        return True

    def _lost(self) -> None:
        """A message the bus link took was dropped from its queue (the bus is not keeping up)."""
        self.published -= 1
        self.dropped += 1

    def _direct(self, payload: bytes) -> int:
        """Send ``payload`` on this publisher's direct route, if it has one; the ``src`` of its bus
        frame, or -1 for none (:meth:`rce.node.links.DirectLinks.publish`)."""
        direct = self.node._direct
        return direct.publish(self.handle, payload) if direct is not None else 0

    def _head(self, payload: bytes, src: int = 0) -> bytes:
        """``src``: 0, or the direct route's version (:mod:`rce.node.links`)."""
        return framing.encode_data_header(framing.MSG, self.handle, src, 0, len(payload))

    async def unregister(self) -> None:
        await self.node._peer.ask(to_bus.BusUnadvertise(handle=self.handle))


class Subscriber:
    """Receives messages of one topic into a bounded queue (``queue_size``, oldest dropped first).

    The callback runs in a loop callback that takes every message waiting, in order (no task wakes per
    message); one that returns an awaitable is awaited in a task, which then takes the rest, so
    messages are handled one at a time, in order, whether the callback is sync or async.

    ``decode`` (``bytes -> Any``) turns each ROS 1 serialized message into what the callback gets;
    default: the full message (:meth:`rce.messages.MessageRegistry.deserialize`)."""

    def __init__(self, node: "Node", topic: str, typename: str, callback: Callable, queue_size: int,
                 decode: Callable[[bytes], Any] | None = None):
        self.node, self.topic, self.typename, self.callback = node, topic, typename, callback
        self.decode = decode or functools.partial(node.registry.deserialize, typename)
        self.queue_size = max(1, queue_size)
        self.queue: deque[tuple[bytes, float]] = deque()     # (payload, arrival: monotonic s)
        self.dropped = 0
        self.received = 0
        self.undecodable = 0       # messages that did not deserialize as typename (counted, logged, reported)
        self.handle = 0
        self._busy = False         # a drain is scheduled or a callback's awaitable is awaited
        self._stopped = False
        self._running: list | None = None     # [arrival, running] of the input whose awaitable is awaited
        self._loop = asyncio.get_running_loop()     # kept: each lookup costs a getpid() on Python 3.11

    def _push(self, payload: bytes) -> None:
        q = self.queue
        if len(q) >= self.queue_size:
            q.popleft()
            self.dropped += 1
        q.append((payload, time.monotonic()))
        if not self._busy and not self._stopped and not self.node.holding:
            self._busy = True
            self._loop.call_soon(self._drain)

    def _release(self) -> None:
        """Take what waited while the node held its inputs (:meth:`Node.handoff`)."""
        if self.queue and not self._busy and not self._stopped:
            self._busy = True
            self._loop.call_soon(self._drain)

    def _drain(self) -> None:
        """Take the waiting messages; an awaitable a callback returns goes on in a task."""
        r = self._take_until_awaitable()
        if r is None:
            self._busy = False
        else:
            self.node.tasks.spawn(self._finish(r), name=f"subscriber {self.topic}")

    def _take_until_awaitable(self) -> Awaitable | None:
        """Take waiting messages until a callback returns an awaitable (returned) or none is left (None)."""
        q = self.queue
        while q and not self._stopped and not self.node.holding:
            r = self._take(*q.popleft())
            if r is not None:
                return r
        return None

    def _take(self, payload: bytes, arrived: float) -> Awaitable | None:
        """Deserialize ``payload`` (arrived at monotonic ``arrived`` s) and call the callback: its
        awaitable result, or None. What the callback publishes is timed from ``arrived``
        (:mod:`rce.node.results`)."""
        self.received += 1
        try:
            msg = self.decode(payload)
        except MessageError as e:
            self.undecodable += 1
            self.node.undecodable(f"subscriber {self.topic}", e)
            return None
        self.node.results.arrived(stamp_of(msg), arrived)
        running = [arrived, True]
        INPUT_ARRIVAL.set(running)
        try:
            r = self.callback(msg)
        except Exception as e:
            running[1] = False
            self._failed(e)
            return None
        if r is None or r.__class__ is bool or not inspect.isawaitable(r):   # most callbacks return None, or
            running[1] = False                                                # publish_nowait's bool
            return None
        self._running = running
        return r

    async def _finish(self, r: Awaitable | None) -> None:
        try:
            while r is not None:
                try:
                    await r
                except Exception as e:
                    self._failed(e)
                if self._running is not None:
                    self._running[1] = False
                r = self._take_until_awaitable()
        finally:
            self._busy = False

    def _failed(self, e: Exception) -> None:
        print(f"[{self.node.full_name}] subscriber callback for {self.topic} failed: {e!r}", file=sys.stderr)

    def _stop(self) -> None:
        """Take no more messages (those waiting are dropped uncounted: the subscription is gone)."""
        self._stopped = True
        self.queue.clear()

    async def unregister(self) -> None:
        self._stop()
        await self.node._peer.ask(to_bus.BusUnsubscribe(handle=self.handle))


class ServiceProxy:
    """Calls one service: ``resp = await proxy(request)``."""

    def __init__(self, node: "Node", name: str, req_type: str, resp_type: str):
        self.node, self.name, self.req_type, self.resp_type = node, name, req_type, resp_type
        self.handle: int | None = None

    async def __call__(self, request: Any = None, timeout: float | None = SERVICE_TIMEOUT) -> Any:
        """Call with ``request`` (instance or dict; None = empty request). Raises the provider's
        :class:`RCEError`, :class:`NotFound` when the service is absent, and
        :class:`~rce.plumbing.errors.Timeout` after ``timeout`` s."""
        payload = self.node._encode(self.req_type, {} if request is None else request)
        if self.handle is None:
            r = await self.node._peer.ask(to_bus.BusResolveService(service=self.name))
            self.handle = r["handle"]
        data = await self.node._call(self.handle, payload, timeout)
        return self.node.registry.deserialize(self.resp_type, data)


class Node:
    """A node connected to a bus. Create with :func:`init_node`."""

    def __init__(self, name: str, namespace: str, bus_path: str, registry: MessageRegistry,
                 bus_token: str | None = None):
        self.name, self.namespace, self.bus_path, self.bus_token = name, namespace, bus_path, bus_token
        self.registry = registry
        self.full_name = join(namespace, name)
        self._peer: rpc.RpcPeer | None = None
        self._direct: DirectLinks | None = None      # direct links, when the bus offers them
        self._subs: dict[int, Subscriber] = {}
        self._services: dict[int, tuple[Callable, str, str]] = {}
        self._calls = PendingCalls(f"the bus (node {self.full_name})")
        self.tasks = Tasks(f"node {self.full_name}")
        self._responder = Responder(f"node {self.full_name}", self.tasks)
        self._ids = itertools.count(1)
        self._shutdown = asyncio.Event()
        self.results = ResultClock()          # outputs timed from their inputs (rce.node.results)
        # a move's new copy holds its inputs until its state arrives (handoff); never longer than HOLD_MAX
        self.holding = os.environ.get("RCE_STATE_IN") == "1"
        self._handoff: tuple[Callable, Callable] | None = None
        if self.holding:
            asyncio.get_running_loop().call_later(HOLD_MAX, self._release)

    async def _connect(self) -> None:
        self._peer = await rpc.connect_unix(self.bus_path, name=f"node {self.full_name}", on_data=self._on_data,
                                            on_close=lambda _p: self._shutdown.set())
        self._peer.link.on_drop = Publisher._lost        # publish_nowait's tag: its Publisher
        self._peer.handlers.update(NODE_OPS.handlers(self))
        r = await self._peer.ask(to_bus.BusHello(name=self.full_name, pid=os.getpid(),
                                              container=os.environ.get("RCE_CONTAINER"), token=self.bus_token,
                                              direct=True))
        key = r.get("fd_key") if isinstance(r, dict) else None
        if isinstance(key, str):             # the environment offers direct links (rce.node.links)
            direct = DirectLinks(self)
            self._peer.handlers.update(DIRECT_OPS.handlers(direct))
            try:
                await direct.open_channel(self.bus_path, key)
            except OSError as e:
                print(f"[{self.full_name}] no direct links (all traffic by the bus): {e}", file=sys.stderr)
                return
            self._direct = direct

    # -- results and handoff (the environment's requests) -----------------------------------------
    @NODE_OPS.op("node_results", args=ops.NodeResults)
    async def _op_results(self, args: ops.NodeResults) -> dict:
        return self.results.take()

    async def _handled(self) -> None:
        """Return once the inputs that arrived so far are handled (a node holding its inputs for
        its state has none to handle)."""
        while not self.holding and any(sub.queue or sub._busy for sub in self._subs.values()):
            await asyncio.sleep(HANDLED_POLL)

    @NODE_OPS.op("settle", args=ops.NodeSettle)
    async def _op_settle(self, args: ops.NodeSettle) -> dict:
        """A moved container's old copy goes (:mod:`rce_master.placement.mover`): ``{unflushed: [link ids]}`` once
        the inputs that arrived so far are handled and what they caused, sent on the node's direct
        links, reached the far ends (at most ``timeout`` s, default :data:`SETTLE_FLUSH` s)."""
        await self._handled()
        unflushed = await self._direct.flush(args.timeout or SETTLE_FLUSH) if self._direct else []
        return {"unflushed": unflushed}

    @NODE_OPS.op("state_out", args=ops.NodeStateOut)
    async def _op_state_out(self, args: ops.NodeStateOut) -> dict:
        """``{state: base64 | None}`` once the inputs that arrived so far are handled."""
        await self._handled()
        if self._handoff is None:
            return {"state": None}
        state = self._handoff[0]()
        if inspect.isawaitable(state):
            state = await state
        if not isinstance(state, (bytes, bytearray)):
            raise RequestError(f"node {self.full_name}: its state_out returned {type(state).__name__}, not bytes")
        if len(state) > MAX_STATE:
            raise RequestError(f"node {self.full_name}: its state is {len(state)} bytes, more than {MAX_STATE}")
        return {"state": base64.b64encode(state).decode()}

    @NODE_OPS.op("state_in", args=ops.NodeStateIn)
    async def _op_state_in(self, args: ops.NodeStateIn) -> dict:
        """Take ``state`` (base64, or None: start fresh) through the hook, then the held inputs."""
        took = False
        try:
            if self._handoff is not None and args.state is not None:
                r = self._handoff[1](base64.b64decode(args.state))
                if inspect.isawaitable(r):
                    await r
                took = True
        finally:
            self._release()
        return {"took": took}

    def _release(self) -> None:
        if self.holding:
            self.holding = False
            for sub in self._subs.values():
                sub._release()

    def undecodable(self, where: str, error: MessageError) -> None:
        """A message for ``where`` (a subscriber's topic, a service) did not deserialize: logged on
        stderr (the node's log) and reported to the bus, which counts it in the node's statistics
        (``undecodable``: the container's stats, ``rce_node_undecodable_total``)."""
        print(f"[{self.full_name}] {where}: message dropped, it does not deserialize: {error.message}", file=sys.stderr)
        if self._peer is not None and not self._peer.closed.is_set():
            self._peer.tell(to_bus.BusUndecodable(where=where, error=error.message[:200]))

    def resolve(self, name: str) -> str:
        """Resolve a graph name for this node (global, relative or ``~private``)."""
        return resolve(name, self.namespace, self.name)

    def _encode(self, typename: str, msg: Any) -> bytes:
        if isinstance(msg, dict):
            return self.registry.json_to_bytes(typename, msg)
        if getattr(msg, "__msgtype__", typename) != typename:
            raise MessageError(f"expected a {wire_name(typename)} message, got {msg.__msgtype__}")
        return self.registry.serialize(typename, msg)

    def _send(self, op: int, dst: int, payload: bytes, call_id: int = 0) -> None:
        """A service request or reply: must not be lost (:meth:`rce.transport.rpc.RpcPeer.send_raw`)."""
        self._peer.send_raw(framing.encode_data_header(op, dst, 0, call_id, len(payload)), payload)

    async def _call(self, handle: int, payload: bytes, timeout: float | None) -> bytes:
        return await self._calls.call(lambda cid: self._send(framing.SRV_REQ, handle, payload, cid), timeout,
                                      what="the service call")

    def _on_data(self, frame: framing.DataFrame) -> None:
        if frame.op == framing.MSG:
            sub = self._subs.get(frame.dst)
            if sub:
                sub._push(bytes(frame.payload))
        elif frame.op in (framing.SRV_RESP, framing.SRV_ERR):
            settle_reply(self._calls, frame)
        elif frame.op == framing.SRV_REQ:
            call_id, handle, payload = frame.call_id, frame.dst, bytes(frame.payload)
            self._responder.serve(
                lambda: self._serve(handle, payload),
                lambda resp: self._send(framing.SRV_RESP, 0, resp, call_id),
                lambda error: self._send(framing.SRV_ERR, 0, error.message.encode(), call_id), f"service call {handle}")

    async def _serve(self, handle: int, payload: bytes) -> bytes:
        """Run the handler of service ``handle`` on a serialized request; the serialized response."""
        if handle not in self._services:
            raise NotFound(f"node {self.full_name} provides no service with handle {handle}")
        handler, req_t, resp_t = self._services[handle]
        try:
            req = self.registry.deserialize(req_t, payload)
        except MessageError as e:
            self.undecodable(f"service handle {handle}", e)
            raise
        resp = handler(req)
        if inspect.isawaitable(resp):
            resp = await resp
        return self._encode(resp_t, resp)

    # -- public API ----------------------------------------------------------------------------
    async def publisher(self, topic: str, msg_class: str, queue_size: int = 10) -> Publisher:
        """Advertise ``topic`` with ``msg_class`` (``pkg/Name``). Raises :class:`MessageError`
        for an unknown class or a topic of another class."""
        t = self.registry.msg_type(msg_class)
        name = self.resolve(topic)
        h = await self._peer.ask(to_bus.BusAdvertise(topic=name, type=wire_name(t)))
        return Publisher(self, name, t, h)

    async def subscriber(self, topic: str, msg_class: str, callback: Callable[[Any], Any],
                         queue_size: int = 10, decode: Callable[[bytes], Any] | None = None) -> Subscriber:
        """Subscribe ``callback(msg)`` (sync or async) to ``topic``; at most ``queue_size``
        messages wait, the oldest is dropped first (and counted in ``dropped``).

        ``decode``: ``bytes -> Any``, what the callback gets from each ROS 1 serialized message in
        place of the full message (for a node that reads a few fields of a frequent message: it
        need not build the rest); it raises :class:`MessageError` for bytes that do not fit
        ``msg_class``, which are then counted and reported as undecodable like any other."""
        t = self.registry.msg_type(msg_class)
        name = self.resolve(topic)
        sub = Subscriber(self, name, t, callback, queue_size, decode)
        sub.handle = next(self._ids)
        self._subs[sub.handle] = sub       # before the request: messages may arrive before its reply
        try:
            await self._peer.ask(to_bus.BusSubscribe(topic=name, type=wire_name(t), queue_size=queue_size,
                                                  handle=sub.handle))
        except BaseException:
            self._subs.pop(sub.handle, None)
            sub._stop()
            raise
        return sub

    async def service(self, name: str, srv_class: str, handler: Callable[[Any], Any]) -> int:
        """Provide service ``name`` of ``srv_class``; ``handler(request)`` returns the response
        (instance or dict; may be async). Returns the service handle."""
        req_t, resp_t = self.registry.srv_types(srv_class)
        h = next(self._ids)
        self._services[h] = (handler, req_t, resp_t)   # before the request: calls may arrive before its reply
        try:
            await self._peer.ask(to_bus.BusAdvertiseService(service=self.resolve(name), type=srv_class.strip("/"),
                                                         handle=h))
        except BaseException:
            self._services.pop(h, None)
            raise
        return h

    def handoff(self, state_out: Callable[[], bytes | Awaitable[bytes]],
                state_in: Callable[[bytes], Any]) -> None:
        """Carry this node's state across a move of its container (make-before-break,
        docs/placement.md "Moves"). On the old copy, once its last input is handled,
        ``state_out()`` returns the state as bytes (at most :data:`MAX_STATE`; may be async); on
        the new copy ``state_in(state)`` takes it (may be async) before the node handles any input:
        until then its inputs wait, in order, in its subscribers' queues (their ``queue_size``
        bounds them, the oldest dropped and counted first), at most :data:`HOLD_MAX` s. A node
        without a hook starts fresh. Call it before :meth:`spin`."""
        self._handoff = (state_out, state_in)
        if self._peer is not None and not self._peer.closed.is_set():
            self._peer.tell(to_bus.BusHandoff())

    async def service_proxy(self, name: str, srv_class: str) -> ServiceProxy:
        """A callable proxy for service ``name`` of ``srv_class``."""
        req_t, resp_t = self.registry.srv_types(srv_class)
        return ServiceProxy(self, self.resolve(name), req_t, resp_t)

    async def get_param(self, name: str, default: Any = _NO) -> Any:
        """Parameter value (JSON types). Raises :class:`NotFound` unless ``default`` is given."""
        try:
            return await self._peer.ask(to_bus.BusGetParam(name=self.resolve(name)))
        except RCEError:
            if default is _NO:
                raise
            return default

    async def set_param(self, name: str, value: Any) -> None:
        await self._peer.ask(to_bus.BusSetParam(name=self.resolve(name), value=value))

    async def delete_param(self, name: str) -> None:
        await self._peer.ask(to_bus.BusDeleteParam(name=self.resolve(name)))

    async def describe(self) -> dict:
        """Topics, services, parameters and nodes of the bus."""
        return await self._peer.ask(to_bus.BusDescribe())

    @property
    def is_shutdown(self) -> bool:
        return self._shutdown.is_set()

    def shutdown(self) -> None:
        """Make :meth:`spin` return."""
        self._shutdown.set()

    async def spin(self) -> None:
        """Run until :meth:`shutdown`, a signal, or the bus going away."""
        await self._shutdown.wait()

    async def close(self) -> None:
        """Disconnect from the bus; subscriber callbacks and service handlers stop."""
        self._shutdown.set()
        await self.tasks.cancel_all()
        if self._direct is not None:
            self._direct.close()
        if self._peer:
            await self._peer.close()


async def init_node(name: str | None = None, *, namespace: str | None = None, bus: str | None = None,
                    argv: list[str] | None = None, registry: MessageRegistry | None = None) -> Node:
    """Connect a new node to its bus and return it.

    ``name``/``namespace`` default to ``__name:=``/``__ns:=`` remappings, then ``RCE_NODE_NAME``/
    ``RCE_NAMESPACE``; ``bus`` to ``RCE_BUS``; the bus token (a container's bus admits only
    its own nodes) is ``RCE_BUS_TOKEN``. Raises :class:`Unavailable` if no bus is reachable,
    :class:`~rce.plumbing.errors.AuthError` if the bus refuses the token."""
    remaps = _argv_remaps(sys.argv[1:] if argv is None else argv)
    name = remaps.get("__name") or os.environ.get("RCE_NODE_NAME") or name or "node"
    namespace = remaps.get("__ns") or os.environ.get("RCE_NAMESPACE") or namespace or "/"
    bus = bus or os.environ.get("RCE_BUS")
    if not bus:
        raise Unavailable("no bus: set RCE_BUS to the bus socket (rce-ros prints it) or pass bus=")
    reg = registry or default_registry()
    load_types(reg)
    node = Node(name, join("/", namespace), bus, reg, os.environ.get("RCE_BUS_TOKEN"))
    try:
        await node._connect()
    except OSError as e:
        raise Unavailable(f"cannot reach the bus at {bus}: {e.strerror or e}") from None
    return node


def run(main: Callable[[Node], Awaitable[Any]], name: str | None = None, **kw) -> None:
    """Blocking convenience: init a node, run ``await main(node)`` until it returns or
    SIGINT/SIGTERM, then close. Exits non-zero with the reason on :class:`RCEError`."""
    async def _amain() -> None:
        node = await init_node(name, **kw)
        loop = asyncio.get_running_loop()
        task = asyncio.current_task()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, task.cancel)
        try:
            await main(node)
        except asyncio.CancelledError:
            pass
        finally:
            await node.close()
    try:
        run_loop(_amain())
    except RCEError as e:
        print(f"{name or 'node'}: {e}", file=sys.stderr)
        sys.exit(1)
