"""The bus server: node processes reach a :class:`~rce.bus.core.Bus` over a Unix socket.

Link protocol (internal framing, :mod:`rce.transport.framing`): CONTROL requests (:data:`BUS_OPS`)
``hello``, ``advertise``, ``unadvertise``, ``subscribe``, ``unsubscribe``,
``advertise_service``, ``unadvertise_service``, ``resolve_service``,
``get_param``, ``set_param``, ``delete_param``, ``describe``, and the notifications
``undecodable``, ``handoff``, ``direct_closed``, ``direct_fence`` and ``fd_channel``; DATA frames:

- node -> bus ``MSG dst=publisher handle`` publishes;
- bus -> node ``MSG dst=subscription handle`` delivers;
- bus -> node ``SRV_REQ dst=service handle call_id=c``; node answers
  ``SRV_RESP``/``SRV_ERR call_id=c``;
- node -> bus ``SRV_REQ dst=resolved service handle call_id=c``; bus answers
  ``SRV_RESP``/``SRV_ERR call_id=c``.

A node's subscriptions are bounded by the bytes waiting in its socket
(``max_buffer``) and by the age of what waits for a node that is not keeping up
(:mod:`rce.transport.link`, oldest first); messages beyond it are dropped and counted. Service calls either way
use the link layer's :class:`~rce.plumbing.pending.PendingCalls` and :class:`~rce.transport.link.Responder`.

Who may join (a container's bus: ``token`` and ``uids`` given): the socket file is mode
0660 and owned (user and group) by the container's node uid (``owner``); a connecting process whose uid
(``SO_PEERCRED``, unix(7)) is not in ``uids`` is cut off at once; every other op waits for a
``hello {name, pid, container, token}`` whose token equals the container's bus token
(``RCE_BUS_TOKEN`` in each node's environment, compared in constant time). Until then no op
but ``hello`` is served and DATA frames are ignored; a wrong or missing token gets an
:class:`~rce.plumbing.errors.AuthError` and the link is closed. Each refusal is logged and counted
(:attr:`BusServer.refused`).

Direct links (a server with ``direct=True``, a container's; :mod:`rce_container.direct_routes`):
a node that says ``direct: true`` in its hello gets an ``fd_key`` (128 random bits) and opens a
second connection whose only frame is the notification ``fd_channel {key}``. On that channel
the environment passes the node connected data-plane sockets (``SCM_RIGHTS``, unix(7)), each
with its 8-byte link id. A MSG frame whose ``src`` is not 0 names the route version its node
published it under: the subscriptions that version reached directly are skipped here.
"""
from __future__ import annotations

import asyncio
import hmac
import itertools
import os
import secrets
import socket
import struct
from collections.abc import Collection
from pathlib import Path

from rce.contract import bus as ops
from rce.transport import framing
from rce.bus.core import SERVICE_TIMEOUT, Bus, Subscription, Topic
from rce.interfaces.actions import call_timeout
from rce.plumbing.errors import AuthError, NotFound, RCEError, RequestError
from rce.transport.link import STREAM_LIMIT, Responder, settle_reply
from rce.plumbing.log import get_logger
from rce.transport.op_table import OpTable
from rce.plumbing.pending import PendingCalls
from rce.transport.rpc import RpcPeer

log = get_logger("rce.bus")

DEFAULT_MAX_BUFFER = 16 * 1024 * 1024   # bytes that may wait unread per node connection
CLOSE_TIMEOUT = 2.0                     # s :meth:`BusServer.close` waits for its listeners to close
REFUSED_LINGER = 0.1                    # s a refused node's link stays open so that it reads why
SOCKET_MODE = 0o660                     # a bus socket: its owner and group (a container's: its node uid) only
_UCRED = struct.Struct("3i")            # struct ucred {pid, uid, gid} of SO_PEERCRED

#: The ops a node sends its bus (the module doc); ``hello`` and ``fd_channel`` are served before the token is shown.
BUS_OPS = OpTable("node -> bus")


class NodeSession:
    """One connected node."""

    def __init__(self, server: "BusServer", peer: RpcPeer, sid: int):
        self.server, self.bus, self.peer = server, server.bus, peer
        self.owner = f"conn{sid}"
        self.node: str | None = None
        self.pubs: dict[int, Topic] = {}
        self.subs: dict[int, Subscription] = {}
        self.services: dict[int, str] = {}
        self.resolved: dict[int, str] = {}
        self.calls = PendingCalls(f"node {self.owner}")
        self.responder = Responder(f"bus {self.bus.name} for {self.owner}", peer.tasks)
        self.ids = itertools.count(1)
        self.direct = False                # the node takes direct links (hello ``direct``)
        self.fd_key: str | None = None                     # names its fd channel until it is opened
        self.fd_sock: socket.socket | None = None          # its fd channel, once it has opened it
        self.channel: RpcPeer | None = None
        self.routes: dict[int, dict[int, frozenset[Subscription]]] = {}   # handle -> version -> reached
        # what this node published (in) and was delivered (out), for per-node statistics
        self.msgs_in = self.bytes_in = self.msgs_out = self.bytes_out = 0
        self.undecodable = 0           # messages the node reported it could not deserialize
        self.handoff = False           # the node hands its state over when its container moves
        peer.on_close = lambda _p: self.close()
        peer.link.on_drop = self._lost
        if server.token is None:
            self._admit()
        else:                              # nothing but hello (and an fd channel) until the token is shown
            peer.handlers.update(BUS_OPS.handlers(self, unauthenticated=True))

    def _lost(self, tag: tuple[int, int]) -> None:
        """A delivery the link took was dropped from its queue (the node is not keeping up)."""
        handle, n = tag
        sub = self.subs.get(handle)
        if sub is not None:
            sub.dropped += 1
        self.msgs_out -= 1
        self.bytes_out -= n

    def _admit(self) -> None:
        self.peer.handlers.update(BUS_OPS.handlers(self))
        self.peer.on_data = self.on_data

    def stats(self) -> dict:
        """``{node, msgs_in, bytes_in, msgs_out, bytes_out, dropped, undecodable}``: in = published
        by the node, out = delivered to it, dropped = messages its subscriptions could not take,
        undecodable = messages delivered to it that it could not deserialize (its own report)."""
        return {"node": self.node, "msgs_in": self.msgs_in, "bytes_in": self.bytes_in, "msgs_out": self.msgs_out,
                "bytes_out": self.bytes_out, "dropped": sum(s.dropped for s in self.subs.values()),
                "undecodable": self.undecodable}

    @BUS_OPS.op("handoff", args=ops.BusHandoff)
    async def op_handoff(self, args: ops.BusHandoff) -> None:
        """The node hands its state over when its container moves (:meth:`rce.node.Node.handoff`)."""
        self.handoff = True

    @BUS_OPS.op("undecodable", args=ops.BusUndecodable)
    async def op_undecodable(self, args: ops.BusUndecodable) -> None:
        """``{where, error}``: the node could not deserialize a message delivered to it (counted)."""
        self.undecodable += 1
        log.warning("node could not deserialize a message", node=self.node, where=args.where[:100],
                    error=args.error[:200])

    # -- control ops ---------------------------------------------------------------------------
    @BUS_OPS.op("hello", args=ops.BusHello, unauthenticated=True)
    async def op_hello(self, args: ops.BusHello) -> dict:
        """``{name, pid, container, token}`` -> ``{bus}``. Raises :class:`AuthError` (and
        closes the link) when the bus has a token and ``token`` is not it."""
        token = self.server.token
        if token is not None and self.node is None:
            given = args.token
            if not isinstance(given, str) or not hmac.compare_digest(given.encode(), token.encode()):
                self.server.refuse(f"hello of {args.name!r} (pid {args.pid!r}) with "
                                   + ("no" if given is None else "a wrong") + " bus token")
                self.peer.tasks.spawn(self._drop(), name="drop a refused node")
                raise AuthError(f"bus {self.bus.name}: wrong or missing bus token (RCE_BUS_TOKEN); "
                                "only the container's own nodes may join its bus")
            self._admit()
        self.node = args.name or self.owner
        self.owner = self.calls.name = self.node
        self.bus.nodes[self.node] = {"pid": args.pid, "container": args.container}
        reply = {"bus": self.bus.name}
        if self.server.direct and args.direct and not self.direct:
            self.direct = True
            reply["fd_key"] = self.fd_key = secrets.token_hex(16)
            self.server.fd_keys[self.fd_key] = self
        self.server.changed()
        return reply

    @BUS_OPS.op("fd_channel", args=ops.BusFdChannel, unauthenticated=True)
    async def op_fd_channel(self, args: ops.BusFdChannel) -> None:
        """``{key}`` (a notification, the only frame of a node's second connection): this
        connection is the fd channel of the session whose hello got ``fd_key`` = ``key``."""
        owner = self.server.fd_keys.pop(args.key, None) if isinstance(args.key, str) else None
        if owner is None or owner.fd_sock is not None or self.node is not None:
            self.server.refuse("an fd channel with an unknown key")
            self.peer.tasks.spawn(self._drop(), name="drop a refused fd channel")
            return
        self.server.sessions.discard(self)          # a channel, not a node
        self.peer.handlers.clear()
        sock = self.peer.link.writer.get_extra_info("socket")
        owner.fd_sock = socket.socket(fileno=os.dup(sock.fileno()))
        owner.channel = self.peer
        self.server.changed()

    @BUS_OPS.op("advertise", args=ops.BusAdvertise)
    async def op_advertise(self, args: ops.BusAdvertise) -> int:
        t = self.bus.advertise(args.topic, args.type, self.owner)
        h = next(self.ids)
        self.pubs[h] = t
        self.server.changed()
        return h

    @BUS_OPS.op("unadvertise", args=ops.BusUnadvertise)
    async def op_unadvertise(self, args: ops.BusUnadvertise) -> None:
        t = self.pubs.pop(args.handle, None)
        if t:
            self.bus.unadvertise(t.name, self.owner)

    def _handle(self, h: int | None) -> int:
        """The handle the node chose (so frames can arrive before the reply), or a fresh one."""
        if h is None:
            return next(self.ids) + (1 << 40)
        if h <= 0 or h >= (1 << 40) or h in self.subs or h in self.services:
            raise RequestError(f"bad or duplicate handle {h!r}")
        return h

    @BUS_OPS.op("subscribe", args=ops.BusSubscribe)
    async def op_subscribe(self, args: ops.BusSubscribe) -> int:
        h = self._handle(args.handle)
        offer = self.peer.link.offer

        def deliver(payload: bytes, _h=h) -> bool:
            n = len(payload)
            if not offer(framing.encode_data_header(framing.MSG, _h, 0, 0, n), payload, (_h, n)):
                return False
            self.msgs_out += 1
            self.bytes_out += n
            return True
        self.subs[h] = self.bus.subscribe(args.topic, args.type, deliver, self.owner, args.queue_size)
        self.server.changed()
        return h

    @BUS_OPS.op("unsubscribe", args=ops.BusUnsubscribe)
    async def op_unsubscribe(self, args: ops.BusUnsubscribe) -> None:
        sub = self.subs.pop(args.handle, None)
        if sub:
            self.bus.unsubscribe(sub)

    @BUS_OPS.op("advertise_service", args=ops.BusAdvertiseService)
    async def op_advertise_service(self, args: ops.BusAdvertiseService) -> int:
        h = self._handle(args.handle)

        async def handler(payload: bytes, _h=h) -> bytes:
            # no timeout of its own: the bus's call_service bounds the call and cancels this
            return await self.calls.call(
                lambda cid: self.peer.send_raw(framing.encode_data_header(framing.SRV_REQ, _h, 0, cid, len(payload)),
                                               payload), None, what=f"the call to its service {args.service!r}")
        self.bus.advertise_service(args.service, args.type, handler, self.owner)
        self.services[h] = args.service
        self.server.changed()
        return h

    @BUS_OPS.op("unadvertise_service", args=ops.BusUnadvertiseService)
    async def op_unadvertise_service(self, args: ops.BusUnadvertiseService) -> None:
        name = self.services.pop(args.handle, None)
        if name:
            self.bus.unadvertise_service(name, self.owner)

    @BUS_OPS.op("resolve_service", args=ops.BusResolveService)
    async def op_resolve_service(self, args: ops.BusResolveService) -> dict:
        s = self.bus.services.get(args.service)
        if s is None:
            raise NotFound(f"service {args.service!r} is not provided on {self.bus.name}")
        h = next(self.ids)
        self.resolved[h] = s.name
        return {"handle": h, "type": s.type}

    @BUS_OPS.op("direct_closed", args=ops.BusDirectClosed)
    async def op_direct_closed(self, args: ops.BusDirectClosed) -> None:
        """``{link}`` (a notification): the node's direct link ``link`` ended."""
        for cb in self.server.on_direct_closed:
            cb(self, args.link)

    @BUS_OPS.op("direct_fence", args=ops.BusDirectFence)
    async def op_direct_fence(self, args: ops.BusDirectFence) -> None:
        """``{fence, src, dst}`` (a notification): a fence of ``src -> dst`` came on one of the node's
        direct links, behind everything that came there before it (:meth:`rce.transport.dataplane.DataPlane.fence`)."""
        for cb in self.server.on_direct_fence:
            cb(args.fence, args.src, args.dst)

    @BUS_OPS.op("get_param", args=ops.BusGetParam)
    async def op_get_param(self, args: ops.BusGetParam):
        return self.bus.get_param(args.name)

    @BUS_OPS.op("set_param", args=ops.BusSetParam)
    async def op_set_param(self, args: ops.BusSetParam) -> None:
        self.bus.set_param(args.name, args.value)

    @BUS_OPS.op("delete_param", args=ops.BusDeleteParam)
    async def op_delete_param(self, args: ops.BusDeleteParam) -> None:
        self.bus.delete_param(args.name)

    @BUS_OPS.op("describe", args=ops.BusDescribe)
    async def op_describe(self, args: ops.BusDescribe) -> dict:
        return self.bus.describe()

    # -- data ----------------------------------------------------------------------------------
    def on_data(self, f: framing.DataFrame) -> None:
        if f.op == framing.MSG:
            t = self.pubs.get(f.dst)
            if t is not None:
                self.msgs_in += 1
                self.bytes_in += len(f.payload)
                skip = ()
                if f.src:                            # published under a direct route: skip what it reached
                    skip = self.routes.get(f.dst, {}).get(f.src, ())
                self.bus.publish(t, f.payload, skip)      # a view nobody writes again (rce.transport.framing): no copy
        elif f.op in (framing.SRV_RESP, framing.SRV_ERR):
            settle_reply(self.calls, f)
        elif f.op == framing.SRV_REQ:
            self._serve_call(f.dst, f.call_id, bytes(f.payload))

    def _serve_call(self, handle: int, call_id: int, payload: bytes) -> None:
        """The node calls the service it resolved as ``handle``; the answer goes back with ``call_id``."""
        name = self.resolved.get(handle)
        send = self.peer.send_raw

        async def call() -> bytes:
            if name is None:
                raise NotFound(f"unknown service handle {handle}")
            s = self.bus.services.get(name)    # an action's get_result waits for its goal's end, not 30 s
            return await self.bus.call_service(name, payload, timeout=call_timeout(s.type) if s else SERVICE_TIMEOUT)

        def reply(resp: bytes) -> None:
            send(framing.encode_data_header(framing.SRV_RESP, 0, 0, call_id, len(resp)), resp)

        def refuse(e: RCEError) -> None:
            send(framing.encode_data(framing.SRV_ERR, 0, 0, call_id, e.message.encode()))
        self.responder.serve(call, reply, refuse, f"call to {name or handle}")

    async def _drop(self) -> None:
        await asyncio.sleep(REFUSED_LINGER)
        await self.peer.close()

    def close(self) -> None:
        for t in self.pubs.values():
            self.bus.unadvertise(t.name, self.owner)
        for sub in self.subs.values():
            self.bus.unsubscribe(sub)
        for name in self.services.values():
            self.bus.unadvertise_service(name, self.owner)
        self.calls.fail_all(RequestError(f"node {self.owner!r} left while serving a call"))
        self.routes.clear()
        if self.fd_sock is not None:
            self.fd_sock.close()
            self.fd_sock = None
            self.channel.link.close("its node left")
        if self.fd_key is not None:
            self.server.fd_keys.pop(self.fd_key, None)
        if self.node:
            self.bus.nodes.pop(self.node, None)
        self.pubs, self.subs, self.services = {}, {}, {}
        self.server.sessions.discard(self)
        self.server.changed()


class BusServer:
    """Serves ``bus`` on Unix socket(s). ``max_buffer``: bytes that may wait per node connection.

    ``token``: the bus token a node must give in ``hello`` (None: no check, e.g. a robot's
    local bus under ``rce-ros``, whose socket only its user can reach); ``uids``: the uids a
    connecting process may have (None: any); ``owner``: uid that owns the socket file
    (default: this process's); ``direct``: offer nodes direct links (module doc). ``refused``
    counts the connections turned away."""

    def __init__(self, bus: Bus, max_buffer: int = DEFAULT_MAX_BUFFER, *, token: str | None = None,
                 uids: Collection[int] | None = None, owner: int | None = None, direct: bool = False):
        self.bus = bus
        self.direct = direct
        self.fd_keys: dict[str, NodeSession] = {}
        self.on_direct_closed: list = []     # cb(session, link id): a node's direct link ended
        self.on_direct_fence: list = []      # cb(fence id, src, dst): a fence came on a node's direct link
        self.max_buffer = max_buffer
        self.token, self.owner = token, owner
        self.uids = None if uids is None else frozenset(uids)
        self.refused = 0
        self.sessions: set[NodeSession] = set()
        self._servers: list[asyncio.AbstractServer] = []
        self._ids = itertools.count(1)

    def changed(self) -> None:
        """Tell the bus's ``on_change`` listeners that its graph changed (a node came, a topic...)."""
        for cb in self.bus.on_change:
            cb()

    def refuse(self, why: str) -> None:
        """Count and log a connection turned away."""
        self.refused += 1
        log.warning("bus connection refused", bus=self.bus.name, reason=why, refused=self.refused)

    async def listen(self, path: str | Path) -> None:
        """Listen on Unix socket ``path`` (replacing a stale socket file); mode
        :data:`SOCKET_MODE`, owned by ``owner``."""
        path = str(path)
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        if os.path.exists(path):
            os.unlink(path)
        srv = await asyncio.start_unix_server(self._accept, path, limit=STREAM_LIMIT)
        os.chmod(path, SOCKET_MODE)
        if self.owner is not None and self.owner != os.geteuid():
            os.chown(path, self.owner, self.owner)       # group too: 0660 reaches no one else
        self._servers.append(srv)

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.uids is not None:
            sock = writer.get_extra_info("socket")
            pid, uid, _gid = _UCRED.unpack(sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _UCRED.size))
            if uid not in self.uids:
                self.refuse(f"a process of uid {uid} (pid {pid}) is not a node of this container")
                writer.close()
                return
        peer = RpcPeer(reader, writer, name=f"{self.bus.name}-node", max_buffer=self.max_buffer)
        self.sessions.add(NodeSession(self, peer, next(self._ids)))
        peer.start()

    async def close(self) -> None:
        """Stop listening and drop every node connection."""
        for s in self._servers:
            s.close()
        for sess in list(self.sessions):
            await sess.peer.close()
        for s in self._servers:
            try:
                async with asyncio.timeout(CLOSE_TIMEOUT):
                    await s.wait_closed()
            except TimeoutError:
                pass
        self._servers.clear()
