"""An environment's direct routes: which topic traffic of its nodes goes straight between the
node and the far data plane (a robot endpoint, another environment), past this process.

The environment stays the directory, as the ROS master is for TCPROS: it knows the bus graph,
the interfaces and their connections, and the credentials; the node only carries the bytes
(:mod:`rce.node.links`). A message that takes a direct route crosses two event loops fewer.

Rules, recomputed whenever the bus graph, an interface or a connection changes:

- **Node -> peers.** For a container-side ``SubscriberInterface`` S on topic T, connected to
  peer interfaces R at data addresses A: every node that publishes T (and takes direct links)
  sends each message straight to each R, from S, on its direct link to A. It still sends the
  message to the bus, marked with the route's version so that the bus skips S, only while T
  has other subscribers.
- **Peers -> nodes.** For a container-side ``PublisherInterface`` X on topic T: while every
  subscription of T belongs to nodes that take direct links, each of those nodes claims X on
  its direct link to each of X's peers' addresses, as one member of a numbered claim set
  (:mod:`rce.transport.dataplane`, "Direct links"); once the set is complete, the peers' planes send
  X's messages to each member. Any other subscriber (an interface, ``bus_sample``, a
  recording, a ROS 1 node) ends the claims, and the messages come through the bus again; a
  change of members starts a new set, and until it is complete the bus carries them.
- **Order.** A node's new route holds its messages until what it sent by the bus before has
  been handed on at the far ends (:meth:`rce.transport.dataplane.DataPlane.flush`), when the
  environment's links there carried any, or the node had published by the bus (it answers
  ``held``: those may still be on its bus link, and this environment reads them before the
  answer). When a claim set completes, messages the peers sent through this environment just
  before may still be on their way; the nodes hold what comes directly until this environment
  has passed the far plane's switch marker on to them (:meth:`DirectRoutes.switch_arrived`).
- A ``SubscriberInterface`` with a peer of the other ROS (ROS 1 and ROS 2 ends,
  :mod:`rce.messages.convert`) is served by the bus: it converts what it sends there.
- Services, and nodes that do not take direct links (ROS 1 nodes' relay, older runtimes), go
  through the bus as before.

A direct link is a TCP connection this environment dials to the far plane (reading its nonce),
then passes to the node on the node's fd channel (:mod:`rce.bus.server`): a sandboxed node has
no network of its own, but a socket it is given works. The grants each route needs are
computed here, from this environment's credentials and the link's nonce, and sent by the node.
A link that ends (its node or its far end died) ends its routes; the node notifies
``direct_closed`` and the routes are recomputed, redialling after :data:`RETRY`.

Counters: each node counts what it sent and received for each interface; :meth:`collect`
(run before ``stats``) adds them into the interfaces' and the node's counters.
"""
from __future__ import annotations

import asyncio
import itertools
import socket
import time
from typing import TYPE_CHECKING, Any

from rce.contract import node as to_node
from rce.transport import cluster_auth

from rce.transport import framing
from rce.bus.core import Subscription
from rce.transport.dataplane import parse_nonce
from rce.plumbing.errors import ProtocolError, RCEError
from rce.transport.link import data_socket
from rce.plumbing.log import get_logger
from rce.node.links import LINK_ID
from rce.plumbing.tasks import Tasks
from rce_container.interfaces import BusInterface, PublisherInterface, SubscriberInterface

if TYPE_CHECKING:
    from rce.bus.server import NodeSession

log = get_logger("rce.container.direct")

DIAL_TIMEOUT = 5.0     # s to connect to a far plane and read its nonce
RETRY = 2.0            # s before a far plane that could not be dialled is tried again
CALL_TIMEOUT = 5.0     # s a node has to apply a route
COUNTS_TIMEOUT = 1.0   # s a node has to report its counters to :meth:`DirectRoutes.collect`


class _NodeLink:
    """A direct link of one node: its id, far address, the far plane's nonce, pairs granted."""

    __slots__ = ("lid", "addr", "nonce", "granted")

    def __init__(self, lid: int, addr: str, nonce: bytes):
        self.lid, self.addr, self.nonce = lid, addr, nonce
        self.granted: set[tuple[int, int]] = set()


class _NodeState:
    """What the routes of one node session are: its links by far address, the route key of
    each publisher handle, the claims ``(addr, iid) -> (peers, handles, gen, size)``, counters seen."""

    def __init__(self) -> None:
        self.links: dict[str, _NodeLink] = {}
        self.pubs: dict[int, tuple] = {}
        self.claims: dict[tuple[str, int], tuple] = {}      # (addr, iid) -> (peers, handles, gen, size)
        self.failed: dict[str, float] = {}
        self.seen: dict[int, tuple[int, int, int]] = {}


class DirectRoutes:
    """Keeps the direct routes of ``env``'s nodes (module doc). Start with :meth:`start`.
    ``env``: the :class:`rce_container.environment.Environment` (its ``bus``, ``plane``,
    ``containers`` and ``interfaces`` are read, never changed)."""

    def __init__(self, env: Any):
        self.env = env
        self.states: dict[NodeSession, _NodeState] = {}
        self.tasks = Tasks("direct routes")
        self._dirty = asyncio.Event()
        self._links = itertools.count(1)
        self._versions = itertools.count(1)
        self._gens: dict[int, tuple[int, tuple]] = {}     # PublisherInterface id -> (claim generation, its shape)
        env.bus.on_graph.append(self.touch)
        env.bus.on_change.append(self.touch)
        env.plane.on_switch.append(self.switch_arrived)
        # counters (environment stats)
        self.links_opened = self.dial_failures = self.route_failures = 0

    def start(self) -> None:
        self.tasks.spawn(self._run(), name="direct routes")

    async def close(self) -> None:
        await self.tasks.cancel_all()

    def touch(self) -> None:
        """Something the routes depend on changed: recompute them soon."""
        self._dirty.set()

    def link_closed(self, session: NodeSession, lid: int) -> None:
        """``direct_closed {link}`` from ``session``'s node: forget the link, recompute."""
        st = self.states.get(session)
        if st is not None:
            for addr, nl in list(st.links.items()):
                if nl.lid == lid:
                    del st.links[addr]
                    st.pubs = {h: k for h, k in st.pubs.items() if addr not in k[2]}
                    st.claims = {k: v for k, v in st.claims.items() if k[0] != addr}
        self.touch()

    def switch_arrived(self, iid: int, sid: int) -> None:
        """A far plane's switch marker ``sid`` for interface ``iid`` came, behind every message it sent
        here before (:mod:`rce.transport.dataplane`, "Direct links"), and those are on the bus: tell
        the nodes, behind those messages on their bus links, so that the claimers among them stop
        holding what came to them directly."""
        for session in self.states:
            session.peer.tell(to_node.DirectSwitch(iid=iid, id=sid))

    def stats(self) -> dict:
        """``{enabled, nodes, links, routes, claims, links_opened, dial_failures, route_failures}``."""
        return {"enabled": True, "nodes": len(self.states), "links": sum(len(s.links) for s in self.states.values()),
                "routes": sum(len(s.pubs) for s in self.states.values()),
                "claims": sum(len(s.claims) for s in self.states.values()),
                "links_opened": self.links_opened, "dial_failures": self.dial_failures,
                "route_failures": self.route_failures}

    async def _run(self) -> None:
        while True:
            await self._dirty.wait()
            self._dirty.clear()
            try:
                await self.reconcile()
            except Exception as e:            # a bug here must not end direct routing for good
                log.error("direct routes: reconcile failed", exc_info=e)

    # -- the routes ------------------------------------------------------------------------------
    def _sessions(self) -> list[NodeSession]:
        return [s for c in list(self.env.containers.values()) for s in c.server.sessions
                if s.direct and s.fd_sock is not None and not s.peer.closed.is_set()]

    async def reconcile(self) -> None:
        """Bring every node's routes and claims to what the rules (module doc) say now."""
        sessions = self._sessions()
        for s in [s for s in self.states if s not in sessions]:
            del self.states[s]
        served_by: dict[Subscription, SubscriberInterface] = {}
        publishers: list[PublisherInterface] = []
        for iface in list(self.env.interfaces.values()):
            if isinstance(iface, SubscriberInterface) and iface.sub is not None and iface.peers \
                    and not iface.conversions:      # a peer of the other ROS gets what the interface converts
                served_by[iface.sub] = iface
            elif isinstance(iface, PublisherInterface) and iface.topic is not None and iface.peers:
                publishers.append(iface)
        claims = self._wanted_claims(sessions, publishers)
        for s in sessions:
            st = self.states.setdefault(s, _NodeState())
            try:
                for h, topic in list(s.pubs.items()):
                    await self._publisher(s, st, h, topic.subscriptions, served_by)
                for h in [h for h in st.pubs if h not in s.pubs]:
                    del st.pubs[h]
                await self._claims(s, st, claims.get(s, {}))
            except RCEError as e:             # the node left, or is too slow: the next change retries
                self.route_failures += 1
                log.debug("direct routes: a node did not take its routes", node=s.node, reason=e.message)

    def _wanted_claims(self, sessions: list[NodeSession], publishers: list[PublisherInterface]) -> dict:
        """``{session: {(addr, iid): (peers, handles, gen, size)}}``: the claims the rules want now.
        A claim set keeps its generation while its members, their handles and the peers stay."""
        node_subs = {sub: s for s in sessions for sub in s.subs.values()}
        out: dict[NodeSession, dict] = {}
        for x in publishers:
            subs = x.topic.subscriptions
            if not subs or not all(sub in node_subs for sub in subs):
                continue
            members: dict[NodeSession, tuple[int, ...]] = {}
            for s in {node_subs[sub] for sub in subs}:
                members[s] = tuple(sorted(h for h, sub in s.subs.items() if sub.topic is x.topic))
            by_addr: dict[str, tuple[int, ...]] = {}
            for peer, addr in self._sendable(x):
                by_addr[addr] = (*by_addr.get(addr, ()), peer)
            shape = (frozenset((id(s), h) for s, h in members.items()), tuple(sorted(by_addr.items())))
            gen = self._gens.get(x.iid)
            if gen is None or gen[1] != shape:
                gen = self._gens[x.iid] = (next(self._versions), shape)
            for s, handles in members.items():
                for addr, peers in by_addr.items():
                    out.setdefault(s, {})[(addr, x.iid)] = (peers, handles, gen[0], len(members))
        live = {x.iid for x in publishers}
        self._gens = {k: v for k, v in self._gens.items() if k in live}
        return out

    def _sendable(self, iface: BusInterface) -> list[tuple[int, str]]:
        """``[(peer, addr)]``, sorted: the peers of ``iface`` this environment holds a credential
        for (the grants a direct link needs are made from it)."""
        return sorted((peer, addr) for peer, addr in iface.peers.items()
                      if (iface.iid, peer) in self.env.plane.credentials)

    async def _publisher(self, session: NodeSession, st: _NodeState, handle: int, subs: list[Subscription],
                         served_by: dict[Subscription, SubscriberInterface]) -> None:
        served = [sub for sub in subs if sub in served_by]
        targets = sorted((addr, peer, served_by[sub].iid) for sub in served
                         for peer, addr in self._sendable(served_by[sub]))
        local = len(served) < len(subs)
        key = (tuple(targets), local, frozenset(a for a, _, _ in targets))
        if st.pubs.get(handle, ((), True, frozenset())) == key:
            return
        links = {addr: await self._link(session, st, addr) for addr in key[2]}
        if not all(links.values()):
            targets, key = [], ((), True, frozenset())      # a far plane is unreachable: all by the bus
        if not targets:
            await session.peer.ask(to_node.DirectPublish(handle=handle, version=0, targets=[], local=True, grants=[]),
                                   CALL_TIMEOUT)
            session.routes.pop(handle, None)
            st.pubs[handle] = key
            return
        grants = self._grants([(links[addr], src, dst) for addr, dst, src in targets])
        version = next(self._versions)
        reached = {src for _, _, src in targets}
        session.routes.setdefault(handle, {})[version] = frozenset(sub for sub in served
                                                                   if served_by[sub].iid in reached)
        plane = self.env.plane
        behind = {addr for addr, dst, src in targets if plane.carried(addr, dst)}
        reply = None
        try:
            reply = await session.peer.ask(to_node.DirectPublish(
                handle=handle, version=version, local=local, grants=grants, hold=bool(behind),
                targets=[(links[addr].lid, dst, src) for addr, dst, src in targets]), CALL_TIMEOUT)
        finally:        # also when the call timed out: the node may have taken the route all the same
            if reply is None or reply.get("held"):     # with hold=bool(behind), a node holds when behind
                # the node's bus messages sent before its answer came ahead of it on its bus link, and
                # are on the far ends' links now: what went by the bus first reaches them first
                behind |= {addr for addr, dst, src in targets if plane.carried(addr, dst)}
                self.tasks.spawn(self._go(session, handle, version, behind), name=f"direct go {handle}")
        # frames of older versions have all arrived
        session.routes[handle] = {version: session.routes[handle][version]}
        st.pubs[handle] = key

    async def _go(self, session: NodeSession, handle: int, version: int, addrs: set[str]) -> None:
        """Once the far planes at ``addrs`` have handed on what this environment sent them, let
        route ``version`` of ``session``'s publisher ``handle`` send what it held."""
        unflushed = await self.env.plane.flush(addrs, CALL_TIMEOUT)
        if unflushed:
            log.warning("direct route released unflushed", node=session.node, handle=handle, peers=unflushed)
        session.peer.tell(to_node.DirectGo(handle=handle, version=version))

    async def _claims(self, session: NodeSession, st: _NodeState, wanted: dict) -> None:
        for key in [k for k in st.claims if k not in wanted]:
            nl = st.links.get(key[0])
            del st.claims[key]
            if nl is not None:
                await session.peer.ask(to_node.DirectUnsubscribe(link=nl.lid, iid=key[1]), CALL_TIMEOUT)
        for (addr, iid), claim in wanted.items():
            if st.claims.get((addr, iid)) == claim:
                continue
            nl = await self._link(session, st, addr)
            if nl is None:
                continue
            peers, handles, gen, size = claim
            grants = self._grants([(nl, iid, peer) for peer in peers])
            await session.peer.ask(to_node.DirectSubscribe(
                link=nl.lid, iid=iid, peers=list(peers), handles=list(handles), gen=gen, size=size, grants=grants,
                at=self.env.plane.addr), CALL_TIMEOUT)
            st.claims[(addr, iid)] = claim

    def _grants(self, pairs: list[tuple[_NodeLink, int, int]]) -> list[to_node.Grant]:
        """``[[link id, grant frame]]`` for each ``(link, src, dst)`` not yet granted on its link."""
        out = []
        for nl, src, dst in pairs:
            token = self.env.plane.credentials.get((src, dst))
            if token is not None and (src, dst) not in nl.granted:
                out.append((nl.lid, cluster_auth.grant_frame(token, nl.nonce, src, dst)))
                nl.granted.add((src, dst))
        return out

    # -- links -----------------------------------------------------------------------------------
    async def _link(self, session: NodeSession, st: _NodeState, addr: str) -> _NodeLink | None:
        """``session``'s node's direct link to ``addr``, dialled and handed over if it has none; None
        if ``addr`` cannot be reached now (retried after :data:`RETRY`)."""
        nl = st.links.get(addr)
        if nl is not None:
            return nl
        if st.failed.get(addr, 0.0) > time.monotonic():
            return None
        try:
            sock, nonce = await dial(addr)
        except (OSError, ProtocolError, asyncio.TimeoutError) as e:
            self.dial_failures += 1
            st.failed[addr] = time.monotonic() + RETRY
            asyncio.get_running_loop().call_later(RETRY, self.touch)
            log.warning("direct link: cannot dial a far plane; its traffic goes by the bus", addr=addr,
                        reason=str(e) or type(e).__name__)
            return None
        lid = next(self._links)
        try:
            if session.fd_sock is None:
                raise OSError("its fd channel is closed")
            socket.send_fds(session.fd_sock, [LINK_ID.pack(lid)], [sock.fileno()])
        except OSError as e:
            raise ProtocolError(f"cannot pass a direct link to node {session.node!r}: {e}") from None
        finally:
            sock.close()                  # the node holds its own copy now
        await session.peer.ask(to_node.DirectLink(link=lid, name=addr), CALL_TIMEOUT)
        nl = st.links[addr] = _NodeLink(lid, addr, nonce)
        self.links_opened += 1
        return nl

    # -- counters --------------------------------------------------------------------------------
    async def collect(self) -> None:
        """Add what each node sent and received on its direct routes since the last collect to
        the interfaces' counters (``msgs/bytes in/out``, ``dropped``) and the node's."""
        for s, st in list(self.states.items()):
            if not st.links:
                continue
            try:
                counts = await s.peer.ask(to_node.DirectCounts(), COUNTS_TIMEOUT)
            except RCEError:
                continue
            for key, value in (counts or {}).items():
                iid, (m, b, d) = int(key), value
                pm, pb, pd = st.seen.get(iid, (0, 0, 0))
                st.seen[iid] = (m, b, d)
                iface = self.env.interfaces.get(iid)
                if isinstance(iface, SubscriberInterface):       # the node published, straight to peers
                    iface.msgs_out += m - pm
                    iface.bytes_out += b - pb
                    s.msgs_in += m - pm
                    s.bytes_in += b - pb
                elif isinstance(iface, PublisherInterface):      # peers sent, straight to the node
                    iface.msgs_in += m - pm
                    iface.bytes_in += b - pb
                    s.msgs_out += m - pm
                    s.bytes_out += b - pb
                if iface is not None:
                    iface.dropped += d - pd


async def dial(addr: str) -> tuple[socket.socket, bytes]:
    """Connect to the data plane at ``addr`` (``host:port``, ``[v6]:port``) and read its nonce;
    returns the non-blocking socket (:func:`rce.transport.link.data_socket`) and the nonce. Raises :class:`OSError`,
    :class:`ProtocolError` or :class:`asyncio.TimeoutError` after :data:`DIAL_TIMEOUT` s."""
    loop = asyncio.get_running_loop()
    host, _, port = addr.rpartition(":")
    infos = await loop.getaddrinfo(host.strip("[]"), int(port), type=socket.SOCK_STREAM)
    family, kind, proto, _name, sockaddr = infos[0]
    sock = socket.socket(family, kind, proto)
    sock.setblocking(False)
    try:
        async with asyncio.timeout(DIAL_TIMEOUT):
            await loop.sock_connect(sock, sockaddr)
            data_socket(sock)
            decoder = framing.FrameDecoder(max_frame=4096)
            while True:
                data = await loop.sock_recv(sock, 4096)
                if not data:
                    raise ConnectionError(f"{addr} closed the link before its nonce")
                for f in decoder.feed(data):
                    if isinstance(f, dict) and "nonce" in f:
                        return sock, parse_nonce(f["nonce"])
                    raise ProtocolError(f"{addr} sent something other than its nonce")
    except BaseException:
        sock.close()
        raise
