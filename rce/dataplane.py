"""The data plane: direct endpoint <-> endpoint links (robot endpoint <-> environment,
environment <-> environment); the master carries no data.

Every endpoint process (an rce-robot task set, an environment) runs one
:class:`DataPlane`: a TCP listener for incoming links, and one outgoing link per
peer address, opened on first use. Frames are DATA frames of
:mod:`rce.framing` addressed by interface id (``dst``), so one link carries every
connection between the two processes. Each process sends only on the links it
dialled and receives on the links it accepted: no dial races.

Interfaces (:mod:`rce.interfaces`) register here by id and receive the frames
addressed to them. Outgoing links are bounded (``max_buffer`` bytes waiting in
the socket); a message that would pass the bound is dropped and counted.
"""
from __future__ import annotations

import asyncio
import collections
import itertools
from typing import TYPE_CHECKING

from rce import framing
from rce.errors import ProtocolError, Unavailable
from rce.log import get_logger
from rce.rpc import nodelay

if TYPE_CHECKING:
    from rce.interfaces import Interface

log = get_logger("rce.dataplane")


class _Link:
    """An outgoing link to one peer address; frames wait in ``backlog`` while it connects."""

    def __init__(self, plane: "DataPlane", addr: str):
        self.plane, self.addr = plane, addr
        self.writer: asyncio.StreamWriter | None = None
        self.backlog: collections.deque[bytes] = collections.deque()
        self.backlog_bytes = 0
        self.task = asyncio.create_task(self._connect())

    async def _connect(self) -> None:
        host, _, port = self.addr.rpartition(":")
        try:
            reader, writer = await asyncio.open_connection(host.strip("[]"), int(port))
        except OSError as e:
            log.warning("data link failed", peer=self.addr, reason=str(e))
            self.plane._links.pop(self.addr, None)
            self.plane.dropped += len(self.backlog)
            return
        nodelay(writer)
        self.writer = writer
        for chunk in self.backlog:
            writer.write(chunk)
        self.backlog.clear()
        self.backlog_bytes = 0
        try:
            await reader.read()        # the peer never sends on this link; EOF = closed
        except (ConnectionError, OSError):
            pass
        finally:
            self.plane._links.pop(self.addr, None)
            writer.close()

    def write(self, head: bytes, payload: bytes | memoryview) -> bool:
        n = len(head) + len(payload)
        if self.writer is None:
            if self.backlog_bytes + n > self.plane.max_buffer:
                return False
            self.backlog.append(head + bytes(payload))
            self.backlog_bytes += n
            return True
        t = self.writer.transport
        if t.is_closing() or t.get_write_buffer_size() + n > self.plane.max_buffer:
            return False
        self.writer.write(head)
        self.writer.write(payload)
        return True


class DataPlane:
    """One process's data-plane endpoint. ``advertise_host`` is the address peers dial."""

    def __init__(self, name: str, *, max_buffer: int = 64 * 1024 * 1024,
                 max_frame: int = framing.DEFAULT_MAX_FRAME):
        self.name = name
        self.max_buffer, self.max_frame = max_buffer, max_frame
        self.interfaces: dict[int, "Interface"] = {}
        self.addr = ""
        self._links: dict[str, _Link] = {}
        self._server: asyncio.AbstractServer | None = None
        self._readers: set[asyncio.Task] = set()
        self._calls: dict[int, asyncio.Future] = {}
        self._call_ids = itertools.count(1)
        # counters (metrics and status)
        self.msgs_in = self.msgs_out = self.bytes_in = self.bytes_out = self.dropped = 0

    async def listen(self, bind: str = "127.0.0.1", port: int = 0, advertise_host: str | None = None) -> str:
        """Start the listener; returns and stores the advertised address ``host:port``."""
        self._server = await asyncio.start_server(self._accept, bind, port, limit=2**20)
        real_port = self._server.sockets[0].getsockname()[1]
        host = advertise_host or bind
        self.addr = f"[{host}]:{real_port}" if ":" in host else f"{host}:{real_port}"
        return self.addr

    async def close(self) -> None:
        """Close the listener and all links."""
        if self._server:
            self._server.close()
        for link in list(self._links.values()):
            link.task.cancel()
            if link.writer:
                link.writer.close()
        for t in list(self._readers):
            t.cancel()
        for fut in self._calls.values():
            if not fut.done():
                fut.set_exception(Unavailable("data plane closed"))

    # -- sending -------------------------------------------------------------------------------
    def send(self, addr: str, op: int, dst: int, src: int, call_id: int, payload: bytes | memoryview) -> bool:
        """Send one DATA frame to interface ``dst`` at ``addr``; False (and counted) if dropped."""
        link = self._links.get(addr)
        if link is None:
            link = self._links[addr] = _Link(self, addr)
        if link.write(framing.encode_data_header(op, dst, src, call_id, len(payload)), payload):
            self.msgs_out += 1
            self.bytes_out += len(payload)
            return True
        self.dropped += 1
        return False

    async def call(self, addr: str, dst: int, src: int, payload: bytes, timeout: float | None) -> bytes:
        """Send a service request to interface ``dst`` at ``addr`` and await the response bytes.

        Raises :class:`Unavailable` on timeout or drop, :class:`RequestError` with the
        provider's reason on a failed call."""
        cid = next(self._call_ids)
        fut = asyncio.get_running_loop().create_future()
        self._calls[cid] = fut
        try:
            if not self.send(addr, framing.SRV_REQ, dst, src, cid, payload):
                raise Unavailable("service request dropped: the link to the provider is saturated")
            return await asyncio.wait_for(fut, timeout)
        except asyncio.TimeoutError:
            raise Unavailable(f"service call timed out after {timeout} s") from None
        finally:
            self._calls.pop(cid, None)

    # -- receiving -----------------------------------------------------------------------------
    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nodelay(writer)
        task = asyncio.current_task()
        self._readers.add(task)
        try:
            while True:
                f = await framing.read_frame(reader, self.max_frame)
                if isinstance(f, framing.DataFrame):
                    self._dispatch(f)
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        except ProtocolError as e:
            log.warning("closing data link on bad frame", plane=self.name, reason=str(e))
        except asyncio.CancelledError:
            pass   # close(): end normally, or Python 3.11's stream callback logs the cancellation as an error
        finally:
            self._readers.discard(task)
            writer.close()

    def _dispatch(self, f: framing.DataFrame) -> None:
        self.msgs_in += 1
        self.bytes_in += len(f.payload)
        if f.op in (framing.SRV_RESP, framing.SRV_ERR):
            framing.settle_call(self._calls, f)
            return
        iface = self.interfaces.get(f.dst)
        if iface is None:
            self.dropped += 1
            if f.op == framing.SRV_REQ:
                self._reply_error(f, f"interface {f.dst} is gone")
            return
        if f.op == framing.MSG:
            iface.on_message(f.payload)
        elif f.op == framing.SRV_REQ:
            asyncio.create_task(self._serve(iface, f.src, f.call_id, bytes(f.payload)))

    async def _serve(self, iface: "Interface", src: int, call_id: int, payload: bytes) -> None:
        addr = iface.peers.get(src)
        if addr is None:
            return
        try:
            resp = await iface.serve(payload)
            self.send(addr, framing.SRV_RESP, src, iface.iid, call_id, resp)
        except Exception as e:
            reason = getattr(e, "message", None) or f"{type(e).__name__}: {e}"
            self.send(addr, framing.SRV_ERR, src, iface.iid, call_id, reason.encode())

    def _reply_error(self, f: framing.DataFrame, reason: str) -> None:
        for iface in self.interfaces.values():
            addr = iface.peers.get(f.src)
            if addr:
                self.send(addr, framing.SRV_ERR, f.src, f.dst, f.call_id, reason.encode())
                return

    def stats(self) -> dict:
        return {"msgs_in": self.msgs_in, "msgs_out": self.msgs_out, "bytes_in": self.bytes_in,
                "bytes_out": self.bytes_out, "dropped": self.dropped, "links": len(self._links)}
