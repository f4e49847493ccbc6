"""A TCP proxy for fault tests: forwards between clients and a target port on loopback and can
drop every connection (RST both ways) and refuse new ones for a while, as a wireless link that
goes away does.

::

    proxy = await Proxy(target_port).start()     # listens on 127.0.0.1, an ephemeral port
    proxy.url                                     # ws://127.0.0.1:PORT/
    proxy.cut()                                   # drop everything, refuse (reset) new connections
    proxy.restore()                               # accept again; proxy.restored_at: when (monotonic s)
    await proxy.stop()
"""
from __future__ import annotations

import asyncio
import time

CHUNK = 65536       # bytes read at a time from either side


class Proxy:
    """A TCP proxy on 127.0.0.1 to ``target`` port; ``requests``: the first bytes of each accepted
    connection (for a websocket: its HTTP upgrade request line)."""

    def __init__(self, target: int):
        self.target = target
        self.refusing = False
        self.pairs: set[tuple[asyncio.StreamWriter, asyncio.StreamWriter]] = set()
        self.server: asyncio.Server | None = None
        self.restored_at = 0.0
        self.requests: list[bytes] = []

    async def start(self) -> "Proxy":
        self.server = await asyncio.start_server(self._accept, "127.0.0.1", 0)
        return self

    @property
    def port(self) -> int:
        return self.server.sockets[0].getsockname()[1]

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/"

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.refusing:
            writer.transport.abort()
            return
        try:
            up_r, up_w = await asyncio.open_connection("127.0.0.1", self.target)
        except OSError:
            writer.transport.abort()
            return
        pair = (writer, up_w)
        self.pairs.add(pair)
        try:
            await asyncio.gather(self._pipe(reader, up_w, first=True), self._pipe(up_r, writer))
        finally:
            self.pairs.discard(pair)

    async def _pipe(self, r: asyncio.StreamReader, w: asyncio.StreamWriter, first: bool = False) -> None:
        try:
            while data := await r.read(CHUNK):
                if first:
                    self.requests.append(data.split(b"\r\n", 1)[0])
                    first = False
                w.write(data)
                await w.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            w.transport.abort()

    def cut(self) -> None:
        """Drop every connection (RST both ways) and refuse new ones until :meth:`restore`."""
        self.refusing = True
        for a, b in list(self.pairs):
            a.transport.abort()
            b.transport.abort()

    def restore(self) -> None:
        self.refusing = False
        self.restored_at = time.monotonic()

    async def stop(self) -> None:
        self.cut()
        self.server.close()
        await self.server.wait_closed()
