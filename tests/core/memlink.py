"""In-memory streams for link-layer tests: what one end writes, the other end's
:class:`asyncio.StreamReader` receives; no sockets. ``waiting`` plays the bytes a real
transport would hold unsent (set it to test write bounds)."""
from __future__ import annotations

import asyncio


class MemTransport:
    """The write half of one end: ``write`` feeds the other end's reader (or records, unpaired)."""

    def __init__(self, peer: asyncio.StreamReader | None = None):
        self.peer = peer
        self.written = bytearray()
        self.waiting = 0
        self.closing = False

    def write(self, data) -> None:
        assert not self.closing, "write after close"
        if self.peer is not None:
            self.peer.feed_data(bytes(data))
        else:
            self.written += data

    def get_write_buffer_size(self) -> int:
        return self.waiting

    def is_closing(self) -> bool:
        return self.closing

    def close(self) -> None:
        if not self.closing:
            self.closing = True
            if self.peer is not None:
                self.peer.feed_eof()


class MemWriter:
    """Stands in for :class:`asyncio.StreamWriter` (what :class:`rce.link.FramedLink` uses of it)."""

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
    return (ra, MemWriter(MemTransport(rb), "b")), (rb, MemWriter(MemTransport(ra), "a"))


def lone(data: bytes = b"", eof: bool = False) -> tuple[asyncio.StreamReader, MemWriter]:
    """One end whose reader holds ``data`` (then EOF if ``eof``) and whose writes are recorded."""
    r = asyncio.StreamReader()
    if data:
        r.feed_data(data)
    if eof:
        r.feed_eof()
    return r, MemWriter(MemTransport())
