"""A robot's login for a link through a loopback proxy the demo runs (:class:`rce.transport.tcpproxy.TcpProxy`),
so ``rce-fleet demo --fault link:RobotN@T`` can cut it (:mod:`rce_fleet.live.faults`).

:class:`LoginRelay`: the robot's login URL. It passes ``GET /?userID=..&version=..`` on to the
master and answers with the master's status and body, with the websocket ``url`` of a 200 answer
replaced by the proxy's: the robot's bridge (and its reconnects, which dial the URL of its
session) then goes through the proxy. The RCE login protocol: docs/INTERNALS.md, "Processes and
links".

::

    proxy = await TcpProxy(ws_port).start()
    relay = await LoginRelay(master_url, proxy.url).start()    # relay.url: the robot's login URL
    proxy.cut(); proxy.restore()
    await relay.stop(); await proxy.close()
"""
from __future__ import annotations

import asyncio
import json

import aiohttp
from aiohttp import web

LOGIN_TIMEOUT_S = 10.0      # wall s the relay waits for the master's login answer (a client's own login waits as long)


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
