"""In-memory streams for link-layer tests: what one end writes, the other end receives, through
its protocol as from a real transport (the end's :class:`asyncio.StreamReader` until a link takes
the transport over with its own protocol, e.g. a buffered one); no sockets. ``waiting`` plays the
bytes a real transport would hold unsent (set it to test write bounds); ``recv_size`` the most
bytes one receive hands over (a frame arrives in several reads, as from a socket)."""
from __future__ import annotations

import asyncio

RECV_SIZE = 64 * 1024     # bytes one simulated receive hands over at most


class _ReaderProtocol:
    """An end's protocol before a link takes it over: bytes go to its StreamReader."""

    def __init__(self, reader: asyncio.StreamReader):
        self.reader = reader

    def data_received(self, data: bytes) -> None:
        self.reader.feed_data(data)

    def eof_received(self) -> None:
        self.reader.feed_eof()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.reader.at_eof():
            self.reader.feed_eof()

    def pause_writing(self) -> None:
        pass

    def resume_writing(self) -> None:
        pass


class MemTransport:
    """One end's transport: ``write`` delivers to the other end's protocol (or records, unpaired)."""

    def __init__(self, reader: asyncio.StreamReader | None = None):
        self.protocol = _ReaderProtocol(reader or asyncio.StreamReader())
        self.other: MemTransport | None = None
        self.written = bytearray()
        self.writes = 0           # write and writelines calls (each is one system call on a real transport)
        self.waiting = 0
        self.closing = False
        self.recv_size = RECV_SIZE

    def write(self, data) -> None:
        assert not self.closing, "write after close"
        self.writes += 1
        if self.other is not None:
            self.other._deliver(bytes(data))
        else:
            self.written += data

    def writelines(self, chunks) -> None:
        self.write(b"".join(chunks))      # one call, as a real transport's writelines

    def _deliver(self, data: bytes) -> None:
        if self.closing:
            return
        p = self.protocol
        for pos in range(0, len(data), self.recv_size):
            piece = memoryview(data)[pos:pos + self.recv_size]
            if not isinstance(p, asyncio.BufferedProtocol):
                p.data_received(bytes(piece))
                continue
            while piece:
                buf = p.get_buffer(len(piece))
                k = min(len(buf), len(piece))
                buf[:k] = piece[:k]
                piece = piece[k:]
                p.buffer_updated(k)

    def get_protocol(self):
        return self.protocol

    def set_protocol(self, protocol) -> None:
        self.protocol = protocol

    def resume_reading(self) -> None:
        pass

    def get_write_buffer_size(self) -> int:
        return self.waiting

    def is_closing(self) -> bool:
        return self.closing

    def close(self) -> None:
        if not self.closing:
            self.closing = True
            if self.other is not None and not self.other.closing:
                self.other.protocol.eof_received()
            self.protocol.connection_lost(None)


class MemWriter:
    """Stands in for :class:`asyncio.StreamWriter` (what :class:`rce.transport.link.FramedLink` uses of it)."""

    def __init__(self, transport: MemTransport, peername: str = "mem"):
        self.transport = transport
        self.peername = peername

    def close(self) -> None:
        self.transport.close()

    def get_extra_info(self, key: str, default=None):
        return self.peername if key == "peername" else default

    async def drain(self) -> None:
        pass


def pipe() -> tuple[tuple[asyncio.StreamReader, MemWriter], tuple[asyncio.StreamReader, MemWriter]]:
    """Two connected ends, each ``(reader, writer)``."""
    ra, rb = asyncio.StreamReader(), asyncio.StreamReader()
    ta, tb = MemTransport(ra), MemTransport(rb)
    ta.other, tb.other = tb, ta
    return (ra, MemWriter(ta, "b")), (rb, MemWriter(tb, "a"))


def lone(data: bytes = b"", eof: bool = False) -> tuple[asyncio.StreamReader, MemWriter]:
    """One end whose reader holds ``data`` (then EOF if ``eof``) and whose writes are recorded."""
    r = asyncio.StreamReader()
    if data:
        r.feed_data(data)
    if eof:
        r.feed_eof()
    return r, MemWriter(MemTransport(r))
