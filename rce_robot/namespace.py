"""A robot namespace: one connected robot's session on a robot endpoint.

It reads the robot's websocket (JSON text frames and binary parts, DESIGN
section 3), hands CC/DC/CN/CX to the master one at a time and in order, routes
DMs to the robot's interfaces, and writes everything the robot receives
through one bounded outgoing queue (data messages beyond the bound are
dropped and counted; ST and ER are never dropped). Any bad frame gets an ER
naming what was wrong; the session goes on.
"""
from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING, Any

from websockets.exceptions import ConnectionClosed

from rce import protocol
from rce.errors import ProtocolError, RCEError
from rce.log import get_logger

if TYPE_CHECKING:
    from rce_robot.endpoint import RobotEndpoint
    from rce_robot.interfaces import RobotInterface

log = get_logger("rce.robot")


class RobotNamespace:
    """Session of robot ``robot`` of user ``user`` on websocket ``ws``."""

    def __init__(self, endpoint: "RobotEndpoint", ws, user: str, robot: str):
        self.endpoint, self.ws, self.user, self.robot = endpoint, ws, user, robot
        self.interfaces: dict[str, "RobotInterface"] = {}
        self.assembler = protocol.Assembler(expiry=endpoint.expiry)
        self.out: asyncio.Queue = asyncio.Queue()
        self.out_data = 0                      # data messages waiting in ``out``
        self.requests: asyncio.Queue = asyncio.Queue()
        self.in_flight = 0                     # requests queued or running
        self.idle = asyncio.Event()            # set when no request is queued or running
        self.idle.set()
        self.dropped = self.msgs_in = self.msgs_out = self.errors = 0

    # -- outgoing ----------------------------------------------------------------------------------
    def _enqueue(self, obj: dict, data: bool) -> None:
        if data:
            if self.out_data >= self.endpoint.queue_size:
                self.dropped += 1
                self.endpoint.metrics.dropped.inc()
                return
            self.out_data += 1
        self.out.put_nowait((obj, data))

    def send_dm(self, itag: str, cls: str, msg_id: str, msg: Any, data: bool = False) -> None:
        """Queue a DM to the robot; ``data=True`` marks droppable topic data."""
        self._enqueue({"type": "DM", "data": {"iTag": itag, "type": cls, "msgID": msg_id, "msg": msg}}, data)

    def send_status(self, data: dict) -> None:
        self._enqueue({"type": "ST", "data": data}, False)

    def send_error(self, reason: str) -> None:
        self.errors += 1
        self.endpoint.metrics.errors.inc()
        log.info("ER to robot", user=self.user, robot=self.robot, reason=reason)
        self._enqueue({"type": "ER", "data": reason}, False)

    async def _writer(self) -> None:
        while True:
            obj, data = await self.out.get()
            if data:
                self.out_data -= 1
            text, frames = protocol.encode(obj)
            await self.ws.send(text)
            for f in frames:
                await self.ws.send(f)
            self.msgs_out += 1
            self.endpoint.metrics.msgs_out.inc()

    # -- incoming ----------------------------------------------------------------------------------
    async def run(self) -> None:
        """Serve the session until the websocket closes."""
        tasks = [asyncio.create_task(self._writer()), asyncio.create_task(self._requests()),
                 asyncio.create_task(self._expire())]
        try:
            async for frame in self.ws:
                self._on_frame(frame)
        except ConnectionClosed:
            pass
        finally:
            for t in tasks:
                t.cancel()
            for iface in list(self.interfaces.values()):
                await iface.stop()
            self.interfaces.clear()

    def _on_frame(self, frame: str | bytes) -> None:
        limit = self.endpoint.max_message
        now = time.monotonic()
        try:
            if len(frame) > limit:
                raise ProtocolError(f"{'binary' if isinstance(frame, bytes) else 'text'} frame of {len(frame)} "
                                    f"bytes exceeds the limit of {limit} bytes; dropped")
            if isinstance(frame, bytes):
                done = self.assembler.feed_binary(frame, now)
            else:
                done = self.assembler.feed_text(frame, now)
        except RCEError as e:
            self.send_error(e.message)
            return
        for msg in done:
            self._on_message(msg)

    def _on_message(self, msg: dict) -> None:
        self.msgs_in += 1
        self.endpoint.metrics.msgs_in.inc()
        try:
            t, data = protocol.validate(msg)
        except RCEError as e:
            self.send_error(e.message)
            return
        if t == protocol.DM:
            iface = self.interfaces.get(data["iTag"])
            if iface is None and not self.idle.is_set():
                # the interface may be created by a request sent before this DM: keep the robot's order
                asyncio.create_task(self._dm_after_requests(data))
                return
            self._route_dm(iface, data)
        else:
            self.in_flight += 1
            self.idle.clear()
            self.requests.put_nowait((t, data))

    async def _dm_after_requests(self, data: dict) -> None:
        await self.idle.wait()
        self._route_dm(self.interfaces.get(data["iTag"]), data)

    def _route_dm(self, iface: "RobotInterface | None", data: dict) -> None:
        if iface is None:
            self.send_error(f"DM: no interface {data['iTag']!r} on robot {self.robot!r}")
            return
        if str(data["type"]).strip("/") != iface.cls:
            self.send_error(f"DM: interface {data['iTag']!r} carries {iface.cls!r}, not {data['type']!r}")
            return
        if iface.kind == "ServiceProvider":      # the only DM that waits (for the service's reply)
            asyncio.create_task(self._call(iface, data))
            return
        try:
            iface.from_robot(data)
        except RCEError as e:
            self.send_error(e.message)

    async def _call(self, iface: "RobotInterface", data: dict) -> None:
        try:
            await iface.call_from_robot(data)
        except RCEError as e:
            self.send_error(f"service call {data.get('msgID')!r} on {iface.itag!r} failed: {e.message}")

    async def _requests(self) -> None:
        master = self.endpoint.master
        while True:
            t, data = await self.requests.get()
            try:
                await master.call("robot_request", timeout=120, user=self.user, robot=self.robot, type=t, data=data)
            except RCEError as e:
                self.send_error(f"{t}: {e.message}")
            finally:
                self.in_flight -= 1
                if self.in_flight == 0:
                    self.idle.set()

    async def _expire(self) -> None:
        while True:
            await asyncio.sleep(min(5.0, self.endpoint.expiry / 2))
            for reason in self.assembler.expire(time.monotonic()):
                self.send_error(reason)

    async def close(self, reason: str) -> None:
        await self.ws.close(1008, reason[:120])

    def stats(self) -> dict:
        return {"user": self.user, "robot": self.robot, "interfaces": len(self.interfaces), "msgs_in": self.msgs_in,
                "msgs_out": self.msgs_out, "dropped": self.dropped, "errors": self.errors,
                "pending_binary": self.assembler.pending}
