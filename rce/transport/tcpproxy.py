"""A TCP proxy on loopback whose links can be cut, as a wireless link that goes away: for fault
tests (tests/engine, tests/client, tests/web), the faults benchmark (``bench/faults.py``) and the
fleet demo's ``--fault link:RobotN@T`` (``rce_fleet.live.faults``).

It listens on 127.0.0.1 (an ephemeral port) and forwards every connection to a target port on
127.0.0.1, both ways, passing an EOF on (a half close) and a reset on as a reset.
:meth:`TcpProxy.cut` resets every link (RST both ways: SO_LINGER 0, as the ends of a dropped
link see it) and refuses new connections (accepts and resets them) until :meth:`TcpProxy.restore`
or for ``refuse_s`` seconds.

Bounded: at most ``max_connections`` links at once (more are reset, counted in ``over_limit``);
per direction of a link the proxy reads at most ``buffer_bytes`` at a time and a write waits
(drain) while more than ``buffer_bytes`` are queued for the other end, so a slow end slows the
sender instead of growing a buffer. Counted: ``accepted``, ``refused``, ``over_limit``,
``unreachable`` connections, ``resets`` (links cut), ``bytes_up``/``bytes_down`` forwarded.

::

    proxy = await TcpProxy(target_port).start()   # proxy.port; proxy.url: ws://127.0.0.1:PORT/
    proxy.cut()                                   # drop everything, refuse new connections ...
    proxy.restore()                               # ... until now (proxy.restored_at: monotonic s)
    proxy.cut(refuse_s=2.0)                       # or drop everything and refuse for 2 s
    await proxy.close()
"""
from __future__ import annotations

import asyncio
import collections
import contextlib
import socket
import struct
import time
from typing import Callable

from rce.plumbing.log import get_logger

log = get_logger("rce.tcpproxy")

CONNECT_TIMEOUT_S = 5.0     # s the proxy waits for its target to accept (loopback: longer means it is down)
MAX_CONNECTIONS = 64        # links through one proxy at once (a fault test has a few); more are reset, counted
BUFFER_BYTES = 65536        # bytes per direction of a link: one read, and the queued-write bound before drain waits
REQUESTS_KEPT = 256         # first lines of accepted links kept in ``requests``; older ones are dropped, counted

Writer = asyncio.StreamWriter


def reset(writer: Writer) -> None:
    """Close ``writer``'s connection with an RST (SO_LINGER 0) at once, dropping what is queued."""
    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    writer.transport.abort()


class TcpProxy:
    """A TCP proxy from 127.0.0.1 (``port`` once started) to ``target_port`` on 127.0.0.1 (see
    the module docstring).

    ``max_connections``: links at once; ``buffer_bytes``: per direction of a link;
    ``connect_timeout_s``: the wait for the target to accept (s); ``clock``: monotonic s, for
    ``refuse_s``. ``requests``: the first line of the first bytes each accepted link sent (for a
    websocket: its HTTP request line), the last :data:`REQUESTS_KEPT`; ``restored_at``: when
    :meth:`restore` last ran (``clock`` s, 0.0 before)."""

    def __init__(self, target_port: int, *, max_connections: int = MAX_CONNECTIONS,
                 buffer_bytes: int = BUFFER_BYTES, connect_timeout_s: float = CONNECT_TIMEOUT_S,
                 clock: Callable[[], float] = time.monotonic):
        if max_connections < 1 or buffer_bytes < 2:
            raise ValueError(f"TcpProxy: max_connections {max_connections} must be >= 1 and "
                             f"buffer_bytes {buffer_bytes} >= 2")
        self.target_port = target_port
        self.max_connections, self.buffer_bytes = max_connections, buffer_bytes
        self.connect_timeout_s, self.clock = connect_timeout_s, clock
        self.port = 0
        self.restored_at = 0.0
        self.requests: collections.deque[bytes] = collections.deque(maxlen=REQUESTS_KEPT)
        self.requests_dropped = 0
        self.accepted = self.refused = self.over_limit = self.unreachable = self.resets = 0
        self.bytes_up = self.bytes_down = 0           # client -> target, target -> client
        self._refuse_until: float | None = 0.0        # None: until restore()
        self._generation = 0                          # bumped by every cut
        self._connecting = 0
        self._links: set[tuple[Writer, Writer]] = set()
        self._handlers: set[asyncio.Task] = set()
        self._server: asyncio.Server | None = None

    async def start(self) -> "TcpProxy":
        """Listen on 127.0.0.1, an ephemeral port (``port``); returns self. Raises OSError."""
        self._server = await asyncio.start_server(self._accept, "127.0.0.1", 0, limit=self._read_limit)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    @property
    def url(self) -> str:
        """``ws://127.0.0.1:PORT/``: the target's websocket endpoint, through the proxy."""
        return f"ws://127.0.0.1:{self.port}/"

    @property
    def refusing(self) -> bool:
        """Are new connections refused (a cut not yet over)?"""
        return self._refuse_until is None or self.clock() < self._refuse_until

    @property
    def links(self) -> int:
        """Links open through the proxy now."""
        return len(self._links)

    @property
    def _read_limit(self) -> int:
        return self.buffer_bytes // 2     # a StreamReader stops reading its socket above twice its limit

    def cut(self, refuse_s: float | None = None) -> None:
        """Reset every link (RST both ways) and refuse new connections until :meth:`restore`, or
        for ``refuse_s`` s."""
        self._refuse_until = None if refuse_s is None else self.clock() + refuse_s
        self._generation += 1
        for pair in self._links:
            for w in pair:
                reset(w)
            self.resets += 1
        self._links.clear()

    def restore(self) -> None:
        """Accept connections again (``restored_at``: now)."""
        self._refuse_until = 0.0
        self.restored_at = self.clock()

    def stats(self) -> dict[str, int]:
        """The counters: ``accepted``, ``reset`` (links cut), ``refused``, ``over_limit``,
        ``unreachable`` (connections), ``bytes_up``, ``bytes_down``."""
        return {"accepted": self.accepted, "reset": self.resets, "refused": self.refused,
                "over_limit": self.over_limit, "unreachable": self.unreachable,
                "bytes_up": self.bytes_up, "bytes_down": self.bytes_down}

    async def close(self) -> None:
        """Stop listening, reset every link, and wait (at most ``connect_timeout_s``) for the
        links' tasks to end."""
        if self._server is None:
            return
        self._server.close()
        self._server = None
        self.cut()
        if self._handlers:
            await asyncio.wait(list(self._handlers), timeout=self.connect_timeout_s)

    async def _accept(self, reader: asyncio.StreamReader, writer: Writer) -> None:
        task = asyncio.current_task()
        self._handlers.add(task)
        try:
            await self._serve(reader, writer)
        finally:
            self._handlers.discard(task)

    async def _serve(self, reader: asyncio.StreamReader, writer: Writer) -> None:
        if self.refusing or self._server is None:
            self.refused += 1
            return reset(writer)
        if len(self._links) + self._connecting >= self.max_connections:
            self.over_limit += 1
            log.warning("proxy: too many links, connection reset", port=self.port, limit=self.max_connections)
            return reset(writer)
        generation = self._generation
        self._connecting += 1
        try:
            async with asyncio.timeout(self.connect_timeout_s):
                up_r, up_w = await asyncio.open_connection("127.0.0.1", self.target_port, limit=self._read_limit)
        except (OSError, TimeoutError) as e:
            self.unreachable += 1
            log.warning("proxy: target unreachable", port=self.target_port, reason=str(e) or type(e).__name__)
            return reset(writer)
        finally:
            self._connecting -= 1
        if generation != self._generation:            # cut while connecting: this link went too
            self.resets += 1
            reset(writer)
            return reset(up_w)
        pair = (writer, up_w)
        self._links.add(pair)
        self.accepted += 1
        for w in pair:
            w.transport.set_write_buffer_limits(high=self.buffer_bytes)
        try:
            await asyncio.gather(self._pump(reader, up_w, pair, up=True), self._pump(up_r, writer, pair, up=False))
        finally:
            self._links.discard(pair)
            for w in pair:
                w.close()

    async def _pump(self, src: asyncio.StreamReader, dst: Writer, pair: tuple[Writer, Writer], up: bool) -> None:
        """Copy ``src`` to ``dst`` until EOF (passed on: a half close) or an error (both ends reset)."""
        first = up
        try:
            while data := await src.read(self.buffer_bytes):
                if first:
                    if len(self.requests) == self.requests.maxlen:
                        self.requests_dropped += 1
                    self.requests.append(data.split(b"\r\n", 1)[0])
                    first = False
                if dst.is_closing():
                    return
                dst.write(data)
                if up:
                    self.bytes_up += len(data)
                else:
                    self.bytes_down += len(data)
                await dst.drain()
            if not dst.is_closing() and dst.can_write_eof():
                dst.write_eof()
        except (ConnectionError, OSError):
            for w in pair:
                reset(w)
