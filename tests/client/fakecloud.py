"""A tiny stand-in for the cloud side of the client protocol, for client unit tests.

:class:`FakeEndpoint` plays a robot endpoint (websockets server on 127.0.0.1, port 0):
it records the handshake query, assembles what the robot sends (JSON + binary parts)
into ``received`` and lets the test send any frame, binary parts before or after the
JSON frame. With ``auto=True`` it behaves like a minimal cloud for ``rce-ros``: robot-side
interfaces come up (ST iu true) when connected, sync probes get their ER, DMs to a
Subscriber* interface are echoed on the paired Publisher* interface, and service calls to a
ServiceProvider* interface are answered with the request.

:func:`login_server` is a tiny aiohttp master login (``GET /?userID=U&version=V``).
"""
from __future__ import annotations

import asyncio
import json
import time
from http import HTTPStatus
from urllib.parse import parse_qsl, urlsplit

from aiohttp import web
from websockets.asyncio.server import serve

from rce.protocol import frames as wire


class FakeEndpoint:
    def __init__(self, *, refuse: tuple[int, str] | None = None, auto: bool = False,
                 echo: dict[str, str] | None = None):
        self.refuse = refuse
        self.auto = auto
        self.echo = echo or {}                 # Subscriber iTag -> Publisher iTag (auto mode)
        self.received: asyncio.Queue[dict] = asyncio.Queue()
        self.log: list[dict] = []              # every assembled message, in order
        self.query: dict[str, str] = {}
        self.ws = None
        self.connected = asyncio.Event()
        self.disconnected = asyncio.Event()
        self.robot_itfs: dict[str, str] = {}   # robot-side iTag -> interfaceType (auto mode)
        self.assembler = wire.Assembler()
        self.server = None

    async def start(self) -> "FakeEndpoint":
        self.server = await serve(self._session, "127.0.0.1", 0, process_request=self._handshake,
                                  compression=None)
        return self

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.server.sockets[0].getsockname()[1]}/"

    async def stop(self) -> None:
        self.server.close()
        await self.server.wait_closed()

    def _handshake(self, connection, request):
        self.query = dict(parse_qsl(urlsplit(request.path).query))
        if self.refuse:
            status, reason = self.refuse
            return connection.respond(HTTPStatus(status), reason + "\n")
        return None

    async def _session(self, ws) -> None:
        self.ws = ws
        self.connected.set()
        try:
            async for frame in ws:
                now = time.monotonic()
                done = (self.assembler.feed_text(frame, now) if isinstance(frame, str)
                        else self.assembler.feed_binary(frame, now))
                for m in done:
                    self.log.append(m)
                    self.received.put_nowait(m)
                    if self.auto:
                        await self._auto(m)
        except Exception:
            pass
        finally:
            self.disconnected.set()

    # -- sending ---------------------------------------------------------------------------------
    async def send(self, type_: str, data, *, binary_first: bool = False) -> None:
        text, frames = wire.encode({"type": type_, "data": data})
        order = frames + [text] if binary_first else [text] + frames
        for f in order:
            await self.ws.send(f)

    async def recv(self, timeout: float = 5.0) -> dict:
        return await asyncio.wait_for(self.received.get(), timeout)

    async def recv_type(self, type_: str, timeout: float = 5.0) -> dict:
        """The next received message of ``type_`` (others are skipped)."""
        while True:
            m = await self.recv(timeout)
            if m["type"] == type_:
                return m

    # -- auto mode: a minimal cloud ----------------------------------------------------------------
    async def _auto(self, m: dict) -> None:
        t, d = m["type"], m["data"]
        robot = self.query.get("robotID")
        if t == "CN":
            for itf in d.get("addInterfaces", []):
                if itf["endpointTag"] == robot:
                    self.robot_itfs[itf["interfaceTag"]] = itf["interfaceType"]
            for itf in d.get("removeInterfaces", []):
                if self.robot_itfs.pop(itf["interfaceTag"], None) is not None:
                    await self.send("ST", {"topic": "iu", "iTag": itf["interfaceTag"], "status": False})
        elif t == "CX":
            for c in d.get("connect", []):
                tags = (c["tagA"], c["tagB"])
                if any(tag.startswith("rcesync") for tag in tags):
                    await self.send("ER", f"CX: interface {c['tagA']!r} does not exist")
                    continue
                for tag in tags:
                    etag, itag = tag.split("/")
                    if etag == robot and itag in self.robot_itfs:
                        await self.send("ST", {"topic": "iu", "iTag": itag, "status": True})
        elif t == "DM":
            itag = d["iTag"]
            kind = self.robot_itfs.get(itag, "")
            if kind.startswith("Subscriber") and itag in self.echo:
                await self.send("DM", {"iTag": self.echo[itag], "type": d["type"], "msgID": "", "msg": d["msg"]})
            elif kind.startswith("ServiceProvider"):
                await self.send("DM", {"iTag": itag, "type": d["type"], "msgID": d.get("msgID"), "msg": d["msg"]})


async def login_server(handler) -> tuple[web.AppRunner, str]:
    """Serve ``handler(request)`` on GET / at 127.0.0.1:0; returns (runner, url)."""
    app = web.Application()
    app.router.add_get("/", handler)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = site._server.sockets[0].getsockname()[1]
    return runner, f"http://127.0.0.1:{port}/"


def ws_url_answer(ws_url: str, **extra) -> web.Response:
    return web.json_response({"url": ws_url, **extra})


def dumps(obj) -> str:
    return json.dumps(obj, separators=(",", ":"))
