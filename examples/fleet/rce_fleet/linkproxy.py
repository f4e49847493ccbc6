"""A robot's link through a loopback proxy the demo runs, so ``rce-fleet demo --fault
link:RobotN@T`` can cut it (:mod:`rce_fleet.faults`).

* :class:`LinkProxy`: a TCP proxy on 127.0.0.1 to the robot endpoint's websocket port. ``cut()``
  drops every connection (RST both ways, as a wireless link that goes away) and resets new ones
  until ``restore()``.
* :class:`LoginRelay`: the robot's login URL. It passes ``GET /?userID=..&version=..`` on to the
  master and answers with the master's status and body, with the websocket ``url`` of a 200
  answer replaced by the proxy's: the robot's bridge (and its reconnects, which dial the URL of its
  session) then goes through the proxy. The RCE login protocol: docs/INTERNALS.md, "Processes
  and links".

::

    proxy = await LinkProxy(ws_port).start()
    relay = await LoginRelay(master_url, proxy.url).start()    # relay.url: the robot's login URL
    proxy.cut(); proxy.restore()
    await relay.stop(); await proxy.stop()
"""
from __future__ import annotations

import asyncio
import json

import aiohttp
from aiohttp import web

from rce.log import get_logger

log = get_logger("fleet.link")

CHUNK = 65536               # bytes read at a time from either side of the proxy
LOGIN_TIMEOUT_S = 10.0      # wall s the relay waits for the master's login answer (a client's own login waits as long)


class LinkProxy:
    """A TCP proxy from 127.0.0.1 (an ephemeral port) to ``target`` port on 127.0.0.1.
    ``connections``: links accepted; ``refused``: connections reset while cut."""

    def __init__(self, target: int):
        self.target = target
        self.cutting = False
        self.connections = self.refused = 0
        self._pairs: set[tuple[asyncio.StreamWriter, asyncio.StreamWriter]] = set()
        self._server: asyncio.Server | None = None

    async def start(self) -> "LinkProxy":
        self._server = await asyncio.start_server(self._accept, "127.0.0.1", 0)
        return self

    @property
    def url(self) -> str:
        """``ws://127.0.0.1:PORT/``: the robot endpoint, through the proxy."""
        return f"ws://127.0.0.1:{self._server.sockets[0].getsockname()[1]}/"

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.cutting:
            self.refused += 1
            writer.transport.abort()
            return
        try:
            up_r, up_w = await asyncio.open_connection("127.0.0.1", self.target)
        except OSError as e:
            log.warning("proxy: robot endpoint unreachable", port=self.target, reason=str(e))
            writer.transport.abort()
            return
        self.connections += 1
        pair = (writer, up_w)
        self._pairs.add(pair)
        try:
            await asyncio.gather(_pipe(reader, up_w), _pipe(up_r, writer))
        finally:
            self._pairs.discard(pair)

    def cut(self) -> None:
        """Drop every connection (RST both ways) and reset new ones until :meth:`restore`."""
        self.cutting = True
        for a, b in list(self._pairs):
            a.transport.abort()
            b.transport.abort()

    def restore(self) -> None:
        """Accept connections again."""
        self.cutting = False

    async def stop(self) -> None:
        self.cut()
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()


async def _pipe(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
    """Copy ``r`` to ``w`` until either ends; then reset ``w`` (the other pipe ends in turn)."""
    try:
        while data := await r.read(CHUNK):
            w.write(data)
            await w.drain()
    except (ConnectionError, OSError):
        pass
    finally:
        w.transport.abort()


class LoginRelay:
    """The login URL of a robot whose link goes through ``ws_url`` (see the module docstring)."""

    def __init__(self, master_url: str, ws_url: str):
        self.master_url, self.ws_url = master_url, ws_url
        self._runner: web.AppRunner | None = None
        self.url = ""

    async def start(self) -> "LoginRelay":
        app = web.Application()
        app.router.add_get("/", self._login)
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, "127.0.0.1", 0)
        await site.start()
        self.url = f"http://127.0.0.1:{self._runner.addresses[0][1]}/"
        return self

    async def _login(self, request: web.Request) -> web.Response:
        url = self.master_url.rstrip("/") + "/?" + request.query_string
        try:
            async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=LOGIN_TIMEOUT_S)) as http:
                async with http.get(url) as resp:
                    status, body = resp.status, await resp.read()
                    headers = {k: v for k, v in resp.headers.items() if k in ("Retry-After", "Content-Type")}
        except (aiohttp.ClientError, asyncio.TimeoutError, OSError) as e:
            return web.json_response({"error": f"login relay: master unreachable: {e or type(e).__name__}"},
                                     status=503)
        if status == 200:
            try:
                answer = json.loads(body)
                answer["url"] = self.ws_url
                body = json.dumps(answer).encode()
            except (ValueError, TypeError):
                pass                # the client reports the master's malformed answer
        return web.Response(status=status, body=body, headers=headers)

    async def stop(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
