"""A Prometheus ``/metrics`` endpoint on asyncio's own stream server, for the task sets that serve
no other HTTP (rce-robot, rce-container).

::

    server = MetricsServer(render)                  # render: async () -> bytes, the exposition text
    port = await server.start("127.0.0.1", 0)       # ssl_context=...: https://
    await server.close()

``GET /metrics`` (any query string) answers 200 with what ``render`` returns (Prometheus' text format,
``CONTENT_TYPE_LATEST``); another path 404, another method 405, a request that is not HTTP/1.x 400. A request head
is read within :data:`HEAD_TIMEOUT` s and up to :data:`MAX_HEAD` bytes (else the connection is
closed), and each connection carries one request (``Connection: close``). aiohttp would serve the
same, but importing it (its client and TLS contexts come with it) costs each of these processes
about 0.4 CPU-s at start.
"""
from __future__ import annotations

import asyncio
import ssl
from collections.abc import Awaitable, Callable
from http import HTTPStatus

from prometheus_client import CONTENT_TYPE_LATEST

from rce.plumbing.http1 import closing_answer
from rce.plumbing.log import get_logger

__all__ = ["HEAD_TIMEOUT", "MAX_HEAD", "MetricsServer"]

log = get_logger("rce.metrics")

HEAD_TIMEOUT = 10.0     # seconds a client has to send its request line and headers
MAX_HEAD = 8192         # bytes of request line and headers taken


class MetricsServer:
    """Serves ``GET /metrics`` with the bytes ``render()`` returns (see the module's docstring)."""

    def __init__(self, render: Callable[[], Awaitable[bytes]]) -> None:
        self.render = render
        self._server: asyncio.Server | None = None

    async def start(self, host: str, port: int, ssl_context: ssl.SSLContext | None = None) -> int:
        """Listen on ``host``:``port`` (0: an ephemeral port; https:// with ``ssl_context``); returns the port."""
        self._server = await asyncio.start_server(self._serve, host, port, ssl=ssl_context, limit=MAX_HEAD)
        return self._server.sockets[0].getsockname()[1]

    async def close(self) -> None:
        """Stop listening (requests being answered are answered)."""
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            try:
                async with asyncio.timeout(HEAD_TIMEOUT):
                    head = await reader.readuntil(b"\r\n\r\n")
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError):
                return
            status, body = await self._answer(head.split(b"\r\n", 1)[0].split(b" "))
            writer.write(closing_answer(status, body, CONTENT_TYPE_LATEST))
            await writer.drain()
        except (ConnectionError, ssl.SSLError) as e:
            log.debug("metrics client gone", error=str(e))
        finally:
            writer.close()

    async def _answer(self, request_line: list[bytes]) -> tuple[HTTPStatus, bytes]:
        """The status and body for a request line split at its spaces."""
        if len(request_line) != 3 or not request_line[2].startswith(b"HTTP/1."):
            return HTTPStatus.BAD_REQUEST, b"bad request\n"
        method, target, _ = request_line
        if target.split(b"?", 1)[0] != b"/metrics":
            return HTTPStatus.NOT_FOUND, b"not found\n"
        if method != b"GET":
            return HTTPStatus.METHOD_NOT_ALLOWED, b"method not allowed\n"
        return HTTPStatus.OK, await self.render()
