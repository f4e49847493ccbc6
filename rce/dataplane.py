"""The data plane: direct endpoint <-> endpoint links (robot endpoint <-> environment,
environment <-> environment); the master carries no data.

Every endpoint process (an rce-robot task set, an environment) runs one
:class:`DataPlane`: a TCP listener for incoming links, and one outgoing link per
peer address, opened on first use. Frames are DATA frames of
:mod:`rce.framing` addressed by interface id (``dst``), so one link carries every
connection between the two processes. Each process sends only on the links it
dialled and receives on the links it accepted: no dial races.

What receives frames registers here by id as a :class:`Receiver` (the interfaces of
:mod:`rce.interfaces`). Outgoing links are bounded (``max_buffer`` bytes waiting in the
socket, or in the backlog while the link connects); a message that would pass the bound
is dropped and counted (:meth:`rce.link.FramedLink.offer`).
"""
from __future__ import annotations

import asyncio
import collections
from typing import Protocol

from rce import framing
from rce.errors import RCEError, Unavailable
from rce.link import DEFAULT_MAX_BUFFER, STREAM_LIMIT, FramedLink, Responder, nodelay, settle_reply
from rce.log import get_logger
from rce.pending import PendingCalls

log = get_logger("rce.dataplane")


class Receiver(Protocol):
    """What the data plane delivers to (an interface): ``iid`` its id, ``peers`` the connected
    interface ids -> their data addresses (a service reply goes back to the caller's)."""

    iid: int
    peers: dict[int, str]

    def on_message(self, payload: memoryview) -> None:
        """A topic message arrived (a view of the received bytes, valid during the call)."""

    async def serve(self, payload: bytes) -> bytes:
        """A service request arrived; returns the serialized response."""


class _Dialled:
    """The outgoing link to one peer address; frames wait in a bounded backlog while it connects."""

    def __init__(self, plane: "DataPlane", addr: str):
        self.plane, self.addr = plane, addr
        self.link: FramedLink | None = None
        self.backlog: collections.deque[bytes] = collections.deque()
        self.backlog_bytes = 0
        plane.tasks.spawn(self._connect(), name=f"dial {addr}")

    async def _connect(self) -> None:
        host, _, port = self.addr.rpartition(":")
        try:
            reader, writer = await asyncio.open_connection(host.strip("[]"), int(port), limit=STREAM_LIMIT)
        except (OSError, ValueError) as e:
            log.warning("data link failed", peer=self.addr, reason=str(e))
            self._gone()
            self.plane.dropped += len(self.backlog)
            return
        nodelay(writer)
        self.link = FramedLink(reader, writer, name=f"data link to {self.addr}", on_frame=self._unexpected,
                               on_close=lambda _link: self._gone(), max_frame=self.plane.max_frame,
                               max_buffer=self.plane.max_buffer).start()
        for chunk in self.backlog:
            self.link.offer(chunk)
        self.backlog.clear()
        self.backlog_bytes = 0

    def _gone(self) -> None:
        if self.plane._dialled.get(self.addr) is self:
            del self.plane._dialled[self.addr]

    def _unexpected(self, _frame: framing.DataFrame | dict) -> None:
        self.plane.dropped += 1          # the peer never sends on the link we dialled

    def offer(self, head: bytes, payload: bytes | memoryview) -> bool:
        if self.link is not None:
            return self.link.offer(head, payload)
        n = len(head) + len(payload)
        if self.backlog_bytes + n > self.plane.max_buffer:
            return False
        self.backlog.append(head + payload)
        self.backlog_bytes += n
        return True

    def close(self) -> None:
        if self.link is not None:
            self.link.close()


class DataPlane:
    """One process's data-plane endpoint. ``name`` names it in logs; ``max_buffer``: bytes that
    may wait per outgoing link; ``max_frame``: largest frame accepted, bytes. ``interfaces``
    maps interface ids to their :class:`Receiver`."""

    def __init__(self, name: str, *, max_buffer: int = DEFAULT_MAX_BUFFER,
                 max_frame: int = framing.DEFAULT_MAX_FRAME):
        self.name = name
        self.max_buffer, self.max_frame = max_buffer, max_frame
        self.interfaces: dict[int, Receiver] = {}
        self.addr = ""
        self.calls = PendingCalls(f"data plane {name}")
        self.responder = Responder(f"data plane {name}")
        self.tasks = self.responder.tasks
        self._dialled: dict[str, _Dialled] = {}
        self._accepted: set[FramedLink] = set()
        self._server: asyncio.AbstractServer | None = None
        # counters (metrics and status)
        self.msgs_in = self.msgs_out = self.bytes_in = self.bytes_out = self.dropped = 0

    async def listen(self, bind: str = "127.0.0.1", port: int = 0, advertise_host: str | None = None) -> str:
        """Start the listener; returns and stores the advertised address ``host:port``."""
        self._server = await asyncio.start_server(self._accept, bind, port, limit=STREAM_LIMIT)
        real_port = self._server.sockets[0].getsockname()[1]
        host = advertise_host or bind
        self.addr = f"[{host}]:{real_port}" if ":" in host else f"{host}:{real_port}"
        return self.addr

    async def close(self) -> None:
        """Close the listener and all links; calls in flight fail with :class:`Unavailable`."""
        if self._server:
            self._server.close()
        for d in list(self._dialled.values()):
            d.close()
        for link in list(self._accepted):
            link.close()
        self.calls.fail_all(Unavailable(f"data plane {self.name} closed"))
        await self.tasks.cancel_all()

    # -- sending -------------------------------------------------------------------------------
    def send(self, addr: str, op: int, dst: int, src: int, call_id: int, payload: bytes | memoryview) -> bool:
        """Send one DATA frame to interface ``dst`` at ``addr``; False (and counted) if dropped."""
        d = self._dialled.get(addr)
        if d is None:
            d = self._dialled[addr] = _Dialled(self, addr)
        if d.offer(framing.encode_data_header(op, dst, src, call_id, len(payload)), payload):
            self.msgs_out += 1
            self.bytes_out += len(payload)
            return True
        self.dropped += 1
        return False

    async def call(self, addr: str, dst: int, src: int, payload: bytes, timeout: float | None) -> bytes:
        """Send a service request to interface ``dst`` at ``addr`` and await the response bytes.

        Raises :class:`Unavailable` when the request is dropped (the link to the provider is
        saturated or gone), :class:`~rce.errors.Timeout` after ``timeout`` s,
        :class:`~rce.errors.RequestError` with the provider's reason on a failed call."""
        def send(cid: int) -> None:
            if not self.send(addr, framing.SRV_REQ, dst, src, cid, payload):
                raise Unavailable("service request dropped: the link to the provider is saturated")
        return await self.calls.call(send, timeout, what=f"the service call to interface {dst}")

    # -- receiving -----------------------------------------------------------------------------
    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nodelay(writer)
        link = FramedLink(reader, writer, name=f"data link from {writer.get_extra_info('peername')}",
                          on_frame=self._dispatch, on_close=self._accepted.discard, max_frame=self.max_frame,
                          max_buffer=self.max_buffer)
        self._accepted.add(link)
        link.start()

    def _dispatch(self, f: framing.DataFrame | dict) -> None:
        if not isinstance(f, framing.DataFrame):
            self.dropped += 1             # no control frames on data links
            return
        self.msgs_in += 1
        self.bytes_in += len(f.payload)
        if f.op == framing.MSG:
            iface = self.interfaces.get(f.dst)
            if iface is None:
                self.dropped += 1
                return
            try:
                iface.on_message(f.payload)
            except RCEError as e:         # e.g. a message for an interface that takes none
                self.dropped += 1
                log.debug("message refused", plane=self.name, iid=f.dst, reason=e.message)
        elif f.op == framing.SRV_REQ:
            self._serve(f)
        elif f.op in (framing.SRV_RESP, framing.SRV_ERR):
            settle_reply(self.calls, f)
        else:
            self.dropped += 1

    def _serve(self, f: framing.DataFrame) -> None:
        iface = self.interfaces.get(f.dst)
        addr = iface.peers.get(f.src) if iface is not None else self._reply_addr(f.src)
        if addr is None:                  # nowhere to answer: the caller times out
            self.dropped += 1
            return
        src, iid, call_id, payload = f.src, f.dst, f.call_id, bytes(f.payload)

        def reply(resp: bytes) -> None:
            self.send(addr, framing.SRV_RESP, src, iid, call_id, resp)

        def refuse(e: RCEError) -> None:
            self.send(addr, framing.SRV_ERR, src, iid, call_id, e.message.encode())
        if iface is None:
            self.dropped += 1
            refuse(Unavailable(f"interface {iid} is gone"))
            return
        self.responder.serve(lambda: iface.serve(payload), reply, refuse, f"service call to interface {iid}")

    def _reply_addr(self, src: int) -> str | None:
        """Where interface ``src`` lives, known from any local interface connected to it."""
        for iface in self.interfaces.values():
            addr = iface.peers.get(src)
            if addr:
                return addr
        return None

    def stats(self) -> dict:
        """``{msgs_in, msgs_out, bytes_in, bytes_out, dropped, links}`` (``links``: outgoing)."""
        return {"msgs_in": self.msgs_in, "msgs_out": self.msgs_out, "bytes_in": self.bytes_in,
                "bytes_out": self.bytes_out, "dropped": self.dropped, "links": len(self._dialled)}
