"""A robot endpoint stand-in that offers session resume, for client tests: the cloud side's rules
are the real ones (:class:`rce.protocol.session.RobotSession`, one per robot, kept across links);
this only moves frames and plays a tiny cloud:

- CN ``addInterfaces`` of robot-side interfaces creates them; CX ``connect`` of one brings it up
  (ST ``iu`` true); a CX naming a ``rcesync`` tag (a barrier) is refused with an ER naming it;
- a DM to a Subscriber* interface ``X`` is echoed on the interface ``echo[X]``;
- a service call through a ServiceProvider* interface is answered with its request, unless
  ``hold_calls`` is set (then it waits in ``held`` until :meth:`answer_held`).

:meth:`forget` ends the session (a resume is then refused with 401); :meth:`close_robot` closes
its link with 1008 (the cloud ended the session)."""
from __future__ import annotations

import hmac
import time
from http import HTTPStatus
from urllib.parse import parse_qsl, urlsplit

from websockets.asyncio.server import serve
from websockets.exceptions import ConnectionClosed

from rce.protocol.events import Deliver, RequestReady, ServiceCall
from rce.protocol.session import ResumeOptions, RobotSession


class ResumeCloud:
    def __init__(self, echo: dict[str, str] | None = None):
        self.echo = echo or {}
        self.session: RobotSession | None = None
        self.ws = None
        self.queries: list[dict[str, str]] = []
        self.taken: list[dict] = []                 # every DM the cloud took, in order
        self.hold_calls = False
        self.held: list[dict] = []
        self.itypes: dict[str, str] = {}
        self.server = None

    async def start(self) -> "ResumeCloud":
        self.server = await serve(self._serve, "127.0.0.1", 0, process_request=self._handshake, compression=None)
        return self

    @property
    def port(self) -> int:
        return self.server.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        self.server.close()
        await self.server.wait_closed()

    def _handshake(self, connection, request):
        q = dict(parse_qsl(urlsplit(request.path).query))
        self.queries.append(q)
        if "session" in q:
            s = self.session
            if s is None or not hmac.compare_digest(s.token.encode(), q["session"].encode()):
                return connection.respond(HTTPStatus.UNAUTHORIZED, "no session to resume (wrong or expired token)\n")
            connection.rce_ack = int(q.get("ack", "0"))
        else:
            resume = ResumeOptions() if q.get("resume") == "1" else None
            self.session = RobotSession(q.get("robotID", "r1"), resume=resume)
            self.itypes = {}
            connection.rce_ack = None
        return None

    async def _serve(self, ws) -> None:
        s = self.session
        if ws.rce_ack is not None:
            s.attach(ws.rce_ack)
        self.ws = ws
        await self._flush()
        try:
            async for frame in ws:
                (s.receive_text if isinstance(frame, str) else s.receive_binary)(frame, time.monotonic())
                self._events()
                await self._flush()
        except ConnectionClosed:
            pass
        if self.ws is ws and s.outgoing is not None and s is self.session:
            s.detach()

    async def _flush(self) -> None:
        try:
            for f in self.session.data_to_send():
                await self.ws.send(f)
        except ConnectionClosed:
            pass

    def _events(self) -> None:
        s = self.session
        for ev in s.events_received():
            match ev:
                case RequestReady(type=type_, data=data):
                    self._request(type_, data.wire())       # what the robot endpoint sends the master
                case Deliver(itag=itag, data=data):
                    self.taken.append(data)
                    if itag in self.echo:
                        s.send_dm(self.echo[itag], data["type"], "", data["msg"], data=True)
                case ServiceCall(data=data):
                    self.taken.append(data)
                    if self.hold_calls:
                        self.held.append(data)
                    else:
                        s.answer_call(data, data["msg"])

    def _request(self, t: str, data: dict) -> None:
        s = self.session
        error = None
        for itf in data.get("addInterfaces", []) if t == "CN" else []:
            if itf["endpointTag"] == s.robot:
                s.add_interface(itf["interfaceTag"], itf["interfaceType"], itf["className"])
        for c in data.get("connect", []) if t == "CX" else []:
            tags = [c["tagA"], c["tagB"]]
            if any("rcesync" in tag for tag in tags):
                error = f"interface {c['tagA']!r} does not exist"
                continue
            for tag in tags:
                etag, itag = tag.split("/")
                if etag == s.robot and itag in s.interfaces:
                    s.send_status({"topic": "iu", "iTag": itag, "status": True})
        s.request_done(error)
        self._events()

    async def answer_held(self) -> None:
        for call in self.held:
            self.session.answer_call(call, call["msg"])
        self.held.clear()
        await self._flush()

    async def push(self, itag: str, msg: dict) -> None:
        """The cloud sends a DM on ``itag`` (kept while detached)."""
        self.session.send_dm(itag, "std_msgs/String", "", msg, data=True)
        if self.session.attached:
            await self._flush()

    def forget(self) -> None:
        self.session = None

    async def close_robot(self, reason: str) -> None:
        await self.ws.close(1008, reason)
