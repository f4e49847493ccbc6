"""The data plane: direct endpoint <-> endpoint links (robot endpoint <-> environment,
environment <-> environment); the master carries no data.

Every endpoint process (an rce-robot task set, an environment) runs one
:class:`DataPlane`: a TCP listener for incoming links, and one outgoing link per
peer address, opened on first use. Frames are DATA frames of
:mod:`rce.transport.framing` addressed by interface id (``dst``), so one link carries every
connection between the two processes. Topic messages and service requests go on the
links a process dialled; a service's reply goes back on the link its request came in on.

Only peers the master introduced send (:mod:`rce.transport.cluster_auth`, "Data-plane credentials"):

- the acceptor of a link first sends ``{"nonce": hex}``; the dialler holds its frames until
  then;
- before its first frame from interface ``src`` to interface ``dst`` the dialler sends a grant
  ``{"grant": [src, dst], "proof": hex}`` made from the credential the master handed it with
  ``connect`` (:meth:`DataPlane.allow`); the acceptor checks it with its own data key, and a
  wrong one closes the link (counted in ``unauthenticated``, logged);
- a topic message or service request whose ``(src, dst)`` was not granted on its link, or whose
  ``src`` is not connected to interface ``dst`` (not among its ``peers``), is dropped and counted
  in ``refused`` (the first of each link is logged); a reply is taken only on a link this
  plane dialled, for a call in flight;
- a link that has no valid grant within :data:`GRANT_TIMEOUT`, or beyond :data:`MAX_ACCEPTED`
  links, is closed (counted in ``unauthenticated``).

Direct links (nodes' shortcut past their environment, :mod:`rce_container.direct_routes`): a
dialler that was granted ``(x, dst)`` on a link speaks for interface ``x`` and may *claim* it,
``{"claim": x, "gen": g, "size": n}``: generation ``g`` of ``x``'s claim set has ``n`` members
(the nodes that subscribe to what ``x`` publishes; ``"at": addr``, the data address of ``x``'s
environment: a claim made at an address this plane does not send ``x``'s messages to, a moved
container's new copy before its switch, waits until it does). While all ``n`` of the newest generation
have claimed, this plane sends what its interfaces send to ``x`` on each of their accepted links
(one copy each) instead of to ``x``'s own address; while the set is incomplete (being built, or
a member released or gone), everything goes to ``x``'s address as before, so no member misses
a message and none gets one twice. ``{"release": x}`` takes this link out of the set and is
answered ``{"released": x}`` (every frame for ``x`` sent before it has gone ahead). A claim
without such a grant closes the link (``unauthenticated``); claims end with their link.

Switch markers keep the order across that change of path. Messages sent to ``x``'s address just
before the set completed may still be on their way (in the backlog of a link that connects, in
the environment, on its bus) when the first direct one reaches a member. So when a set completes
and the link dialled to ``x``'s address has carried or holds anything for ``x``, this plane sends
``{"switch": x, "id": s}`` there, behind those messages, and ``{"switch": x, "id": s}`` on each
member's link, ahead of the first direct message. The environment's plane, once it has handed on
everything before its marker, tells the members through their bus (:attr:`DataPlane.on_switch`);
a member holds what comes directly for ``x`` until then (:mod:`rce.node.links`).

Fences and end of stream (a container's move, :mod:`rce_master.placement.mover`): when a connection's peer is
pointed at a new address (:meth:`DataPlane.fence`), this plane first sends ``{"fence": [src, dst],
"id": f}`` on every path that carried ``src -> dst`` to the old copy (its dialled link to the old
address, and each accepted link of ``dst``'s claim set), after the last message it sent there; the
old copy's plane counts each fence it gets (:meth:`DataPlane.fence_arrived`; a node's direct link
reports the fences it gets the same way), so it knows when nothing more will come. What this plane
had sent to the old copy but still holds (a link's backlog or queue, behind a thin link) it first
takes back and sends to the new address, ahead of what follows (:meth:`DataPlane.take_unsent`): the
old copy never gets it, the new one gets it once. Before the old
copy goes, :meth:`DataPlane.flush` sends ``{"eos": k}`` on its links to its peers and waits for
each peer's ``{"eos_ack": k}``, which the peer sends once it has handed on every frame before it.

What receives frames registers here by id as a :class:`Receiver` (the interfaces of
:mod:`rce.transport.interface`). Outgoing links are bounded (``max_buffer`` bytes waiting in the
socket, or in the backlog while the link connects); a message that would pass the bound
is dropped and counted (:meth:`rce.transport.link.FramedLink.offer`), and so is one that waited longer
than :data:`rce.transport.link.DEFAULT_MAX_DELAY` for a peer that does not keep up (oldest first:
the peer gets the newest messages).
"""
from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import secrets
from typing import Protocol

from rce.transport import cluster_auth

from rce.transport import framing
from rce.plumbing.errors import ProtocolError, RCEError, Unavailable
from rce.transport.link import DEFAULT_MAX_BUFFER, STREAM_LIMIT, FramedLink, LinkFull, Responder, nodelay, settle_reply
from rce.plumbing.log import get_logger
from rce.plumbing.pending import PendingCalls

log = get_logger("rce.dataplane")

GRANT_TIMEOUT = 10.0     # s an accepted link may stay without a valid grant (a peer dials on first use and grants
                         # at once; one that does not is no peer): then it is closed and counted unauthenticated
MAX_CLAIMERS = 64        # members of one interface's claim set (nodes subscribed to what it publishes)
MAX_ACCEPTED = 1024      # accepted links at once (one per peer process is the norm); more are closed at once

Pair = tuple[int, int]        # (src interface id, dst interface id): one direction of one connection


class Receiver(Protocol):
    """What the data plane delivers to (an interface): ``iid`` its id, ``peers`` the connected
    interface ids -> their data addresses (only those may send to it)."""

    iid: int
    peers: dict[int, str]

    def on_message(self, payload: memoryview) -> None:
        """A topic message arrived (a view of the received bytes, valid during the call)."""

    async def serve(self, payload: bytes) -> bytes:
        """A service request arrived; returns the serialized response."""


class _Dialled:
    """The outgoing link to one peer address. Frames wait in a bounded backlog until the link is
    up and the acceptor's nonce has arrived; each ``(src, dst)`` is granted once per link."""

    def __init__(self, plane: "DataPlane", addr: str):
        self.plane, self.addr = plane, addr
        self.link: FramedLink | None = None
        self.nonce: bytes | None = None
        self.granted: set[Pair] = set()
        self.backlog: collections.deque[tuple[Pair, bytes, int]] = collections.deque()   # (pair, frame, payload bytes)
        self.backlog_bytes = 0
        plane.tasks.spawn(self._connect(), name=f"dial {addr}")

    async def _connect(self) -> None:
        host, _, port = self.addr.rpartition(":")
        try:
            reader, writer = await asyncio.open_connection(host.strip("[]"), int(port), limit=STREAM_LIMIT)
        except (OSError, ValueError) as e:
            log.warning("data link failed", peer=self.addr, reason=str(e))
            self._gone()
            return
        nodelay(writer, data=True)
        self.link = FramedLink(reader, writer, name=f"data link to {self.addr}", on_frame=self._on_frame,
                               on_close=lambda _link: self._gone(), max_frame=self.plane.max_frame,
                               max_buffer=self.plane.max_buffer, on_drop=self.plane._lost, data=True).start()

    def _gone(self) -> None:
        if self.plane._dialled.get(self.addr) is self:
            del self.plane._dialled[self.addr]
        self.plane.dropped += len(self.backlog)
        self.backlog.clear()

    def _on_frame(self, frame: framing.DataFrame | dict) -> None:
        if isinstance(frame, dict):
            if self.nonce is None and "nonce" in frame:
                self._ready(parse_nonce(frame["nonce"]))
                return
            self._control(frame)
            return
        if frame.op in (framing.SRV_RESP, framing.SRV_ERR) and settle_reply(self.plane.calls, frame):
            return
        self.plane.dropped += 1          # a late reply, or something the acceptor should not send

    def _control(self, frame: dict) -> None:
        if "eos_ack" in frame:
            self.plane.eos_acked(frame["eos_ack"])
            return
        raise ProtocolError(f"data link to {self.addr}: unexpected control frame {str(frame)[:120]}")

    def _ready(self, nonce: bytes) -> None:
        self.nonce = nonce
        backlog, self.backlog, self.backlog_bytes = self.backlog, collections.deque(), 0
        for pair, chunk, n in backlog:
            if pair is None:             # a control frame (a fence) queued behind the messages
                self._control_send(chunk)
            elif not self._offer(pair, chunk, b"", n):
                self.plane.dropped += 1

    def offer(self, pair: Pair, head: bytes, payload: bytes | memoryview) -> bool:
        if self.nonce is not None:
            return self._offer(pair, head, payload, len(payload))
        n = len(head) + len(payload)
        if self.backlog_bytes + n > self.plane.max_buffer:
            return False
        self.backlog.append((pair, head + payload, len(payload)))
        self.backlog_bytes += n
        return True

    def control(self, frame: dict) -> bool:
        """Send a control frame after every frame offered before it (queued behind the backlog while
        the link connects); False if the link is gone or refuses it."""
        chunk = framing.encode_control(frame)
        if self.nonce is None:
            if self.plane._dialled.get(self.addr) is not self:
                return False
            self.backlog.append((None, chunk, 0))
            return True
        return self._control_send(chunk)

    def carried(self, dst: int, src: int | None = None) -> bool:
        """Has this link carried, or does its backlog hold, a message for interface ``dst`` (from
        ``src``; None: from any)?"""
        def match(p: Pair | None) -> bool:
            return p is not None and p[1] == dst and (src is None or p[0] == src)
        return any(match(p) for p in self.granted) or any(match(p) for p, _, _ in self.backlog)

    def take_back(self, pair: Pair) -> list[tuple[bytes, bytes | memoryview]]:
        """Take ``pair``'s messages that have not left this plane yet (in the backlog while the link
        connects, or in its link's queue) out, in order: ``(header, payload)`` each."""
        taken: list[tuple[bytes, bytes | memoryview]] = []
        if self.backlog:
            kept: collections.deque = collections.deque()
            for entry in self.backlog:
                if entry[0] == pair:
                    chunk = entry[1]
                    taken.append((chunk[:framing.DATA_HEADER_LEN], chunk[framing.DATA_HEADER_LEN:]))
                    self.backlog_bytes -= len(chunk)
                else:
                    kept.append(entry)
            self.backlog = kept
        if self.link is not None:
            taken += [(f, p) for f, p, _tag in self.link.take_back(lambda f: framing.data_pair(f) == pair)]
        return taken

    def _control_send(self, chunk: bytes) -> bool:
        if self.link is None:
            return False
        try:
            self.link.send(chunk)
        except (LinkFull, Unavailable):
            return False
        return True

    def _offer(self, pair: Pair, head: bytes, payload: bytes | memoryview, nbytes: int) -> bool:
        """``nbytes``: the payload's bytes (counted in the plane's ``bytes_out``)."""
        if self.link is None or (pair not in self.granted and not self._grant(pair)):
            return False
        return self.link.offer(head, payload, nbytes)

    def _grant(self, pair: Pair) -> bool:
        token = self.plane.credentials.get(pair)
        if token is None:
            log.debug("no credential for a connection; frame dropped", peer=self.addr, src=pair[0], dst=pair[1])
            return False
        try:
            self.link.send(framing.encode_control(cluster_auth.grant_frame(token, self.nonce, *pair)))
        except (LinkFull, Unavailable):
            return False
        self.granted.add(pair)
        return True

    def close(self) -> None:
        if self.link is not None:
            self.link.close()


def parse_nonce(text: object) -> bytes:
    """The nonce of an acceptor's ``{"nonce": hex}`` frame. Raises :class:`ProtocolError`."""
    try:
        nonce = bytes.fromhex(text) if isinstance(text, str) else b""
    except ValueError:
        nonce = b""
    if len(nonce) != cluster_auth.NONCE_BYTES:
        raise ProtocolError(f"a data link's nonce is {2 * cluster_auth.NONCE_BYTES} hex digits")
    return nonce


class _ClaimSet:
    """Generation ``gen`` of an interface's claim set: ``size`` members expected, ``links`` the
    accepted links that have claimed so far (module doc)."""

    __slots__ = ("gen", "size", "links")

    def __init__(self, gen: int, size: int):
        self.gen, self.size = gen, size
        self.links: list[_Accepted] = []


class _Accepted:
    """An incoming link: the nonce it was opened with and the ``(src, dst)`` granted on it."""

    def __init__(self, plane: "DataPlane", reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        self.plane = plane
        self.nonce = secrets.token_bytes(cluster_auth.NONCE_BYTES)
        self.granted: set[Pair] = set()
        self.claims: set[int] = set()
        self.warned = False
        self.link = FramedLink(reader, writer, name=f"data link from {writer.get_extra_info('peername')}",
                               on_frame=self._on_frame, on_close=self._closed,
                               max_frame=plane.max_frame, max_buffer=plane.max_buffer, on_drop=plane._lost,
                               data=True)

    def _closed(self, _link: FramedLink) -> None:
        self.plane._accepted.discard(self)
        for parked in self.plane._parked.values():
            parked.pop(self, None)
        for iid in self.claims:
            self.plane._unclaim(iid, self)
        self.claims.clear()

    def _on_frame(self, frame: framing.DataFrame | dict) -> None:
        if isinstance(frame, framing.DataFrame):
            self.plane._dispatch(self, frame)
            return
        try:
            if "claim" in frame:
                self._claim(frame)
            elif "release" in frame:
                self._release(frame["release"])
            elif "fence" in frame:
                self._fence(frame)
            elif "switch" in frame:
                self._switch_arrived(frame)
            elif "eos" in frame:
                self.link.send(framing.encode_control({"eos_ack": frame["eos"]}))
            elif "eos_ack" in frame:
                self.plane.eos_acked(frame["eos_ack"])
            else:
                self.granted.add(cluster_auth.check_grant(self.plane.data_key, self.nonce, frame))
        except (cluster_auth.AuthFailed, ProtocolError) as e:
            self.plane.unauthenticated += 1
            log.warning("unauthenticated data link closed", plane=self.plane.name, peer=self.link.peername,
                        reason=e.message)
            self.link.close(e.message)

    def _claim(self, frame: dict) -> None:
        """The dialler speaks for interface ``f["claim"]`` (it was granted a connection from it)
        as one of generation ``gen``'s ``size`` members (module doc)."""
        iid, gen, size = frame.get("claim"), frame.get("gen", 0), frame.get("size", 1)
        if not (type(iid) is int and type(gen) is int and type(size) is int and 1 <= size <= MAX_CLAIMERS):
            raise ProtocolError(f"a claim is {{claim: iid, gen: int, size: 1..{MAX_CLAIMERS}}}, not {str(frame)[:80]}")
        if not any(src == iid for src, _dst in self.granted):
            raise ProtocolError(f"claim of interface {iid} without a grant from it on this link")
        at = frame.get("at")
        if isinstance(at, str) and not self.plane.sends_to(iid, at):
            self.plane._parked.setdefault(iid, {})[self] = frame     # a moved copy's: taken at its switch
            return
        cs = self.plane._claims.get(iid)
        if cs is None or gen > cs.gen:
            if cs is not None:
                for a in cs.links:
                    a.claims.discard(iid)
            cs = self.plane._claims[iid] = _ClaimSet(gen, size)
        elif gen < cs.gen:
            return                        # a stale generation: the environment has moved on
        if self not in cs.links:
            cs.links.append(self)
            if len(cs.links) == cs.size:
                self.plane._switch(iid, cs)
        self.claims.add(iid)

    def _fence(self, frame: dict) -> None:
        """``{fence: [src, dst], id}``: the dialler sends ``src -> dst`` here no more (module doc)."""
        pair, fid = frame.get("fence"), frame.get("id")
        if not (isinstance(pair, list) and len(pair) == 2 and all(type(x) is int for x in pair)
                and type(fid) is int):
            raise ProtocolError(f"a fence is {{fence: [src, dst], id: int}}, not {str(frame)[:80]}")
        if (pair[0], pair[1]) not in self.granted:
            return                        # nothing of that connection came on this link: nothing to fence
        self.plane.fence_arrived(fid, pair[0], pair[1])

    def _switch_arrived(self, frame: dict) -> None:
        """``{switch: x, id}``: the dialler sends ``x``'s messages to its claimers from now on; every
        frame it sent here before has been handed on (module doc)."""
        iid, sid = frame.get("switch"), frame.get("id")
        if not (type(iid) is int and type(sid) is int):
            raise ProtocolError(f"a switch marker is {{switch: iid, id: int}}, not {str(frame)[:80]}")
        if any(dst == iid for _src, dst in self.granted):
            for cb in self.plane.on_switch:
                cb(iid, sid)

    def _release(self, iid: object) -> None:
        if isinstance(iid, int):
            self.plane._unclaim(iid, self)
            self.plane._parked.get(iid, {}).pop(self, None)
        self.claims.discard(iid)
        try:
            self.link.send(framing.encode_control({"released": iid}))
        except (LinkFull, Unavailable):
            pass                          # the link is saturated or closing: its end is its answer

    def refuse(self, frame: framing.DataFrame, why: str) -> None:
        """Drop a frame whose sender is not connected to its interface (counted; the first logged)."""
        self.plane.refused += 1
        if not self.warned:
            self.warned = True
            log.warning("data frame refused (further ones on this link are only counted)", plane=self.plane.name,
                        peer=self.link.peername, src=frame.src, dst=frame.dst, reason=why)


class DataPlane:
    """One process's data-plane endpoint. ``name`` names it in logs; ``max_buffer``: bytes that
    may wait per outgoing link; ``max_frame``: largest frame accepted, bytes; ``data_key``: this
    endpoint's data key (:meth:`rce.transport.cluster_auth.ClusterKey.data_key` of its address; until it is
    set, every grant is refused); ``grant_timeout``: s an accepted link may go without a valid
    grant. ``interfaces`` maps interface ids to their :class:`Receiver`;
    ``credentials`` maps ``(src, dst)`` to the credential that lets local interface ``src`` send
    to ``dst`` (:meth:`allow`)."""

    def __init__(self, name: str, *, max_buffer: int = DEFAULT_MAX_BUFFER,
                 max_frame: int = framing.DEFAULT_MAX_FRAME, data_key: bytes | None = None,
                 grant_timeout: float = GRANT_TIMEOUT):
        self.name, self.grant_timeout = name, grant_timeout
        self.max_buffer, self.max_frame = max_buffer, max_frame
        self.data_key = data_key
        self.interfaces: dict[int, Receiver] = {}
        self.credentials: dict[Pair, bytes] = {}
        self.addr = ""
        self.calls = PendingCalls(f"data plane {name}")
        self.responder = Responder(f"data plane {name}")
        self.tasks = self.responder.tasks
        self._dialled: dict[str, _Dialled] = {}
        self._accepted: set[_Accepted] = set()
        self._claims: dict[int, _ClaimSet] = {}      # interface id -> the links that claimed it
        self._parked: dict[int, dict[_Accepted, dict]] = {}   # claims made at an address not sent to (yet)
        self._server: asyncio.AbstractServer | None = None
        self.fences: dict[int, collections.Counter] = {}   # fence id -> (src, dst) -> fences that came
        self.on_switch: list = []          # cb(iid, marker id): a switch marker came, behind what went before it
        self._fence_seen = asyncio.Event()
        self._eos_ids = itertools.count(1)
        self._eos: dict[int, asyncio.Future] = {}
        # counters (metrics and status)
        self.msgs_in = self.msgs_out = self.bytes_in = self.bytes_out = self.dropped = 0
        self.refused = self.unauthenticated = 0
        self.moved_unsent = 0              # messages a move took back from the old copy's link and sent to the new

    async def listen(self, bind: str = "127.0.0.1", port: int = 0, advertise_host: str | None = None) -> str:
        """Start the listener; returns and stores the advertised address ``host:port``."""
        self._server = await asyncio.start_server(self._accept, bind, port, limit=STREAM_LIMIT)
        real_port = self._server.sockets[0].getsockname()[1]
        host = advertise_host or bind
        self.addr = f"[{host}]:{real_port}" if ":" in host else f"{host}:{real_port}"
        return self.addr

    def link_sockets(self) -> list:
        """The sockets of this plane's links that are up: those it dialled (to the planes it sends
        to) and those it accepted (direct links of nodes, which it sends their claimed messages on)."""
        links = [d.link for d in self._dialled.values() if d.link is not None] + [a.link for a in self._accepted]
        return [s for s in (link.writer.get_extra_info("socket") for link in links) if s is not None]

    async def close(self) -> None:
        """Close the listener and all links; calls in flight fail with :class:`Unavailable`."""
        if self._server:
            self._server.close()
        for d in list(self._dialled.values()):
            d.close()
        for a in list(self._accepted):
            a.link.close()
        self.calls.fail_all(Unavailable(f"data plane {self.name} closed"))
        await self.tasks.cancel_all()

    def _unclaim(self, iid: int, link: _Accepted) -> None:
        """Take the accepted ``link`` out of ``iid``'s claim set (which is then incomplete)."""
        cs = self._claims.get(iid)
        if cs is not None and link in cs.links:
            cs.links.remove(link)
            if not cs.links:
                del self._claims[iid]

    def sends_to(self, iid: int, addr: str) -> bool:
        """Whether a local interface sends to interface ``iid`` at data address ``addr``."""
        return any(r.peers.get(iid) == addr for r in self.interfaces.values())

    def readdressed(self, iid: int) -> None:
        """Interface ``iid`` is now reached at another address: the claims parked for that address
        (its new copy's nodes claimed it before the switch) are taken."""
        for a, frame in list(self._parked.get(iid, {}).items()):
            if self.sends_to(iid, frame["at"]) and not a.link.closed.is_set():
                del self._parked[iid][a]
                a._claim(frame)
        if not self._parked.get(iid):
            self._parked.pop(iid, None)

    def _switch(self, dst: int, cs: _ClaimSet) -> None:
        """``dst``'s claim set ``cs`` is complete: put switch markers behind what went to ``dst``'s
        address and ahead of what goes to the members (module doc), when something went there."""
        sid = secrets.randbits(62)             # the markers of several far planes never mix
        paths = 0
        for addr in {r.peers.get(dst) for r in self.interfaces.values()} - {None}:
            if self.carried(addr, dst) and self._dialled[addr].control({"switch": dst, "id": sid}):
                paths += 1
        if not paths:
            return
        marker = framing.encode_control({"switch": dst, "id": sid})
        for a in cs.links:
            try:
                a.link.send(marker)
            except (LinkFull, Unavailable):
                pass                           # saturated or closing: the member stops holding on its own

    def carried(self, addr: str, dst: int) -> bool:
        """Has the link dialled to ``addr`` carried, or does it hold, a message for interface ``dst``?"""
        d = self._dialled.get(addr)
        return d is not None and d.carried(dst)

    def take_unsent(self, src: int, dst: int, old_addr: str) -> list[tuple[bytes, bytes | memoryview]]:
        """Take the messages of ``src -> dst`` that have not left this plane for its old copy yet back
        out, in order, ``(header, payload)`` each: those in the backlog or queue of the link dialled to
        ``old_addr``, then those queued on every direct link of ``dst``'s claim set (what a link's
        socket took has left). ``dst`` lives at another address now, and they go there instead
        (:meth:`send_unsent`), so the old copy never sees them and the new one does once."""
        pair = (src, dst)
        d = self._dialled.get(old_addr)
        taken = d.take_back(pair) if d is not None else []
        cs = self._claims.get(dst)
        if cs is not None and len(cs.links) == cs.size:
            # the old copy's nodes got them on their direct links, a copy each (module doc): only what
            # has left on none of them goes to the new copy
            def mine(f: bytes) -> bool:
                return framing.data_pair(f) == pair
            common = set.intersection(*({id(f) for f in a.link.queued(mine)} for a in cs.links))
            if common:
                for i, a in enumerate(cs.links):
                    got = a.link.take_back(lambda f: id(f) in common)
                    if i == 0:
                        taken += [(f, p) for f, p, _tag in got]
                    else:
                        self.msgs_out -= len(got)      # counted once per member when they were offered
                        self.bytes_out -= sum(len(p) for _f, p, _tag in got)
        return taken

    def send_unsent(self, src: int, dst: int, addr: str, taken: list[tuple[bytes, bytes | memoryview]]) -> None:
        """Send what :meth:`take_unsent` took to ``dst`` at its new address ``addr``, ahead of what is
        sent there next (counted in ``moved_unsent``; a message the new link cannot take is dropped
        and counted as any other)."""
        if not taken:
            return
        d = self._dialled.get(addr)
        if d is None:
            d = self._dialled[addr] = _Dialled(self, addr)
        for head, payload in taken:
            if d.offer((src, dst), head, payload):
                self.moved_unsent += 1
            else:
                self._lost(len(payload))

    def drop_claims(self, iid: int) -> None:
        """End interface ``iid``'s claim set (its copy moved: the nodes that claimed it are the old
        copy's); what is sent to ``iid`` goes to its address until a new set is complete."""
        cs = self._claims.pop(iid, None)
        if cs is not None:
            for a in cs.links:
                a.claims.discard(iid)

    # -- fences and end of stream (module doc) ----------------------------------------------------
    def fence(self, src: int, dst: int, old_addr: str, fid: int) -> int:
        """Fence ``src -> dst`` at its old copy (``dst`` now lives at another address): send the fence
        ``fid`` on every path that may have carried it there, behind what went before: the link
        dialled to ``old_addr`` and each accepted link of ``dst``'s claim set. Returns how many
        fences went out (0: nothing of it can still be on its way)."""
        frame = {"fence": [src, dst], "id": fid}
        n = 0
        cs = self._claims.get(dst)
        for a in (cs.links if cs is not None else ()):
            if (src, dst) in self.credentials and not a.link.closed.is_set():
                try:
                    a.link.send(framing.encode_control(frame))
                    n += 1
                except (LinkFull, Unavailable):
                    log.warning("fence not sent: a direct link is saturated", plane=self.name, src=src, dst=dst)
        d = self._dialled.get(old_addr)
        if d is not None and d.carried(dst, src):
            if d.control(frame):
                n += 1
            else:
                log.warning("fence not sent: the link to the old copy is gone or full", plane=self.name,
                            peer=old_addr, src=src, dst=dst)
        return n

    def fence_arrived(self, fid: int, src: int, dst: int) -> None:
        """A fence ``fid`` of ``src -> dst`` came (on an accepted link, or reported by a node)."""
        self.fences.setdefault(fid, collections.Counter())[(src, dst)] += 1
        self._fence_seen.set()

    def fences_missing(self, fid: int, expect: dict[Pair, int]) -> dict[Pair, int]:
        """Of ``expect`` (``(src, dst)`` -> fences to come), those not all come yet: how many are missing."""
        got = self.fences.get(fid) or {}
        return {p: n - got.get(p, 0) for p, n in expect.items() if got.get(p, 0) < n}

    async def wait_fences(self, fid: int, expect: dict[Pair, int], timeout: float) -> dict[Pair, int]:
        """Wait until every fence of ``expect`` came, at most ``timeout`` s; returns the missing ones
        (empty: all came)."""
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout
        while self.fences_missing(fid, expect) and loop.time() < end:
            self._fence_seen.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(end - loop.time()):
                    await self._fence_seen.wait()
        return self.fences_missing(fid, expect)

    def eos_acked(self, k: object) -> None:
        """A peer acknowledged end of stream ``k``: it handed on everything sent before."""
        fut = self._eos.pop(k, None) if isinstance(k, int) else None
        if fut is not None and not fut.done():
            fut.set_result(True)

    async def flush(self, addrs: set[str], timeout: float) -> list[str]:
        """Send end of stream on the links dialled to ``addrs`` and wait (at most ``timeout`` s) until
        each peer acknowledges it: every message sent there before has reached that peer and was
        handed on. Returns the addresses that did not acknowledge (a link gone counts as done: what
        it held is lost with it, and counted)."""
        waits: dict[str, asyncio.Future] = {}
        loop = asyncio.get_running_loop()
        for addr in addrs:
            d = self._dialled.get(addr)
            if d is None:
                continue
            k = next(self._eos_ids)
            fut = self._eos[k] = loop.create_future()
            if d.control({"eos": k}):
                waits[addr] = fut
            else:
                self._eos.pop(k, None)
        if not waits:
            return []
        closed = {addr: self._dialled[addr].link.closed for addr in waits
                  if addr in self._dialled and self._dialled[addr].link is not None}

        async def one(addr: str) -> bool:
            ends = [waits[addr]] + ([asyncio.ensure_future(closed[addr].wait())] if addr in closed else [])
            try:
                done, _ = await asyncio.wait(ends, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for f in ends[1:]:
                    f.cancel()
            return bool(done)
        results = await asyncio.gather(*(one(a) for a in waits))
        for fut in waits.values():
            fut.cancel()
        return [a for a, ok in zip(waits, results, strict=True) if not ok]

    # -- credentials ------------------------------------------------------------------------------
    def allow(self, src: int, dst: int, token: bytes) -> None:
        """Local interface ``src`` may send to interface ``dst``, with the master's credential."""
        self.credentials[(src, dst)] = token

    def forbid(self, src: int, dst: int | None = None) -> None:
        """Forget the credential of ``src -> dst`` (``dst`` None: of every connection of ``src``); the
        links it was granted on no longer carry it."""
        for pair in [p for p in self.credentials if p[0] == src and dst in (None, p[1])]:
            del self.credentials[pair]
            for d in self._dialled.values():
                d.granted.discard(pair)

    # -- sending -------------------------------------------------------------------------------
    def send(self, addr: str, op: int, dst: int, src: int, call_id: int, payload: bytes | memoryview) -> bool:
        """Send one DATA frame from local interface ``src`` to interface ``dst`` at ``addr``; False
        (and counted) if dropped: no credential for ``src -> dst``, or the link is saturated.
        An interface claimed on an accepted link (module doc) gets it there instead of at ``addr``."""
        cs = self._claims.get(dst)
        if cs is not None and len(cs.links) == cs.size:
            if (src, dst) not in self.credentials:
                self.dropped += 1
                return False
            head, sent = framing.encode_data_header(op, dst, src, call_id, len(payload)), 0
            n = len(payload)
            for a in cs.links:
                if a.link.offer(head, payload, n):
                    sent += 1
                else:
                    self.dropped += 1
            self.msgs_out += sent
            self.bytes_out += len(payload) * sent
            return sent > 0
        d = self._dialled.get(addr)
        if d is None:
            d = self._dialled[addr] = _Dialled(self, addr)
        if d.offer((src, dst), framing.encode_data_header(op, dst, src, call_id, len(payload)), payload):
            self.msgs_out += 1
            self.bytes_out += len(payload)
            return True
        self.dropped += 1
        return False

    async def call(self, addr: str, dst: int, src: int, payload: bytes, timeout: float | None) -> bytes:
        """Send a service request to interface ``dst`` at ``addr`` and await the response bytes.

        Raises :class:`Unavailable` when the request is dropped (the link to the provider is
        saturated or gone, or no credential), :class:`~rce.plumbing.errors.Timeout` after ``timeout`` s,
        :class:`~rce.plumbing.errors.RequestError` with the provider's reason on a failed call."""
        def send(cid: int) -> None:
            if not self.send(addr, framing.SRV_REQ, dst, src, cid, payload):
                raise Unavailable("service request dropped: the link to the provider is saturated or unauthorised")
        return await self.calls.call(send, timeout, what=f"the service call to interface {dst}")

    # -- receiving -----------------------------------------------------------------------------
    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nodelay(writer, data=True)
        if len(self._accepted) >= MAX_ACCEPTED:
            self.unauthenticated += 1
            log.warning("data link refused: too many links", plane=self.name, links=len(self._accepted),
                        peer=str(writer.get_extra_info("peername")))
            writer.close()
            return
        a = _Accepted(self, reader, writer)
        self._accepted.add(a)
        a.link.send(framing.encode_control({"nonce": a.nonce.hex()}))
        a.link.start()
        self.tasks.spawn(self._grant_timer(a), name="grant timer")

    async def _grant_timer(self, link: _Accepted) -> None:
        await asyncio.sleep(self.grant_timeout)          # a timer: the link must have a grant by now
        if not link.granted and not link.link.closed.is_set():
            self.unauthenticated += 1
            log.warning("data link closed: no grant", plane=self.name, peer=link.link.peername,
                        waited_s=self.grant_timeout)
            link.link.close("no grant")

    def _dispatch(self, link: _Accepted, frame: framing.DataFrame) -> None:
        if frame.op not in (framing.MSG, framing.SRV_REQ):
            self.dropped += 1             # replies travel on the links we dialled
            return
        if (frame.src, frame.dst) not in link.granted:
            link.refuse(frame, "no grant for this connection on this link")
            return
        iface = self.interfaces.get(frame.dst)
        if iface is not None and frame.src not in iface.peers:
            link.refuse(frame, "the sender is not connected to this interface")
            return
        self.msgs_in += 1
        self.bytes_in += len(frame.payload)
        if frame.op == framing.SRV_REQ:
            self._serve(link, frame, iface)
        elif iface is None:
            self.dropped += 1
        else:
            try:
                iface.on_message(frame.payload)
            except RCEError as e:         # e.g. a message for an interface that takes none
                self.dropped += 1
                log.debug("message refused", plane=self.name, iid=frame.dst, reason=e.message)

    def _serve(self, link: _Accepted, frame: framing.DataFrame, iface: Receiver | None) -> None:
        """Run a service request and send its reply back on the link it came in on."""
        src, iid, call_id, payload = frame.src, frame.dst, frame.call_id, bytes(frame.payload)

        def answer(op: int, body: bytes) -> None:
            if not link.link.offer(framing.encode_data_header(op, src, iid, call_id, len(body)), body, None):
                self.dropped += 1          # the caller times out

        def refuse(error: RCEError) -> None:
            answer(framing.SRV_ERR, error.message.encode())
        if iface is None:
            self.dropped += 1
            refuse(Unavailable(f"interface {iid} is gone"))
            return
        self.responder.serve(lambda: iface.serve(payload), lambda resp: answer(framing.SRV_RESP, resp), refuse,
                             f"service call to interface {iid}")

    def _lost(self, nbytes: int | None) -> None:
        """A frame a link took was dropped from its queue (the peer is not keeping up,
        :mod:`rce.transport.link`): ``nbytes`` the payload bytes of a message counted as sent, None for a reply."""
        self.dropped += 1
        if nbytes is not None:
            self.msgs_out -= 1
            self.bytes_out -= nbytes

    def stats(self) -> dict:
        """``{msgs_in, msgs_out, bytes_in, bytes_out, dropped, refused, unauthenticated, links, claims,
        moved_unsent}``:
        ``dropped`` includes what waited past a link's ``max_delay`` for a peer that did not keep up
        (:mod:`rce.transport.link`); ``refused`` frames from senders not connected to their interface,
        ``unauthenticated``
        links closed for a wrong credential, ``links`` outgoing, ``claims`` interfaces reached on
        direct links (module doc), ``moved_unsent`` messages a move sent to the new copy that had not left
        for the old one (:meth:`take_unsent`)."""
        return {"msgs_in": self.msgs_in, "msgs_out": self.msgs_out, "bytes_in": self.bytes_in,
                "bytes_out": self.bytes_out, "dropped": self.dropped, "refused": self.refused,
                "unauthenticated": self.unauthenticated, "links": len(self._dialled),
                "claims": sum(len(c.links) == c.size for c in self._claims.values()),
                "moved_unsent": self.moved_unsent}
