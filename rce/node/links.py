"""A node's direct links: data-plane links its environment opened for it, so that its topic
messages go straight to the robot endpoint (or another environment) and back, past the
environment process, as TCPROS goes from publisher to subscriber past the ROS master.

The environment decides every route (:mod:`rce_container.direct_routes`); this module only
follows its orders, which come as requests on the node's bus link:

- ``direct_link {link}``: the socket of ``link`` was passed on the fd channel (its
  handshake done: the far plane's nonce read). The node wraps it in a
  :class:`~rce.transport.link.FramedLink`.
- ``direct_publish {handle, version, targets: [[link, dst, src]], local, grants}``: from now on
  publisher ``handle`` sends each message as ``MSG dst src`` on each target's link, and to the
  bus as well only when ``local`` (other subscribers are there), marked with ``version`` so the
  bus skips what this route reached. No targets: back to the bus alone. ``hold``: messages this
  publisher sent by the bus may still be on their way to the far ends (the environment's link to
  them still connects, or is slow); the route's messages wait here, in order (at most
  :data:`MAX_HELD`, the oldest dropped and counted), until ``direct_go {handle, version}`` says
  those have been handed on there (:meth:`rce.transport.dataplane.DataPlane.flush`), or
  :data:`ROUTE_HOLD` s pass. The node holds also without ``hold`` when the publisher has sent
  by the bus alone before: those messages may still be on the bus link, where the environment
  reads them only behind the answer ``{held}``, which tells it to send ``direct_go``.
- ``direct_subscribe {link, iid, peers, handles, gen, size, grants, at?}``: claim interface ``iid`` on
  ``link`` as one of the ``size`` members of claim generation ``gen`` (:mod:`rce.transport.dataplane`,
  "Direct links"): once all have claimed, its messages from ``peers`` arrive here and go to
  subscriber ``handles`` (``at``: the data address of the environment holding ``iid``, so that the far
  plane takes the claim only while it sends ``iid``'s messages there: a moved container's new copy
  claims nothing before the switch). ``direct_unsubscribe {link, iid}`` releases the claim.
- ``direct_counts {}`` -> ``{iid: [messages, bytes, dropped]}`` per interface this node stood
  in for (the environment adds them to the interfaces' counters).

Order across a claim's start (:mod:`rce.transport.dataplane`, "Direct links"): a far plane
whose claim set completes while it had sent the interface's messages through the environment
sends ``{"switch": iid, "id": s}`` on the link ahead of the first direct message; the node holds
what comes on that link for ``iid`` (bounded by its subscribers' largest ``queue_size``, the
oldest dropped and counted) until the environment's ``direct_switch {iid, id}`` notification
arrives on the bus link, behind the messages that went that way, or :data:`SWITCH_HOLD` s pass.

``grants`` are the data-plane grant frames (:mod:`rce.transport.cluster_auth`) the environment computed
for the link's nonce; the node sends them before the first frame that needs them. When a link
ends, every route and claim on it ends with it (messages go by the bus again) and the node
notifies ``direct_closed {link}``.

The fd channel (:mod:`rce.bus.server`): a second connection to the bus socket on which the
environment sends ``SCM_RIGHTS`` (unix(7)) messages of an 8-byte link id and one socket.
"""
from __future__ import annotations

import asyncio
import itertools
import socket
import struct
import sys
from collections import deque
from typing import Any

from rce.contract import bus as to_bus
from rce.contract import node as ops
from rce.transport import framing
from rce.plumbing.errors import ProtocolError, Timeout, Unavailable
from rce.transport.link import STREAM_LIMIT, FramedLink, LinkFull
from rce.transport.op_table import OpTable

LINK_ID = struct.Struct("!Q")     # the id that goes with each socket on the fd channel
FD_WAIT = 10.0                    # s ``direct_link`` waits for its socket on the fd channel
MAX_FDS = 16                      # sockets taken per read of the fd channel
MAX_BUFFER = 16 * 1024 * 1024     # bytes that may wait unread per direct link (then messages drop, counted)
MAX_HELD = 1000                   # messages a held route keeps until ``direct_go``
ROUTE_HOLD = 10.0                 # s a held route waits for ``direct_go`` at most (then it sends, and says so)
SWITCH_HOLD = 2.0                 # s direct messages wait at most for the bus path's switch marker
MAX_PASSED = 64                   # switch markers kept that came by the bus before their direct one

#: The ops of a node's direct links, which its environment sends on the node's bus link.
DIRECT_OPS = OpTable("environment -> node (direct links)")


def _lost(tag: tuple[list[int], int]) -> None:
    """A message a direct link took was dropped from its queue: its interface's counts say so."""
    c, n = tag
    c[0] -= 1
    c[1] -= n
    c[2] += 1


class _Route:
    """A publisher's direct route: ``targets`` ``(link, dst, src, counts)``; ``local``: the bus
    has other subscribers too; ``version``: marks its bus frames; ``held``: its messages waiting
    for ``direct_go`` (None: it sends at once)."""

    __slots__ = ("version", "targets", "local", "held", "timer")

    def __init__(self, version: int, targets: list, local: bool, hold: bool = False):
        self.version, self.targets, self.local = version, targets, local
        self.held: deque[bytes] | None = deque() if hold else None
        self.timer: asyncio.TimerHandle | None = None


class _Hold:
    """Direct messages held after a switch marker ``sid`` until the bus path's marker comes;
    ``handles``: the subscribers they are for (kept should the claim end meanwhile)."""

    __slots__ = ("sid", "queue", "timer", "handles")

    def __init__(self, sid: int, timer: asyncio.TimerHandle, handles: tuple[int, ...]):
        self.sid, self.timer, self.handles = sid, timer, handles
        self.queue: deque[bytes] = deque()


class DirectLinks:
    """The direct links of one node (module doc). ``node``: the :class:`rce.node.Node` (its
    subscribers ``_subs`` get what arrives, its bus link ``_peer`` hears ``direct_closed``)."""

    def __init__(self, node: Any):
        self.node = node
        self.links: dict[int, FramedLink] = {}
        self.routes: dict[int, _Route] = {}                  # publisher handle -> its route
        self._by_bus: set[int] = set()                       # publisher handles that sent by the bus alone
        # (link, interface id) -> (its peers, the subscriber handles it feeds)
        self.claims: dict[tuple[int, int], tuple[frozenset[int], tuple[int, ...]]] = {}
        self.counts: dict[int, list[int]] = {}               # interface id -> [messages, bytes, dropped]
        self._channel: socket.socket | None = None
        self._ids: deque[int] = deque()
        self._fds: deque[int] = deque()
        self._buf = b""
        self._arrived: dict[int, int] = {}                   # link id -> socket fd not yet taken
        self._waiting: dict[int, asyncio.Future] = {}
        self._eos_ids = itertools.count(1)
        self._eos: dict[int, asyncio.Future] = {}           # end of stream id -> its acknowledgement
        self._holds: dict[tuple[int, int], _Hold] = {}       # (link, interface id) -> held after a switch marker
        self._passed: dict[tuple[int, int], None] = {}       # (iid, marker id) that came by the bus first
        self.switch_timeouts = 0         # holds ended by SWITCH_HOLD, not by the bus path's marker
        self.route_timeouts = 0          # held routes released by ROUTE_HOLD, not by direct_go

    # -- the fd channel --------------------------------------------------------------------------
    async def open_channel(self, path: str, key: str) -> None:
        """Open the fd channel to the bus socket ``path`` and name it with ``key`` (the hello's
        ``fd_key``). Raises :class:`OSError` if the socket cannot be reached."""
        loop = asyncio.get_running_loop()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.setblocking(False)
        try:
            await loop.sock_connect(sock, path)
            await loop.sock_sendall(sock, framing.encode_control({"op": "fd_channel", "args": {"key": key}}))
        except BaseException:
            sock.close()
            raise
        self._channel = sock
        loop.add_reader(sock.fileno(), self._readable)

    def _readable(self) -> None:
        try:
            data, fds, _flags, _addr = socket.recv_fds(self._channel, 4096, MAX_FDS)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data, fds = b"", []
        self._fds.extend(fds)
        if not data:
            self._close_channel()
            return
        self._buf += data
        while len(self._buf) >= LINK_ID.size:
            self._ids.append(LINK_ID.unpack_from(self._buf)[0])
            self._buf = self._buf[LINK_ID.size:]
        while self._ids and self._fds:
            lid, fd = self._ids.popleft(), self._fds.popleft()
            fut = self._waiting.pop(lid, None)
            if fut is not None and not fut.done():
                fut.set_result(fd)
            else:
                self._arrived[lid] = fd

    def _close_channel(self) -> None:
        if self._channel is not None:
            try:
                asyncio.get_running_loop().remove_reader(self._channel.fileno())
            except (RuntimeError, ValueError):
                pass
            self._channel.close()
            self._channel = None
        for fd in list(self._fds) + list(self._arrived.values()):
            socket.close(fd)
        self._fds.clear()
        self._arrived.clear()

    # -- ops ------------------------------------------------------------------------------------
    @DIRECT_OPS.op("direct_link", args=ops.DirectLink)
    async def op_direct_link(self, args: ops.DirectLink) -> dict:
        """``{link, name?}``: take the socket of ``link`` from the fd channel."""
        lid = args.link
        fd = self._arrived.pop(lid, None)
        if fd is None:
            fut = self._waiting[lid] = asyncio.get_running_loop().create_future()
            try:
                async with asyncio.timeout(FD_WAIT):
                    fd = await fut
            except TimeoutError:
                raise Timeout(f"the socket of direct link {lid} did not arrive in {FD_WAIT:g} s") from None
            finally:
                self._waiting.pop(lid, None)
        sock = socket.socket(fileno=fd)
        try:
            reader, writer = await asyncio.open_connection(sock=sock, limit=STREAM_LIMIT)
        except BaseException:
            sock.close()
            raise
        old = self.links.pop(lid, None)
        if old is not None:
            old.close("replaced")
        self.links[lid] = FramedLink(reader, writer, name=f"direct link {lid} to {args.name}",
                                     on_frame=lambda frame: self._on_frame(lid, frame),
                                     on_close=lambda _l: self._link_closed(lid),
                                     max_frame=framing.DEFAULT_MAX_FRAME, max_buffer=MAX_BUFFER,
                                     on_drop=_lost).start()
        return {}

    def _link(self, lid: int) -> FramedLink:
        link = self.links.get(lid)
        if link is None or link.closed.is_set():
            raise Unavailable(f"direct link {lid} is not open")
        return link

    def _grant(self, grants: list[ops.Grant]) -> None:
        for lid, frame in grants:
            self._link(lid).send(framing.encode_control(frame))

    @DIRECT_OPS.op("direct_publish", args=ops.DirectPublish)
    async def op_direct_publish(self, args: ops.DirectPublish) -> dict:
        """``{handle, version, targets, local, grants, hold}`` (module doc) -> ``{held}``: whether
        the route holds its messages until ``direct_go``."""
        handle = args.handle
        self._grant(args.grants)
        targets = [(self._link(lid), dst, src, self.counts.setdefault(src, [0, 0, 0]))
                   for lid, dst, src in args.targets]
        old = self.routes.pop(handle, None)
        if old is not None:
            self._go(old)                     # the older route's order is kept: its messages go first
        if not targets:
            return {"held": False}
        # what this publisher sent by the bus may not have reached the environment's links yet
        # (the environment reads it behind this answer): hold whenever there was any
        r = self.routes[handle] = _Route(args.version, targets, args.local, args.hold or handle in self._by_bus)
        if r.held is not None:
            r.timer = asyncio.get_running_loop().call_later(ROUTE_HOLD, self._route_expire, handle, r)
        return {"held": r.held is not None}

    def _route_expire(self, handle: int, r: _Route) -> None:
        if self.routes.get(handle) is r and r.held is not None:
            self.route_timeouts += 1
            self._say(f"no direct_go for publisher {handle} in {ROUTE_HOLD:g} s: its held messages go")
            self._go(r)

    def _say(self, text: str) -> None:
        """A line on the node's stderr (its log), naming the node."""
        print(f"[{getattr(self.node, 'full_name', '?')}] {text}", file=sys.stderr)

    def _go(self, r: _Route) -> None:
        """Route ``r`` holds no more: what it held goes, in order."""
        if r.timer is not None:
            r.timer.cancel()
            r.timer = None
        if r.held is not None:
            held, r.held = r.held, None
            self._send(r, held)

    @DIRECT_OPS.op("direct_go", args=ops.DirectGo)
    async def op_direct_go(self, args: ops.DirectGo) -> None:
        """``{handle, version}`` (a notification): what publisher ``handle`` sent by the bus before its
        route ``version`` has been handed on at the far ends; the route's held messages go."""
        r = self.routes.get(args.handle)
        if r is not None and r.version == args.version:
            self._go(r)

    @DIRECT_OPS.op("direct_subscribe", args=ops.DirectSubscribe)
    async def op_direct_subscribe(self, args: ops.DirectSubscribe) -> dict:
        """``{link, iid, peers, handles, gen, size, grants}``: claim interface ``iid`` on ``link``."""
        link, iid = self._link(args.link), args.iid
        self._grant(args.grants)
        self.claims[(args.link, iid)] = (frozenset(args.peers), tuple(args.handles))
        self.counts.setdefault(iid, [0, 0, 0])
        claim = {"claim": iid, "gen": args.gen, "size": args.size}
        if args.at is not None:
            claim["at"] = args.at             # where the far end sends iid's messages: only then it takes the claim
        link.send(framing.encode_control(claim))
        return {}

    @DIRECT_OPS.op("direct_unsubscribe", args=ops.DirectUnsubscribe)
    async def op_direct_unsubscribe(self, args: ops.DirectUnsubscribe) -> dict:
        """``{link, iid}``: release the claim (its entry goes when the far end says ``released``)."""
        key = (args.link, args.iid)
        link = self.links.get(key[0])
        if key in self.claims and link is not None and not link.closed.is_set():
            try:
                link.send(framing.encode_control({"release": key[1]}))
                return {}
            except (LinkFull, Unavailable):
                link.close("saturated while releasing a claim")
        self.claims.pop(key, None)
        return {}

    @DIRECT_OPS.op("direct_switch", args=ops.DirectSwitch)
    async def op_direct_switch(self, args: ops.DirectSwitch) -> None:
        """``{iid, id}`` (a notification, behind the messages the bus carried for ``iid``): the bus
        path's switch marker; what was held behind the direct marker ``id`` goes on."""
        iid, sid = args.iid, args.id
        for key, hold in list(self._holds.items()):
            if key[1] == iid and hold.sid == sid:
                self._release(key)
                return
        self._passed[(iid, sid)] = None
        while len(self._passed) > MAX_PASSED:
            del self._passed[next(iter(self._passed))]

    def _switch(self, lid: int, frame: dict) -> None:
        """``{switch: iid, id}`` on link ``lid``: hold its direct messages for ``iid`` (module doc)."""
        iid, sid = frame.get("switch"), frame.get("id")
        if not (type(iid) is int and type(sid) is int):
            raise ProtocolError(f"direct link {lid}: a switch marker is {{switch: iid, id: int}}, "
                                f"not {str(frame)[:80]}")
        if (iid, sid) in self._passed:       # the bus path's marker came first: nothing is behind
            del self._passed[(iid, sid)]
            return
        key = (lid, iid)
        if key in self._holds:
            self._release(key)
        claim = self.claims.get(key)
        self._holds[key] = _Hold(sid, asyncio.get_running_loop().call_later(SWITCH_HOLD, self._expire, key),
                                 claim[1] if claim is not None else ())

    def _expire(self, key: tuple[int, int]) -> None:
        self.switch_timeouts += 1
        self._say(f"no switch marker by the bus for interface {key[1]} in {SWITCH_HOLD:g} s: "
                  f"its direct messages go on")
        self._release(key)

    def _release(self, key: tuple[int, int]) -> None:
        hold = self._holds.pop(key, None)
        if hold is None:
            return
        hold.timer.cancel()
        claim = self.claims.get(key)
        handles = claim[1] if claim is not None else hold.handles      # the claim may have ended meanwhile
        for payload in hold.queue:
            self._deliver(handles, key[1], payload)

    @DIRECT_OPS.op("direct_counts", args=ops.DirectCounts)
    async def op_direct_counts(self, args: ops.DirectCounts) -> dict:
        """``{}`` -> ``{iid: [messages, bytes, dropped]}`` since the node started."""
        return {str(iid): c for iid, c in self.counts.items()}

    # -- data -----------------------------------------------------------------------------------
    def publish(self, handle: int, payload: bytes) -> int:
        """Send ``payload`` of publisher ``handle`` on its direct route. Returns the ``src`` its
        bus frame carries: 0 (no route: all by the bus), the route's version (the bus has other
        subscribers), or -1 (no bus frame needed)."""
        r = self.routes.get(handle)
        if r is None:
            self._by_bus.add(handle)
            return 0
        if r.held is None:
            self._send(r, (payload,))
        else:
            if len(r.held) >= MAX_HELD:
                r.held.popleft()
                for *_, c in r.targets:
                    c[2] += 1
            r.held.append(payload)
        return r.version if r.local else -1

    @staticmethod
    def _send(r: _Route, payloads) -> None:
        for payload in payloads:
            n = len(payload)
            for link, dst, src, c in r.targets:
                if link.offer(framing.encode_data_header(framing.MSG, dst, src, 0, n), payload, (c, n)):
                    c[0] += 1
                    c[1] += n
                else:
                    c[2] += 1

    async def drain(self, handle: int) -> None:
        """Wait for publisher ``handle``'s direct links to drain (backpressure)."""
        r = self.routes.get(handle)
        for link, *_ in (r.targets if r else ()):
            await link.drain()

    async def flush(self, timeout: float) -> list[int]:
        """End of stream on each direct link this node publishes on, and wait (at most ``timeout``
        s) for each far end's acknowledgement: every message sent before has reached it and was
        handed on. Returns the links that did not acknowledge (a link that ends counts as done)."""
        loop = asyncio.get_running_loop()
        lids = {lid for r in self.routes.values() for link, *_ in r.targets
                for lid, lk in self.links.items() if lk is link}
        waits = {}
        for lid in lids:
            link = self.links.get(lid)
            if link is None or link.closed.is_set():
                continue
            k = next(self._eos_ids)
            fut = self._eos[k] = loop.create_future()
            try:
                link.send(framing.encode_control({"eos": k}))
            except (LinkFull, Unavailable):
                self._eos.pop(k, None)
                continue
            waits[lid] = (fut, link)

        async def one(fut: asyncio.Future, link: FramedLink) -> bool:
            closed = asyncio.ensure_future(link.closed.wait())
            try:
                done, _ = await asyncio.wait([fut, closed], timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
            finally:
                closed.cancel()
            return bool(done)
        oks = await asyncio.gather(*(one(f, lk) for f, lk in waits.values()))
        for f, _ in waits.values():
            f.cancel()
        return [lid for lid, ok in zip(waits, oks, strict=True) if not ok]

    def _control(self, lid: int, frame: dict) -> None:
        if "released" in frame:
            self.claims.pop((lid, frame["released"]), None)
        elif "fence" in frame:            # its peer sends here no more: the environment counts it (DataPlane.fence)
            pair, fid = frame.get("fence"), frame.get("id")
            peer = self.node._peer
            if isinstance(pair, list) and len(pair) == 2 and all(type(x) is int for x in (fid, *pair)) \
                    and peer is not None and not peer.closed.is_set():
                peer.tell(to_bus.BusDirectFence(fence=fid, src=pair[0], dst=pair[1]))
        elif "switch" in frame:
            self._switch(lid, frame)
        elif "eos_ack" in frame:
            fut = self._eos.pop(frame["eos_ack"], None) if isinstance(frame["eos_ack"], int) else None
            if fut is not None and not fut.done():
                fut.set_result(True)
        elif "eos" in frame:
            link = self.links.get(lid)
            if link is not None:
                link.send(framing.encode_control({"eos_ack": frame["eos"]}))
        else:
            raise ProtocolError(f"direct link {lid}: unexpected control frame {str(frame)[:120]}")

    def _on_frame(self, lid: int, frame: framing.DataFrame | dict) -> None:
        if isinstance(frame, dict):
            self._control(lid, frame)
            return
        claim = self.claims.get((lid, frame.dst)) if frame.op == framing.MSG else None
        if claim is None or frame.src not in claim[0]:
            self.counts.setdefault(frame.dst, [0, 0, 0])[2] += 1     # not for a claim of this link: dropped
            return
        payload = bytes(frame.payload)
        hold = self._holds.get((lid, frame.dst)) if self._holds else None
        if hold is None:
            self._deliver(claim[1], frame.dst, payload)
            return
        subs = self.node._subs
        if len(hold.queue) >= max((subs[h].queue_size for h in claim[1] if h in subs), default=1):
            hold.queue.popleft()
            self.counts[frame.dst][2] += 1
        hold.queue.append(payload)

    def _deliver(self, handles: tuple[int, ...], iid: int, payload: bytes) -> None:
        """Give ``payload`` (a message for claimed interface ``iid``) to subscribers ``handles``."""
        subs = self.node._subs
        for h in handles:
            sub = subs.get(h)
            if sub is not None:
                sub._push(payload)
        c = self.counts.setdefault(iid, [0, 0, 0])
        c[0] += 1
        c[1] += len(payload)

    def _link_closed(self, lid: int) -> None:
        if self.links.get(lid) is None:
            return
        del self.links[lid]
        for h in [h for h, r in self.routes.items() if any(t[0].closed.is_set() for t in r.targets)]:
            del self.routes[h]
        for key in [k for k in self._holds if k[0] == lid]:
            self._release(key)               # what came before the link ended is the node's
        for key in [k for k in self.claims if k[0] == lid]:
            del self.claims[key]
        peer = self.node._peer
        if peer is not None:
            peer.tell(to_bus.BusDirectClosed(link=lid))

    def close(self) -> None:
        """Close every direct link and the fd channel."""
        for link in list(self.links.values()):
            link.close("the node closes")
        self.links.clear()
        self.routes.clear()
        self.claims.clear()
        for hold in self._holds.values():
            hold.timer.cancel()
        self._holds.clear()
        for r in self.routes.values():
            if r.timer is not None:
                r.timer.cancel()
        self._close_channel()
